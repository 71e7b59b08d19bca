//! Rule 10: under a noisy camera a position move down the bore centres sideways exactly as the
//! demonstrators do, not steered against the learned drift (decision 0034).
//!
//! Prevents: at four times the camera's noise, a learned policy's own sideways part, steered,
//! ended more episodes on the step limit; on a quieter camera the steering is what lets the
//! long steps of a fast policy through whole, so the rule waits for the camera's learned noise.

use super::centred_as_demonstrated::demonstrators_centring_mm;
use super::{RuleContext, Shaped};
use crate::sim::Observation;
use serde::{Deserialize, Serialize};

/// The camera's point noise, as a multiple of its data sheet and as the cell learns it from its
/// fits' residuals, above which a learned policy moves down the bore as its demonstrators do:
/// midway between what the cell learns of a camera twice and four times as noisy as its data
/// sheet (over 200 episodes in the bore it read 0.90–1.08, 1.84–2.16 and 3.74–4.25 at one, two
/// and four times).
pub const NOISY_CAMERA_SCALE: f64 = 3.0;

/// How far past the bore's entrance (mm) the tip is when the descent under a noisy camera
/// starts to apply.
pub const DESCENT_AS_DEMONSTRATED_FROM_MM: f64 = 0.2;

/// `[rules.noisy_camera_descent]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoisyCameraDescent {
    pub enabled: bool,
    /// The learned noise scale above which the rule applies.
    pub noisy_camera_scale: f64,
    /// How far past the entrance (mm) the tip must be.
    pub from_mm: f64,
}

impl Default for NoisyCameraDescent {
    fn default() -> Self {
        NoisyCameraDescent {
            enabled: true,
            noisy_camera_scale: NOISY_CAMERA_SCALE,
            from_mm: DESCENT_AS_DEMONSTRATED_FROM_MM,
        }
    }
}

impl NoisyCameraDescent {
    pub(super) fn apply(&self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        if descends_under_noise(
            context.observation,
            shaped,
            self.noisy_camera_scale,
            self.from_mm,
        ) {
            let centring = demonstrators_centring_mm(context.observation, context.step_limit_mm);
            shaped.action.translation_mm.x = centring.x;
            shaped.action.translation_mm.y = centring.y;
            shaped.exact_sideways = true;
        }
    }
}

/// Whether `shaped` is a position move down the bore, the tip more than `from_mm` past the
/// entrance, with a camera noisier than `noisy_camera_scale` times its data sheet.
pub(super) fn descends_under_noise(
    observation: &Observation,
    shaped: &Shaped,
    noisy_camera_scale: f64,
    from_mm: f64,
) -> bool {
    shaped.is_position()
        && shaped.action.translation_mm.z < 0.0
        && observation.insertion_mm() > from_mm
        && observation.estimate.noise_scale() > noisy_camera_scale
}
