//! The checks shared by every kind of policy file: the container (header length, header, data
//! layout), the metadata, the tensors' names, dtypes and values, and the encoding of a file.
//! Each kind adds its shape check ([`ShapeCheck`]).

use super::{
    FORMAT_VERSION, METADATA_KEYS, PolicyFileError, PolicyKind, PolicyMetadata, PolicyTensor,
};
use crate::policy::inputs::{INPUTS_KEY, PolicyInputs};
use std::collections::BTreeMap;
use std::path::Path;

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

/// Writes `bytes` to `path` (whole or not at all).
pub(crate) fn write_path(path: &Path, bytes: &[u8]) -> Result<(), PolicyFileError> {
    crate::files::write_atomically(path, bytes).map_err(|e| PolicyFileError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// The container (steps 1–3 of a check): the header length against the file length, the header,
/// the data layout. Returns `__metadata__` and the tensors' views.
pub(super) fn parse(
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
        (
            "format_version".to_string(),
            PolicyInputs::Absolute.format_version().to_string(),
        ),
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
    let version = get("format_version", "\"1\" or \"2\"")?;
    let inputs = match version.as_str() {
        "1" => PolicyInputs::Absolute,
        "2" => {
            let names = PolicyInputs::ALL.map(PolicyInputs::name).join(", ");
            let name = get(INPUTS_KEY, &format!("one of {names}"))?;
            PolicyInputs::parse(name).ok_or_else(|| PolicyFileError::BadMetadata {
                key: INPUTS_KEY.into(),
                value: format!("{name:?}"),
                reason: format!("expected one of {names}"),
            })?
        }
        _ => {
            return Err(PolicyFileError::BadMetadata {
                key: "format_version".into(),
                value: format!("{version:?}"),
                reason: format!(
                    "this build reads format_version \"1\" and \"2\" ({FORMAT_VERSION:?} with cell-relative or cell-scaled inputs)"
                ),
            });
        }
    };
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
        .filter(|(k, _)| !METADATA_KEYS.contains(&k.as_str()) && k.as_str() != INPUTS_KEY)
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    Ok(PolicyMetadata {
        format: format.clone(),
        format_version: version.clone(),
        inputs,
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
                "is not part of a {kind} policy (which has exactly: {})",
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
    use super::unflatten;

    #[test]
    fn unflatten_indices() {
        assert_eq!(unflatten(7, &[3, 4]), vec![1, 3]);
        assert_eq!(unflatten(5, &[12]), vec![5]);
    }
}
