//! Rule 7: a turn stops at level, and never turns away from it (decision 0022).
//!
//! Prevents: the demonstrators turn by the error times a factor of at most 1, so a cloned
//! actor's longer or opposite turn is an error of the imitation: a policy 11 mm off the axis
//! above the entrance answered a 0.026° tilt with 0.06° each way and swung there until the
//! step limit.

use super::{RuleContext, Shaped};
use crate::sim::Observation;
use nalgebra::Vector3;

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    if shaped.is_orientation() {
        shaped.action.rotation_deg =
            not_past_level(context.observation, shaped.action.rotation_deg);
    }
}

/// `rotation_deg` with each component (θx, θy, θz in {M}) kept between zero and the
/// orientation error the estimate sees (O_x, O_y, O_z): a tilting move never carries the shaft
/// past level, nor the holes past their line, and never turns away from them.
pub fn not_past_level(observation: &Observation, rotation_deg: Vector3<f64>) -> Vector3<f64> {
    Vector3::from_fn(|axis, _| {
        let error_deg = observation.state[9 + axis];
        rotation_deg[axis].clamp(error_deg.min(0.0), error_deg.max(0.0))
    })
}
