//! Rule 13: right after a move refused as uncertain, a move down the bore asks the full step
//! (decision 0040).
//!
//! The supervisor then tries shares of it down to a quarter, and a move down that no share of
//! is sure enough is made as its sideways part. Not after a refusal for the wall margin or a
//! predicted contact until a move is made: the full step's centring was refused for the wall in
//! turn with refusals as uncertain until 20 refusals ended the episode.
//!
//! Prevents: at twice the camera's noise the policies learnt from `expert-careful` asked moves
//! of about 2 mm there, refused as uncertain under a camera shift suspected by chance, and ended
//! episodes on the step limit; with the full step they fail about as often as `expert`.

use super::noisy_camera_descent::DESCENT_AS_DEMONSTRATED_FROM_MM;
use super::{RuleContext, Shaped};
use crate::collision::supervisor::VetoReason;
use crate::sim::Observation;
use serde::{Deserialize, Serialize};

/// How far short of the seat (mm, by the estimate) the full step still leaves the tip, by
/// default.
pub const FULL_STEP_ENDS_SHORT_OF_THE_SEAT_MM: f64 = 1.0;

/// `[rules.full_step_after_uncertainty]`, and what the rule remembers within an episode.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FullStepAfterUncertainty {
    pub enabled: bool,
    /// How far past the entrance (mm) the tip must be.
    pub from_mm: f64,
    /// How far short of the seat (mm) the full step must still leave the tip.
    pub ends_short_of_the_seat_mm: f64,
    /// A move was refused for the wall margin or a predicted contact and none made since.
    #[serde(skip)]
    pub(super) refused_near_the_wall: bool,
}

impl Default for FullStepAfterUncertainty {
    fn default() -> Self {
        FullStepAfterUncertainty {
            enabled: true,
            from_mm: DESCENT_AS_DEMONSTRATED_FROM_MM,
            ends_short_of_the_seat_mm: FULL_STEP_ENDS_SHORT_OF_THE_SEAT_MM,
            refused_near_the_wall: false,
        }
    }
}

impl FullStepAfterUncertainty {
    /// Called at every decision, whatever the move, so that it follows the refusals.
    pub(super) fn apply(&mut self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        let z = shaped.action.translation_mm.z;
        if self.step(context.observation, z, context.step_limit_mm) {
            shaped.action.translation_mm.z = -context.step_limit_mm;
        }
    }

    /// Whether the tip, `inserted_mm` past the entrance of a bore `depth_mm` deep, is where
    /// the rule asks the full step (`step_limit_mm`): more than [`Self::from_mm`] in, and more
    /// than the full step and [`Self::ends_short_of_the_seat_mm`] short of the seat.
    pub fn applies_at(&self, inserted_mm: f64, depth_mm: f64, step_limit_mm: f64) -> bool {
        let deepest_start_mm = depth_mm - step_limit_mm - self.ends_short_of_the_seat_mm;
        inserted_mm > self.from_mm && inserted_mm < deepest_start_mm
    }

    /// Whether the move down the bore asked now (`asked_z_mm`, negative is deeper) is made
    /// the full step (`step_limit_mm`) instead.
    pub fn step(&mut self, observation: &Observation, asked_z_mm: f64, step_limit_mm: f64) -> bool {
        match &observation.last_veto {
            Some(veto) if veto.is_about_contact() => self.refused_near_the_wall = true,
            None => self.refused_near_the_wall = false,
            Some(_) => {}
        }
        matches!(observation.last_veto, Some(VetoReason::Uncertain { .. }))
            && !self.refused_near_the_wall
            && asked_z_mm < 0.0
            && self.applies_at(
                observation.insertion_mm(),
                observation.cell.bore_depth_mm,
                step_limit_mm,
            )
    }
}
