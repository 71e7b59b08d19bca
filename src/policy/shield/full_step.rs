//! Rule 2: a position move at the top of the actor's range is the full step its labels stand
//! for (decision 0028).
//!
//! Prevents: behaviour cloning keeps its labels off tanh's and the sigmoid's asymptotes, so a
//! move at the step limit is labelled as 0.98 × 0.95 = 0.931 of it (4.66 mm of 5), and a policy
//! fitted to those labels gives 4.5–4.8 mm where its demonstrator took 5: on the reference cell
//! `hierarchical-swift` took 1.1 steps more per episode than with this rule.

use super::{RuleContext, Shaped};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// From this share of the step limit up, a position move is read as the start of a full step
/// (the default of [`FullStep::from_share`]).
pub const FULL_STEP_FROM: f64 = 0.85;

/// The share of the step limit that behaviour cloning's labels of a full step give back: its
/// ceilings on the step-size and the direction labels, 0.98 × 0.95 (`learning::dataset`, whose
/// tests hold the two equal).
pub const FULL_STEP_LABEL_SHARE: f64 = 0.98 * 0.95;

/// `[rules.full_step]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FullStep {
    pub enabled: bool,
    /// From this share of the step limit up, a position move is read as the start of a full
    /// step (below the labels' ceiling, 0.931).
    pub from_share: f64,
}

impl Default for FullStep {
    fn default() -> Self {
        FullStep {
            enabled: true,
            from_share: FULL_STEP_FROM,
        }
    }
}

impl FullStep {
    pub(super) fn apply(&self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        if shaped.is_position() {
            shaped.action.translation_mm =
                self.stretched(shaped.action.translation_mm, context.step_limit_mm);
        }
    }

    /// `translation_mm` with its largest component stretched from [`Self::from_share`] of
    /// `step_limit_mm` up so that the labels of a full step give the limit: between
    /// `from_share` and 0.931 of the limit the largest component maps linearly onto the rest
    /// of the way to the limit, with the direction kept; shorter moves, which the labels carry
    /// exactly, are left as they are.
    pub fn stretched(&self, translation_mm: Vector3<f64>, step_limit_mm: f64) -> Vector3<f64> {
        let largest_mm = translation_mm.amax();
        let from_mm = self.from_share * step_limit_mm;
        let label_mm = FULL_STEP_LABEL_SHARE * step_limit_mm;
        if largest_mm <= from_mm {
            return translation_mm;
        }
        let stretched_mm = (from_mm
            + (largest_mm - from_mm) * (step_limit_mm - from_mm) / (label_mm - from_mm))
            .min(step_limit_mm);
        (translation_mm * (stretched_mm / largest_mm))
            .map(|v| v.clamp(-step_limit_mm, step_limit_mm))
    }
}
