//! Rule 6: a sideways move towards the axis stops just past it (decisions 0019, 0023).
//!
//! Prevents: the demonstrators move sideways by at most the offset, so a cloned actor's longer
//! move is an error of the imitation: a policy 1–2 mm off the axis above the entrance crossed
//! it by about twice the offset each step and swung there until the step limit. A fixed
//! 0.05 mm allowance, ten times a deep cell's figure, let a cloned actor answer a 0.006 mm
//! offset with a 0.017 mm move into the wall margin, refused until 20 refusals ended the
//! episode (0023).

use super::{RuleContext, Shaped};
use crate::config::cell::CellShape;
use crate::sim::Observation;
use nalgebra::Vector3;

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    if shaped.is_position() {
        shaped.action.translation_mm =
            not_past_the_axis(context.observation, shaped.action.translation_mm);
    }
}

/// How far past the bore's axis a sideways move may carry the shoulder (mm): half the radial
/// clearance beside the supervisor's wall margin, 0.015 mm on the reference cell and 0.005 mm
/// on a Φ100 bore 100 mm deep with 0.03 mm of clearance. The demonstrators centre a point of
/// the engaged shaft, not the shoulder, and leave a tilt of at most half the cell's clearance
/// tilt; over the engaged length the two points then differ by at most this.
pub fn past_the_axis_mm(cell: &CellShape) -> f64 {
    (cell.clearance_beside_margin_mm() / 2.0).max(0.0)
}

/// `translation_mm` with each sideways component (x, y in {M}) that moves the shoulder towards
/// the bore's axis cut to the offset the estimate sees (P_x, P_y) plus [`past_the_axis_mm`].
pub fn not_past_the_axis(observation: &Observation, translation_mm: Vector3<f64>) -> Vector3<f64> {
    let mut cut = translation_mm;
    let past_mm = past_the_axis_mm(&observation.cell);
    for axis in 0..2 {
        // A move of +P_x carries the shoulder onto the axis (P is {F}'s origin in {M}).
        let offset_mm = observation.state[6 + axis];
        let towards = cut[axis] * offset_mm > 0.0;
        let widest_mm = offset_mm.abs() + past_mm;
        if towards && cut[axis].abs() > widest_mm {
            cut[axis] = widest_mm.copysign(cut[axis]);
        }
    }
    cut
}
