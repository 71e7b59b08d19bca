//! Rule 1: the actor that acts is one the demonstrators would use in the state (decisions
//! 0024, 0033, 0035).
//!
//! Prevents: selectors that kept choosing the position actor at the entrance with a
//! 0.022–0.031° tilt or, seated, with the holes 0.05–0.12° off, and the orientation actor with
//! nothing to turn 11–15 mm off the axis above the bore, each until the step limit
//! (decision 0024); seated to within 0.05–0.2 mm with nothing left to turn, a selector that held
//! until the step limit (decision 0035). In the bore a tilt left there narrows the gap to the
//! wall along the whole engaged length: at four times the camera's noise, with 1.5 times the
//! tolerance in the bore too, the supervisor refused the moves down until more episodes ran out
//! of steps (decision 0033).

use crate::policy::Actor;
use crate::policy::expert::{ExpertTuning, tip_in_bore};
use crate::sim::Observation;
use serde::{Deserialize, Serialize};

/// How far short of the seated depth (mm, by the estimate) the tip is when the shaft counts
/// as being seated (the default of [`ActorWithWork::being_seated_within_mm`]).
pub const BEING_SEATED_WITHIN_MM: f64 = 1.0;

/// `[rules.actor_with_work]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ActorWithWork {
    pub enabled: bool,
    /// How far past the demonstrators' tolerance (a factor on the tilt and on the roll) the
    /// position actor may still act above the bore; in the bore it acts only within them.
    /// Above the bore the extra half saves a few turns on the reference cell.
    pub tolerance_factor_above_bore: f64,
    /// Within this much of the seated depth (mm) the shaft is being seated.
    pub being_seated_within_mm: f64,
}

impl Default for ActorWithWork {
    fn default() -> Self {
        ActorWithWork {
            enabled: true,
            tolerance_factor_above_bore: 1.5,
            being_seated_within_mm: BEING_SEATED_WITHIN_MM,
        }
    }
}

impl ActorWithWork {
    /// The actor that acts for the selector's choice `selected`: the choice, but for two states
    /// where the demonstrators never use the chosen actor.
    ///
    /// - The position actor, with a tilt or a roll of more than the demonstrators' tolerance on
    ///   this cell in the bore, or of more than [`Self::tolerance_factor_above_bore`] times it
    ///   above the bore: the orientation actor acts. A demonstrator turns first.
    /// - The orientation actor, with nothing to turn and the tip above the bore or the shaft
    ///   being seated: the position actor acts. A demonstrator moves. Elsewhere in the bore a
    ///   chosen turn with nothing to turn stands for a hold while the estimate settles.
    pub fn actor(&self, selected: Actor, observation: &Observation) -> Actor {
        let inside = tip_in_bore(observation.insertion_mm());
        let factor = if inside {
            1.0
        } else {
            self.tolerance_factor_above_bore
        };
        match selected {
            Actor::Position if has_turn_to_make(observation, factor) => Actor::Orientation,
            Actor::Orientation
                if !has_turn_to_make(observation, 1.0)
                    && (!inside || self.being_seated(observation)) =>
            {
                Actor::Position
            }
            actor => actor,
        }
    }

    /// Whether the tip is within [`Self::being_seated_within_mm`] of the seated depth the
    /// estimate sees, or past it (P_z is 0 seated, negative short of it).
    fn being_seated(&self, observation: &Observation) -> bool {
        -observation.state[8] < self.being_seated_within_mm
    }
}

/// Whether the estimate sees a tilt or a roll of more than `factor` times the demonstrators'
/// tolerance on this cell, with the tip where it is
/// ([`ExpertTuning::tilt_tolerance_deg_on`], the roll tolerance).
pub(super) fn has_turn_to_make(observation: &Observation, factor: f64) -> bool {
    let s = &observation.state;
    let demonstrators = ExpertTuning::default();
    let inside = tip_in_bore(observation.insertion_mm());
    let tilt_tolerance =
        demonstrators.tilt_tolerance_deg_on(observation.cell.clearance_tilt_deg(), inside);
    s[9].hypot(s[10]) > factor * tilt_tolerance
        || s[11].abs() > factor * demonstrators.roll_tolerance_deg
}
