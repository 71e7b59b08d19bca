//! Rule 8: a turn in the bore pivots about the middle of the engaged shaft (decision 0025).
//!
//! Prevents: the demonstrators level the shaft above the bore and turn about the shoulder; a
//! policy that enters with a little tilt left and levels it 1 mm in swings its tip sideways by
//! the depth times the turn (0.025 mm for 0.024° on the reference cell). The supervisor refused
//! that turn for the wall margin 20 times in a row, ending the episode, and on a Φ100 bore
//! 100 mm deep such turns ended 13 of 4000 episodes.

use super::{RuleContext, Shaped};
use crate::geometry::Move;
use crate::policy::expert::tip_in_bore;
use crate::sim::Observation;
use nalgebra::Point3;

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    if shaped.is_orientation() {
        shaped.action = pivot_in_bore(context.observation, shaped.action);
    }
}

/// `step` with the translation that keeps the middle of the shaft's engaged length in place
/// once the tip is in the bore, so that a turn pivots there rather than about {M}'s origin at
/// the shoulder.
pub fn pivot_in_bore(observation: &Observation, step: Move) -> Move {
    let insertion_mm = observation.insertion_mm();
    if !tip_in_bore(insertion_mm) {
        return step;
    }
    let length_mm = observation.cell.bore_depth_mm;
    let engaged_mm = insertion_mm.clamp(0.0, length_mm);
    let engaged_middle = Point3::new(0.0, 0.0, -length_mm + engaged_mm / 2.0);
    let keep = engaged_middle - step.as_pose().rotation * engaged_middle;
    Move {
        translation_mm: step.translation_mm + keep,
        ..step
    }
}
