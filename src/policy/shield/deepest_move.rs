//! Rule 5: a position move goes no deeper than the seated depth the estimate sees, and no
//! deeper at all right after a move refused for a predicted contact (docs/learning-reference.md).
//!
//! Prevents: the demonstrators never go past the goal, so a cloned actor's answer there is
//! arbitrary: one that overshot its last step by a few tenths of a millimetre kept pushing
//! against the seat until the step limit. After a refusal, at the entrance a few hundredths of
//! a millimetre off sideways, the policy asks the refused move again up to the camera's noise,
//! and 20 refusals in a row fail the episode; holding the depth lets the sideways part through
//! (paper §2.2: the state is read again and the policy asks for a new move).

use super::{RuleContext, Shaped};
use crate::collision::supervisor::VetoReason;
use crate::sim::Observation;

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    if shaped.is_position() {
        let z = &mut shaped.action.translation_mm.z;
        *z = z.max(deepest_move_mm(context.observation));
    }
}

/// Whether the move after `last_veto` may not go deeper into the bore (Δz < 0 in {M}): after
/// a refusal for contact.
pub fn holds_depth_after(last_veto: Option<&VetoReason>) -> bool {
    last_veto.is_some_and(VetoReason::is_about_contact)
}

/// The deepest move along the axis (Δz, mm in {M}, negative is deeper) the position actor may
/// ask for now: never past the seated depth the estimate sees (P_z; from beyond it, a move
/// back), and no deeper at all after a refusal for contact ([`holds_depth_after`]).
pub fn deepest_move_mm(observation: &Observation) -> f64 {
    let to_goal_mm = observation.state[8];
    if holds_depth_after(observation.last_veto.as_ref()) {
        to_goal_mm.max(0.0)
    } else {
        to_goal_mm
    }
}
