//! Policy files (DESIGN.md §6): one safetensors file, f32, with the names PyTorch's `state_dict`
//! writes, and `__metadata__` carrying the format, its version and the step limits the policy was
//! trained with.
//!
//! [`PolicyFile::from_bytes`] checks everything before anything uses the data — the header length
//! against the file length, the header itself, the metadata, every tensor's name, dtype, shape and
//! values — and refuses a bad file with a [`PolicyFileError`] that names the tensor or metadata key
//! and says why. [`PolicyFile::new`] applies the same checks to tensors built in memory (training),
//! and [`PolicyFile::to_bytes`] / [`PolicyFile::save`] write a file that loads back as is.
//!
//! The checks that do not depend on the network (the container, the metadata, names, dtypes,
//! values) are shared with the flat TD3 baseline's file ([`super::flat::FlatPolicyFile`]), which
//! differs only in its `format`, its tensors and their shapes ([`PolicyKind`]).

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// `__metadata__["format"]` of every hierarchical policy file.
pub const FORMAT: &str = "assembly-cell/hierarchical-policy";
/// `__metadata__["format_version"]` this build reads and writes (both kinds of policy file).
pub const FORMAT_VERSION: &str = "1";
/// Size of the state the policy reads (DESIGN.md §5).
pub const STATE_DIM: usize = 12;
/// Outputs of the high-level head: ω1, ω2, ω3.
pub const HEAD_DIM: usize = 3;
/// Outputs of each actor.
pub const ACTOR_DIM: usize = 3;

/// Every tensor of a policy file, in the order the file is checked and written.
pub const TENSOR_NAMES: [&str; 20] = [
    "high.lstm.weight_ih_l0",
    "high.lstm.weight_hh_l0",
    "high.lstm.bias_ih_l0",
    "high.lstm.bias_hh_l0",
    "high.head.weight",
    "high.head.bias",
    "pos.0.weight",
    "pos.0.bias",
    "pos.2.weight",
    "pos.2.bias",
    "pos.4.weight",
    "pos.4.bias",
    "ori.0.weight",
    "ori.0.bias",
    "ori.2.weight",
    "ori.2.bias",
    "ori.4.weight",
    "ori.4.bias",
    "obs_mean",
    "obs_std",
];

/// Metadata keys every policy file carries.
pub const METADATA_KEYS: [&str; 4] = [
    "format",
    "format_version",
    "step_limit_mm",
    "step_limit_deg",
];

/// Which learned policy a file holds, by its `__metadata__["format"]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PolicyKind {
    /// DESIGN.md §6: the LSTM selector and two 3-value actors ([`FORMAT`]).
    Hierarchical,
    /// The flat TD3 baseline: one 6-value actor ([`super::flat::FORMAT`]).
    Flat,
}

impl PolicyKind {
    /// Its `__metadata__["format"]`.
    pub fn format(self) -> &'static str {
        match self {
            PolicyKind::Hierarchical => FORMAT,
            PolicyKind::Flat => super::flat::FORMAT,
        }
    }

    /// Its tensors, in the order a file is checked and written.
    pub fn tensor_names(self) -> &'static [&'static str] {
        match self {
            PolicyKind::Hierarchical => &TENSOR_NAMES,
            PolicyKind::Flat => &super::flat::TENSOR_NAMES,
        }
    }

    /// The kind a file declares: flat when its `format` metadata is the flat policy's,
    /// hierarchical otherwise — so any other file, unreadable ones included, is checked (and
    /// refused) as a hierarchical policy file, with that loader's messages.
    pub fn declared_by(bytes: &[u8]) -> PolicyKind {
        match parse(bytes) {
            Ok((meta, _))
                if meta.get("format").map(String::as_str) == Some(super::flat::FORMAT) =>
            {
                PolicyKind::Flat
            }
            _ => PolicyKind::Hierarchical,
        }
    }
}

impl std::fmt::Display for PolicyKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PolicyKind::Hierarchical => "hierarchical",
            PolicyKind::Flat => "flat",
        })
    }
}

/// Why a policy file was refused. Each variant names the tensor or metadata key at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolicyFileError {
    #[error("cannot read policy file {path}: {reason}")]
    Io { path: String, reason: String },
    #[error("policy file is truncated: {reason}")]
    Truncated { reason: String },
    #[error(
        "policy file header is longer than the file: the 8-byte prefix gives a header of {header_len} bytes but only {available} bytes follow it"
    )]
    HeaderTooLong { header_len: u64, available: u64 },
    #[error("policy file header is not valid safetensors: {reason}")]
    BadHeader { reason: String },
    #[error("tensor `{name}` is missing: a {kind} policy needs all of {}", kind.tensor_names().join(", "))]
    MissingTensor { name: String, kind: PolicyKind },
    #[error("tensor `{name}` {reason}")]
    UnexpectedTensor { name: String, reason: String },
    #[error("tensor `{name}` is {found}, expected F32")]
    WrongDtype { name: String, found: String },
    #[error("tensor `{name}` has shape {found:?}, expected {expected}")]
    WrongShape {
        name: String,
        found: Vec<usize>,
        expected: String,
    },
    #[error(
        "tensor `{name}` has a non-finite value {value} at index {index:?} (flat index {flat})"
    )]
    NonFinite {
        name: String,
        index: Vec<usize>,
        flat: usize,
        value: f32,
    },
    #[error("tensor `{name}` has the value {value} at index {index:?}: {reason}")]
    BadValue {
        name: String,
        index: Vec<usize>,
        value: f32,
        reason: String,
    },
    #[error("metadata `{key}` is missing (expected {expected})")]
    MissingMetadata { key: String, expected: String },
    #[error("metadata `{key}` is {value}: {reason}")]
    BadMetadata {
        key: String,
        value: String,
        reason: String,
    },
}

impl PolicyFileError {
    /// A short stable identifier of the kind of error (for APIs and tests).
    pub fn code(&self) -> &'static str {
        match self {
            PolicyFileError::Io { .. } => "io",
            PolicyFileError::Truncated { .. } => "truncated",
            PolicyFileError::HeaderTooLong { .. } => "header_too_long",
            PolicyFileError::BadHeader { .. } => "bad_header",
            PolicyFileError::MissingTensor { .. } => "missing_tensor",
            PolicyFileError::UnexpectedTensor { .. } => "unexpected_tensor",
            PolicyFileError::WrongDtype { .. } => "wrong_dtype",
            PolicyFileError::WrongShape { .. } => "wrong_shape",
            PolicyFileError::NonFinite { .. } => "non_finite",
            PolicyFileError::BadValue { .. } => "bad_value",
            PolicyFileError::MissingMetadata { .. } => "missing_metadata",
            PolicyFileError::BadMetadata { .. } => "bad_metadata",
        }
    }

    /// The tensor or metadata key the error is about, when there is one.
    pub fn subject(&self) -> Option<&str> {
        match self {
            PolicyFileError::MissingTensor { name, .. }
            | PolicyFileError::UnexpectedTensor { name, .. }
            | PolicyFileError::WrongDtype { name, .. }
            | PolicyFileError::WrongShape { name, .. }
            | PolicyFileError::NonFinite { name, .. }
            | PolicyFileError::BadValue { name, .. } => Some(name),
            PolicyFileError::MissingMetadata { key, .. }
            | PolicyFileError::BadMetadata { key, .. } => Some(key),
            _ => None,
        }
    }
}

/// The checked metadata of a policy file.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyMetadata {
    pub format: String,
    pub format_version: String,
    /// Step limit the position actor's output is scaled by (mm).
    pub step_limit_mm: f64,
    /// Step limit the orientation actor's output is scaled by (deg).
    pub step_limit_deg: f64,
    /// Every other string of `__metadata__` (e.g. training provenance), kept as is.
    pub extra: BTreeMap<String, String>,
}

/// One f32 tensor of a policy file, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyTensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// A checked policy file: every tensor of [`TENSOR_NAMES`] with consistent shapes and finite
/// values, and the metadata of DESIGN.md §6.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyFile {
    tensors: BTreeMap<String, PolicyTensor>,
    raw_metadata: BTreeMap<String, String>,
    metadata: PolicyMetadata,
    hidden_size: usize,
    actor_width: usize,
}

impl PolicyFile {
    /// Reads and checks a policy file.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self, PolicyFileError> {
        Self::from_bytes(&read_path(path.as_ref())?)
    }

    /// Parses and checks the bytes of a policy file.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyFileError> {
        Ok(Self::from_checked(check_bytes(
            bytes,
            PolicyKind::Hierarchical,
            check_shapes,
        )?))
    }

    /// A policy from tensors built in memory (name, shape, row-major values) and the metadata,
    /// checked exactly as a file is.
    pub fn new(
        tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
        metadata: BTreeMap<String, String>,
    ) -> Result<Self, PolicyFileError> {
        Ok(Self::from_checked(check_in_memory(
            tensors,
            metadata,
            PolicyKind::Hierarchical,
            check_shapes,
        )?))
    }

    fn from_checked(checked: Checked<(usize, usize)>) -> Self {
        let (hidden_size, actor_width) = checked.sizes;
        PolicyFile {
            tensors: checked.tensors,
            raw_metadata: checked.raw_metadata,
            metadata: checked.metadata,
            hidden_size,
            actor_width,
        }
    }

    /// The metadata a policy file needs (format, version, step limits); add any provenance keys
    /// to the returned map.
    pub fn standard_metadata(step_limit_mm: f64, step_limit_deg: f64) -> BTreeMap<String, String> {
        standard_metadata(PolicyKind::Hierarchical, step_limit_mm, step_limit_deg)
    }

    /// The bytes of a safetensors file holding this policy (deterministic: tensors in
    /// [`TENSOR_NAMES`] order, header keys sorted, header padded with spaces to 8 bytes).
    pub fn to_bytes(&self) -> Vec<u8> {
        encode(&self.raw_metadata, &TENSOR_NAMES, &self.tensors)
    }

    /// Writes [`PolicyFile::to_bytes`] to `path`.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), PolicyFileError> {
        write_path(path.as_ref(), &self.to_bytes())
    }

    /// The checked metadata.
    pub fn metadata(&self) -> &PolicyMetadata {
        &self.metadata
    }

    /// `__metadata__` exactly as stored (all keys, required and extra).
    pub fn raw_metadata(&self) -> &BTreeMap<String, String> {
        &self.raw_metadata
    }

    pub fn step_limit_mm(&self) -> f64 {
        self.metadata.step_limit_mm
    }

    pub fn step_limit_deg(&self) -> f64 {
        self.metadata.step_limit_deg
    }

    /// H: the LSTM's hidden size, from `high.lstm.weight_ih_l0` [4H, 12].
    pub fn hidden_size(&self) -> usize {
        self.hidden_size
    }

    /// D: the actors' hidden width, from `pos.0.weight` [D, 12].
    pub fn actor_width(&self) -> usize {
        self.actor_width
    }

    /// One tensor by name.
    pub fn tensor(&self, name: &str) -> Option<&PolicyTensor> {
        self.tensors.get(name)
    }

    /// Every tensor, in [`TENSOR_NAMES`] order.
    pub fn tensors(&self) -> impl Iterator<Item = (&'static str, &PolicyTensor)> {
        TENSOR_NAMES.iter().map(|&n| (n, &self.tensors[n]))
    }

    /// Name → shape of every tensor, in [`TENSOR_NAMES`] order.
    pub fn shapes(&self) -> Vec<(String, Vec<usize>)> {
        self.tensors()
            .map(|(n, t)| (n.to_string(), t.shape.clone()))
            .collect()
    }

    /// Total number of parameters.
    pub fn parameter_count(&self) -> usize {
        self.tensors.values().map(|t| t.data.len()).sum()
    }

    /// The tensors as candle tensors on `device`, by name.
    pub fn to_candle(
        &self,
        device: &candle_core::Device,
    ) -> candle_core::Result<HashMap<String, candle_core::Tensor>> {
        self.tensors()
            .map(|(n, t)| {
                let tensor = candle_core::Tensor::from_slice(&t.data, t.shape.as_slice(), device)?;
                Ok((n.to_string(), tensor))
            })
            .collect()
    }

    /// A candle `VarBuilder` (f32) over the tensors, for `HierarchicalPolicy::load`.
    pub fn var_builder(
        &self,
        device: &candle_core::Device,
    ) -> candle_core::Result<candle_nn::VarBuilder<'static>> {
        Ok(candle_nn::VarBuilder::from_tensors(
            self.to_candle(device)?,
            candle_core::DType::F32,
            device,
        ))
    }
}

// ---------------------------------------------------------------------------------------------
// checks shared by every kind of policy file

/// What the shared checks give: every tensor of the kind, the metadata, and what the kind's
/// shape check read from the shapes (its sizes).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Checked<S> {
    pub tensors: BTreeMap<String, PolicyTensor>,
    pub raw_metadata: BTreeMap<String, String>,
    pub metadata: PolicyMetadata,
    pub sizes: S,
}

/// A kind's shape check: every shape against the others; returns the sizes read from them.
pub(crate) type ShapeCheck<S> = fn(&BTreeMap<&str, &[usize]>) -> Result<S, PolicyFileError>;

/// The bytes of the file at `path`.
pub(crate) fn read_path(path: &Path) -> Result<Vec<u8>, PolicyFileError> {
    std::fs::read(path).map_err(|e| PolicyFileError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// Writes `bytes` to `path`.
pub(crate) fn write_path(path: &Path, bytes: &[u8]) -> Result<(), PolicyFileError> {
    std::fs::write(path, bytes).map_err(|e| PolicyFileError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// The container (steps 1–3 of a check): the header length against the file length, the header,
/// the data layout. Returns `__metadata__` and the tensors' views.
fn parse(
    bytes: &[u8],
) -> Result<(BTreeMap<String, String>, safetensors::SafeTensors<'_>), PolicyFileError> {
    // 1. The 8-byte header length against the file length.
    let len = bytes.len();
    if len < 8 {
        return Err(PolicyFileError::Truncated {
            reason: format!("the file is {len} bytes, too short for the 8-byte header length"),
        });
    }
    let header_len = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
    let available = (len - 8) as u64;
    if header_len > available {
        return Err(PolicyFileError::HeaderTooLong {
            header_len,
            available,
        });
    }
    let header_end = 8 + header_len as usize;
    let data_available = len - header_end;

    // 2. The header: UTF-8 JSON object; metadata values strings; data within the file.
    let header = std::str::from_utf8(&bytes[8..header_end])
        .map_err(|e| bad_header(format!("the header is not UTF-8: {e}")))?;
    let header: serde_json::Map<String, serde_json::Value> = serde_json::from_str(header)
        .map_err(|e| bad_header(format!("the header is not a JSON object: {e}")))?;
    let mut raw_metadata = BTreeMap::new();
    if let Some(meta) = header.get("__metadata__") {
        let serde_json::Value::Object(meta) = meta else {
            return Err(bad_header(format!(
                "`__metadata__` must be an object of strings, found {meta}"
            )));
        };
        for (key, value) in meta {
            match value {
                serde_json::Value::String(s) => {
                    raw_metadata.insert(key.clone(), s.clone());
                }
                other => {
                    return Err(PolicyFileError::BadMetadata {
                        key: key.clone(),
                        value: other.to_string(),
                        reason: "safetensors metadata values must be JSON strings".into(),
                    });
                }
            }
        }
    }
    let mut ends: Vec<(&str, u64)> = header
        .iter()
        .filter(|(name, _)| name.as_str() != "__metadata__")
        .filter_map(|(name, info)| {
            let end = info.get("data_offsets")?.get(1)?.as_u64()?;
            Some((name.as_str(), end))
        })
        .collect();
    ends.sort_by_key(|&(name, end)| (end, name));
    if let Some(&(name, end)) = ends.iter().find(|&&(_, end)| end > data_available as u64) {
        let last = ends.last().map_or(end, |&(_, e)| e);
        return Err(PolicyFileError::Truncated {
            reason: format!(
                "the header places the data of tensor `{name}` up to byte {end} after the header, \
                 and all tensors need {last} bytes, but only {data_available} bytes follow the header"
            ),
        });
    }

    // 3. The rest of the structure (offsets contiguous, sizes match dtype × shape, no
    //    trailing bytes), as the safetensors crate checks it.
    let st = safetensors::SafeTensors::deserialize(bytes).map_err(|e| {
        bad_header(match e {
            safetensors::SafeTensorError::MetadataIncompleteBuffer => format!(
                "the tensors' data does not fill the file exactly ({data_available} bytes follow the header)"
            ),
            other => other.to_string(),
        })
    })?;
    Ok((raw_metadata, st))
}

/// Parses and checks the bytes of a policy file of `kind`: the container, then the metadata,
/// names, dtypes, shapes (by `shapes`) and values.
pub(crate) fn check_bytes<S>(
    bytes: &[u8],
    kind: PolicyKind,
    shapes: ShapeCheck<S>,
) -> Result<Checked<S>, PolicyFileError> {
    let (raw_metadata, st) = parse(bytes)?;
    // 4. Metadata, names, dtypes, shapes, values.
    let metadata = check_metadata(&raw_metadata, kind)?;
    let views: BTreeMap<String, safetensors::tensor::TensorView<'_>> =
        st.tensors().into_iter().collect();
    let names = kind.tensor_names();
    check_names(views.keys().map(String::as_str), kind)?;
    for &name in names {
        let view = &views[name];
        if view.dtype() != safetensors::Dtype::F32 {
            return Err(PolicyFileError::WrongDtype {
                name: name.to_string(),
                found: format!("{:?}", view.dtype()),
            });
        }
    }
    let shape_map: BTreeMap<&str, &[usize]> =
        views.iter().map(|(n, v)| (n.as_str(), v.shape())).collect();
    let sizes = shapes(&shape_map)?;
    let mut tensors = BTreeMap::new();
    for &name in names {
        let view = &views[name];
        let data: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        check_values(name, view.shape(), &data)?;
        tensors.insert(
            name.to_string(),
            PolicyTensor {
                shape: view.shape().to_vec(),
                data,
            },
        );
    }
    Ok(Checked {
        tensors,
        raw_metadata,
        metadata,
        sizes,
    })
}

/// Checks tensors built in memory (name, shape, row-major values) and their metadata as a file
/// of `kind` is checked.
pub(crate) fn check_in_memory<S>(
    tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
    metadata: BTreeMap<String, String>,
    kind: PolicyKind,
    shapes: ShapeCheck<S>,
) -> Result<Checked<S>, PolicyFileError> {
    let meta = check_metadata(&metadata, kind)?;
    let mut map: BTreeMap<String, PolicyTensor> = BTreeMap::new();
    for (name, shape, data) in tensors {
        if map.contains_key(&name) {
            return Err(PolicyFileError::UnexpectedTensor {
                name,
                reason: "appears twice".into(),
            });
        }
        map.insert(name, PolicyTensor { shape, data });
    }
    check_names(map.keys().map(String::as_str), kind)?;
    let names = kind.tensor_names();
    for &name in names {
        let t = &map[name];
        let needed = t.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if needed != Some(t.data.len()) {
            return Err(PolicyFileError::WrongShape {
                name: name.to_string(),
                found: t.shape.clone(),
                expected: format!("a shape with {} elements (the values given)", t.data.len()),
            });
        }
    }
    let shape_map: BTreeMap<&str, &[usize]> = map
        .iter()
        .map(|(n, t)| (n.as_str(), t.shape.as_slice()))
        .collect();
    let sizes = shapes(&shape_map)?;
    for &name in names {
        let t = &map[name];
        check_values(name, &t.shape, &t.data)?;
    }
    Ok(Checked {
        tensors: map,
        raw_metadata: metadata,
        metadata: meta,
        sizes,
    })
}

/// The metadata a policy file of `kind` needs (format, version, step limits).
pub(crate) fn standard_metadata(
    kind: PolicyKind,
    step_limit_mm: f64,
    step_limit_deg: f64,
) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("format".to_string(), kind.format().to_string()),
        ("format_version".to_string(), FORMAT_VERSION.to_string()),
        ("step_limit_mm".to_string(), format!("{step_limit_mm}")),
        ("step_limit_deg".to_string(), format!("{step_limit_deg}")),
    ])
}

/// The bytes of a safetensors file of `tensors` (all F32) in `names` order, with `metadata`
/// (deterministic: header keys sorted, header padded with spaces to 8 bytes).
pub(crate) fn encode(
    metadata: &BTreeMap<String, String>,
    names: &[&str],
    tensors: &BTreeMap<String, PolicyTensor>,
) -> Vec<u8> {
    let mut header = serde_json::Map::new();
    header.insert(
        "__metadata__".to_string(),
        serde_json::Value::Object(
            metadata
                .iter()
                .map(|(k, v)| (k.clone(), serde_json::Value::String(v.clone())))
                .collect(),
        ),
    );
    let mut offset = 0usize;
    for &name in names {
        let t = &tensors[name];
        let end = offset + 4 * t.data.len();
        header.insert(
            name.to_string(),
            serde_json::json!({"dtype": "F32", "shape": t.shape, "data_offsets": [offset, end]}),
        );
        offset = end;
    }
    let mut header = serde_json::to_vec(&serde_json::Value::Object(header))
        .expect("a JSON map of strings and numbers serialises");
    header.resize(header.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + header.len() + offset);
    out.extend_from_slice(&(header.len() as u64).to_le_bytes());
    out.extend_from_slice(&header);
    for &name in names {
        for v in &tensors[name].data {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

fn bad_header(reason: String) -> PolicyFileError {
    PolicyFileError::BadHeader { reason }
}

fn check_metadata(
    raw: &BTreeMap<String, String>,
    kind: PolicyKind,
) -> Result<PolicyMetadata, PolicyFileError> {
    let get = |key: &str, expected: &str| {
        raw.get(key)
            .ok_or_else(|| PolicyFileError::MissingMetadata {
                key: key.to_string(),
                expected: expected.to_string(),
            })
    };
    let expected_format = kind.format();
    let format = get("format", &format!("{expected_format:?}"))?;
    if format != expected_format {
        return Err(PolicyFileError::BadMetadata {
            key: "format".into(),
            value: format!("{format:?}"),
            reason: format!("expected {expected_format:?}"),
        });
    }
    let version = get("format_version", &format!("{FORMAT_VERSION:?}"))?;
    if version != FORMAT_VERSION {
        return Err(PolicyFileError::BadMetadata {
            key: "format_version".into(),
            value: format!("{version:?}"),
            reason: format!("this build reads format_version {FORMAT_VERSION:?} only"),
        });
    }
    let limit = |key: &str, unit: &str| -> Result<f64, PolicyFileError> {
        let text = get(key, &format!("a positive number of {unit}, as a string"))?;
        let bad = |reason: &str| PolicyFileError::BadMetadata {
            key: key.to_string(),
            value: format!("{text:?}"),
            reason: reason.to_string(),
        };
        let value: f64 = text
            .trim()
            .parse()
            .map_err(|_| bad(&format!("expected a number of {unit}")))?;
        if !value.is_finite() || value <= 0.0 {
            return Err(bad(&format!("expected a finite positive number of {unit}")));
        }
        Ok(value)
    };
    let step_limit_mm = limit("step_limit_mm", "mm")?;
    let step_limit_deg = limit("step_limit_deg", "deg")?;
    let extra = raw
        .iter()
        .filter(|(k, _)| !METADATA_KEYS.contains(&k.as_str()))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    Ok(PolicyMetadata {
        format: format.clone(),
        format_version: version.clone(),
        step_limit_mm,
        step_limit_deg,
        extra,
    })
}

fn check_names<'a>(
    names: impl Iterator<Item = &'a str> + Clone,
    kind: PolicyKind,
) -> Result<(), PolicyFileError> {
    let required = kind.tensor_names();
    for &name in required {
        if !names.clone().any(|n| n == name) {
            return Err(PolicyFileError::MissingTensor {
                name: name.to_string(),
                kind,
            });
        }
    }
    let mut unknown: Vec<&str> = names.filter(|n| !required.contains(n)).collect();
    unknown.sort_unstable();
    if let Some(name) = unknown.first() {
        return Err(PolicyFileError::UnexpectedTensor {
            name: name.to_string(),
            reason: format!(
                "is not part of a {kind} policy (format_version {FORMAT_VERSION} has exactly: {})",
                required.join(", ")
            ),
        });
    }
    Ok(())
}

/// The error for tensor `name` of `shapes` not having the shape `expected` describes.
pub(crate) fn wrong_shape(
    shapes: &BTreeMap<&str, &[usize]>,
    name: &str,
    expected: String,
) -> PolicyFileError {
    PolicyFileError::WrongShape {
        name: name.to_string(),
        found: shapes[name].to_vec(),
        expected,
    }
}

/// Checks each (name, shape, why) against `shapes`, in order.
pub(crate) fn expect_shapes(
    shapes: &BTreeMap<&str, &[usize]>,
    expected: Vec<(&str, Vec<usize>, String)>,
) -> Result<(), PolicyFileError> {
    for (name, shape, why) in expected {
        if shapes[name] != shape.as_slice() {
            return Err(wrong_shape(shapes, name, format!("{shape:?} ({why})")));
        }
    }
    Ok(())
}

/// Checks every shape of a hierarchical policy; returns (H, D).
fn check_shapes(shapes: &BTreeMap<&str, &[usize]>) -> Result<(usize, usize), PolicyFileError> {
    let wrong = |name: &str, expected: String| wrong_shape(shapes, name, expected);
    let w_ih = shapes["high.lstm.weight_ih_l0"];
    let hidden = match *w_ih {
        [four_h, STATE_DIM] if four_h > 0 && four_h % 4 == 0 => four_h / 4,
        _ => {
            return Err(wrong(
                "high.lstm.weight_ih_l0",
                format!("[4H, {STATE_DIM}] with H ≥ 1 (PyTorch's LSTM input weights)"),
            ));
        }
    };
    let d0 = shapes["pos.0.weight"];
    let width = match *d0 {
        [d, STATE_DIM] if d > 0 => d,
        _ => {
            return Err(wrong(
                "pos.0.weight",
                format!("[D, {STATE_DIM}] with D ≥ 1 (the position actor's first layer)"),
            ));
        }
    };
    let (h, d) = (hidden, width);
    let from_h = format!("with H = {h} from high.lstm.weight_ih_l0");
    let from_d = format!("with D = {d} from pos.0.weight");
    let mut expected: Vec<(&str, Vec<usize>, String)> = vec![
        (
            "high.lstm.weight_hh_l0",
            vec![4 * h, h],
            format!("4H×H {from_h}"),
        ),
        ("high.lstm.bias_ih_l0", vec![4 * h], format!("4H {from_h}")),
        ("high.lstm.bias_hh_l0", vec![4 * h], format!("4H {from_h}")),
        (
            "high.head.weight",
            vec![HEAD_DIM, h],
            format!("3×H {from_h}"),
        ),
        ("high.head.bias", vec![HEAD_DIM], "ω1, ω2, ω3".to_string()),
    ];
    for actor in ["pos", "ori"] {
        let layers: [(&str, Vec<usize>, String); 6] = [
            ("0.weight", vec![d, STATE_DIM], format!("D×12 {from_d}")),
            ("0.bias", vec![d], format!("D {from_d}")),
            ("2.weight", vec![d, d], format!("D×D {from_d}")),
            ("2.bias", vec![d], format!("D {from_d}")),
            ("4.weight", vec![ACTOR_DIM, d], format!("3×D {from_d}")),
            (
                "4.bias",
                vec![ACTOR_DIM],
                "the actor's 3 outputs".to_string(),
            ),
        ];
        for (suffix, shape, why) in layers {
            let name = TENSOR_NAMES
                .iter()
                .copied()
                .find(|n| n.strip_prefix(actor).and_then(|r| r.strip_prefix('.')) == Some(suffix))
                .expect("every actor layer is in TENSOR_NAMES");
            expected.push((name, shape, why));
        }
    }
    expected.push((
        "obs_mean",
        vec![STATE_DIM],
        "the 12 state means".to_string(),
    ));
    expected.push((
        "obs_std",
        vec![STATE_DIM],
        "the 12 state deviations".to_string(),
    ));
    expect_shapes(shapes, expected)?;
    Ok((hidden, width))
}

fn unflatten(mut flat: usize, shape: &[usize]) -> Vec<usize> {
    let mut index = vec![0; shape.len()];
    for (i, &dim) in shape.iter().enumerate().rev() {
        if dim > 0 {
            index[i] = flat % dim;
            flat /= dim;
        }
    }
    index
}

fn check_values(name: &str, shape: &[usize], data: &[f32]) -> Result<(), PolicyFileError> {
    if let Some((flat, &value)) = data.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(PolicyFileError::NonFinite {
            name: name.to_string(),
            index: unflatten(flat, shape),
            flat,
            value,
        });
    }
    if name != "obs_std" {
        return Ok(());
    }
    match data.iter().enumerate().find(|(_, v)| **v <= 0.0) {
        Some((flat, &value)) => Err(PolicyFileError::BadValue {
            name: name.to_string(),
            index: unflatten(flat, shape),
            value,
            reason: "the state's standard deviations must be positive".into(),
        }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny(h: usize, d: usize) -> Vec<(String, Vec<usize>, Vec<f32>)> {
        let shapes: Vec<(&str, Vec<usize>)> = vec![
            ("high.lstm.weight_ih_l0", vec![4 * h, 12]),
            ("high.lstm.weight_hh_l0", vec![4 * h, h]),
            ("high.lstm.bias_ih_l0", vec![4 * h]),
            ("high.lstm.bias_hh_l0", vec![4 * h]),
            ("high.head.weight", vec![3, h]),
            ("high.head.bias", vec![3]),
            ("pos.0.weight", vec![d, 12]),
            ("pos.0.bias", vec![d]),
            ("pos.2.weight", vec![d, d]),
            ("pos.2.bias", vec![d]),
            ("pos.4.weight", vec![3, d]),
            ("pos.4.bias", vec![3]),
            ("ori.0.weight", vec![d, 12]),
            ("ori.0.bias", vec![d]),
            ("ori.2.weight", vec![d, d]),
            ("ori.2.bias", vec![d]),
            ("ori.4.weight", vec![3, d]),
            ("ori.4.bias", vec![3]),
            ("obs_mean", vec![12]),
            ("obs_std", vec![12]),
        ];
        shapes
            .into_iter()
            .map(|(n, s)| {
                let len = s.iter().product::<usize>();
                let data = (0..len).map(|i| 0.5 + (i % 7) as f32 * 0.01).collect();
                (n.to_string(), s, data)
            })
            .collect()
    }

    #[test]
    fn round_trip_through_bytes() {
        let mut meta = PolicyFile::standard_metadata(5.0, 1.0);
        meta.insert("trained_on".into(), "phi170".into());
        let p = PolicyFile::new(tiny(4, 8), meta).unwrap();
        assert_eq!((p.hidden_size(), p.actor_width()), (4, 8));
        let bytes = p.to_bytes();
        // The safetensors crate reads our files too.
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        assert_eq!(st.len(), 20);
        let back = PolicyFile::from_bytes(&bytes).unwrap();
        assert_eq!(back, p);
        assert_eq!(back.metadata().extra["trained_on"], "phi170");
        assert_eq!(back.step_limit_mm(), 5.0);
        assert_eq!(back.to_bytes(), bytes);
    }

    #[test]
    fn new_refuses_like_the_loader() {
        let meta = PolicyFile::standard_metadata(5.0, 1.0);
        let mut t = tiny(4, 8);
        t[1].1 = vec![16, 3];
        t[1].2.truncate(48);
        let e = PolicyFile::new(t, meta.clone()).unwrap_err();
        assert_eq!(e.code(), "wrong_shape");
        assert!(e.to_string().contains("[16, 4]"), "{e}");

        let mut t = tiny(4, 8);
        t[19].2[3] = 0.0;
        let e = PolicyFile::new(t, meta.clone()).unwrap_err();
        assert_eq!(e.code(), "bad_value");

        let mut t = tiny(4, 8);
        t.push(("extra".into(), vec![1], vec![0.0]));
        let e = PolicyFile::new(t, meta.clone()).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("unexpected_tensor", Some("extra"))
        );

        let mut t = tiny(4, 8);
        t[7].2.pop();
        assert_eq!(PolicyFile::new(t, meta).unwrap_err().code(), "wrong_shape");

        let mut meta = PolicyFile::standard_metadata(5.0, 1.0);
        meta.insert("step_limit_deg".into(), "-1".into());
        let e = PolicyFile::new(tiny(4, 8), meta).unwrap_err();
        assert_eq!(
            (e.code(), e.subject()),
            ("bad_metadata", Some("step_limit_deg"))
        );
    }

    #[test]
    fn short_files() {
        assert_eq!(
            PolicyFile::from_bytes(&[1, 2, 3]).unwrap_err().code(),
            "truncated"
        );
        let mut b = 100u64.to_le_bytes().to_vec();
        b.extend_from_slice(b"{}");
        assert_eq!(
            PolicyFile::from_bytes(&b).unwrap_err().code(),
            "header_too_long"
        );
        let mut b = 2u64.to_le_bytes().to_vec();
        b.extend_from_slice(b"[]");
        assert_eq!(PolicyFile::from_bytes(&b).unwrap_err().code(), "bad_header");
    }

    #[test]
    fn unflatten_indices() {
        assert_eq!(unflatten(7, &[3, 4]), vec![1, 3]);
        assert_eq!(unflatten(5, &[12]), vec![5]);
    }
}
