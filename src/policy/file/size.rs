//! The size a policy file may have, by the numbers it holds: a job keeps its policy's
//! parameters in memory from when it is queued until it ends, and every decision reads them
//! all, so the width of an uploaded network is bounded by a setting
//! (`policies.max_parameters`). Read from the header alone, before any value is checked.

use super::PolicyFileError;
use super::checks::parse;

/// Refuses `bytes` whose tensors hold more than `max_parameters` numbers in all, naming the
/// largest tensor and its shape. Any file of either kind; what is not a readable safetensors
/// file is refused with the reason [`super::PolicyFile::from_bytes`] would give.
pub fn check_parameter_count(bytes: &[u8], max_parameters: usize) -> Result<(), PolicyFileError> {
    let (_, tensors) = parse(bytes)?;
    let mut total: usize = 0;
    let mut largest: Option<(String, Vec<usize>, usize)> = None;
    for (name, view) in tensors.tensors() {
        let count = view
            .shape()
            .iter()
            .try_fold(1_usize, |n, &d| n.checked_mul(d))
            .unwrap_or(usize::MAX);
        total = total.saturating_add(count);
        if largest.as_ref().is_none_or(|(_, _, most)| count > *most) {
            largest = Some((name, view.shape().to_vec(), count));
        }
    }
    match largest {
        Some((name, shape, _)) if total > max_parameters => {
            Err(PolicyFileError::TooManyParameters {
                parameters: total,
                limit: max_parameters,
                name,
                shape,
            })
        }
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bundled policies hold 30,561 (hierarchical) and 70,686 (flat TD3) numbers, counted
    /// by hand from their shapes; a limit one below refuses, naming the largest tensor.
    #[test]
    fn the_count_is_the_sum_of_the_shapes_and_the_largest_tensor_is_named() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("policies");
        let hierarchical = std::fs::read(dir.join("default.safetensors")).unwrap();
        // LSTM 4H×12, 4H×64, 2×4H; head 3×64+3; two actors 64×12+64, 64×64+64, 3×64+3; 2×12.
        let by_hand = 256 * 12
            + 256 * 64
            + 2 * 256
            + 3 * 64
            + 3
            + 2 * (64 * 12 + 64)
            + 2 * (64 * 64 + 64)
            + 2 * (3 * 64 + 3)
            + 2 * 12;
        assert_eq!(by_hand, 30_561);
        check_parameter_count(&hierarchical, by_hand).unwrap();
        let error = check_parameter_count(&hierarchical, by_hand - 1).unwrap_err();
        assert_eq!(error.code(), "too_many_parameters");
        assert_eq!(
            error.to_string(),
            "the policy holds 30561 parameters, more than policies.max_parameters = 30560 \
             (the largest tensor is `high.lstm.weight_hh_l0`, [256, 64])"
        );
        let flat = std::fs::read(dir.join("td3.safetensors")).unwrap();
        check_parameter_count(&flat, 70_686).unwrap();
        assert!(check_parameter_count(&flat, 70_685).is_err());
        // Not a policy file at all: the container's own refusal.
        let error = check_parameter_count(b"short", 10).unwrap_err();
        assert_eq!(error.code(), "truncated");
    }
}
