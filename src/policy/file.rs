//! Policy files (docs/design.md §6): one safetensors file, f32, with the names PyTorch's `state_dict`
//! writes, and `__metadata__` carrying the format, its version and the step limits the policy was
//! trained with.
//!
//! [`PolicyFile::from_bytes`] checks everything before anything uses the data — the header length
//! against the file length, the header itself, the metadata, every tensor's name, dtype, shape and
//! values — and refuses a bad file with a [`PolicyFileError`] that names the tensor or metadata key
//! and says why. [`PolicyFile::new`] applies the same checks to tensors built in memory (training),
//! and [`PolicyFile::to_bytes`] / [`PolicyFile::save`] write a file that loads back as is.
//!
//! The checks that do not depend on the network (`file/checks.rs`: the container, the metadata,
//! names, dtypes, values) are shared with the flat TD3 baseline's file
//! ([`super::flat::FlatPolicyFile`]), which differs only in its `format`, its tensors and their
//! shapes ([`PolicyKind`]).

use super::inputs::PolicyInputs;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

mod checks;
mod size;
use checks::parse;
pub(crate) use checks::{
    Checked, check_bytes, check_in_memory, encode, expect_shapes, read_path, standard_metadata,
    write_path, wrong_shape,
};
pub use size::check_parameter_count;

/// `__metadata__["format"]` of every hierarchical policy file.
pub const FORMAT: &str = "assembly-cell/hierarchical-policy";
/// The newest `__metadata__["format_version"]` this build reads and writes (both kinds of
/// policy file): version 2 names its inputs (`super::inputs`); version 1, the paper's state,
/// still loads and runs.
pub const FORMAT_VERSION: &str = "2";
/// Size of the state the policy reads (docs/design.md §5).
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

/// `__metadata__["format"]` of a flat policy file (the flat TD3 baseline, `super::flat`).
pub const FLAT_FORMAT: &str = "assembly-cell/flat-policy";

/// Every tensor of a flat policy file, in the order the file is checked and written.
pub const FLAT_TENSOR_NAMES: [&str; 8] = [
    "actor.0.weight",
    "actor.0.bias",
    "actor.2.weight",
    "actor.2.bias",
    "actor.4.weight",
    "actor.4.bias",
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
    /// docs/design.md §6: the LSTM selector and two 3-value actors ([`FORMAT`]).
    Hierarchical,
    /// The flat TD3 baseline: one 6-value actor ([`FLAT_FORMAT`]).
    Flat,
}

impl PolicyKind {
    /// Its `__metadata__["format"]`.
    pub fn format(self) -> &'static str {
        match self {
            PolicyKind::Hierarchical => FORMAT,
            PolicyKind::Flat => FLAT_FORMAT,
        }
    }

    /// Its tensors, in the order a file is checked and written.
    pub fn tensor_names(self) -> &'static [&'static str] {
        match self {
            PolicyKind::Hierarchical => &TENSOR_NAMES,
            PolicyKind::Flat => &FLAT_TENSOR_NAMES,
        }
    }

    /// The kind a file declares: flat when its `format` metadata is the flat policy's,
    /// hierarchical otherwise — so any other file, unreadable ones included, is checked (and
    /// refused) as a hierarchical policy file, with that loader's messages.
    pub fn declared_by(bytes: &[u8]) -> PolicyKind {
        match parse(bytes) {
            Ok((meta, _)) if meta.get("format").map(String::as_str) == Some(FLAT_FORMAT) => {
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
    #[error(
        "the policy holds {parameters} parameters, more than policies.max_parameters = {limit} \
         (the largest tensor is `{name}`, {shape:?})"
    )]
    TooManyParameters {
        parameters: usize,
        limit: usize,
        name: String,
        shape: Vec<usize>,
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
            PolicyFileError::TooManyParameters { .. } => "too_many_parameters",
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
            | PolicyFileError::BadValue { name, .. }
            | PolicyFileError::TooManyParameters { name, .. } => Some(name),
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
    /// What the network reads (version 1: the paper's state).
    pub inputs: PolicyInputs,
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
/// values, and the metadata of docs/design.md §6.
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
        assert_eq!(back.metadata().inputs, PolicyInputs::Absolute);
        assert_eq!(back.metadata().format_version, "1");
    }

    #[test]
    fn a_policy_that_reads_the_cell_is_a_version_2_file_that_names_its_inputs() {
        for inputs in [PolicyInputs::CellRelative, PolicyInputs::CellScaled] {
            let mut meta = PolicyFile::standard_metadata(5.0, 1.0);
            inputs.mark(&mut meta);
            let p = PolicyFile::new(tiny(4, 8), meta).unwrap();
            let back = PolicyFile::from_bytes(&p.to_bytes()).unwrap();
            assert_eq!(back.metadata().format_version, "2");
            assert_eq!(back.metadata().inputs, inputs);
            assert!(!back.metadata().extra.contains_key("inputs"));
        }
        // A version 1 file with an `inputs` key reads the paper's state, as version 1 says.
        let mut meta = PolicyFile::standard_metadata(5.0, 1.0);
        meta.insert("inputs".into(), "cell-relative".into());
        let p = PolicyFile::new(tiny(4, 8), meta).unwrap();
        assert_eq!(p.metadata().inputs, PolicyInputs::Absolute);
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
}
