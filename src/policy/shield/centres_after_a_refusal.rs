//! Rule 11: the position move right after a move refused for a predicted contact centres
//! sideways exactly as the demonstrators do, not steered against the learned drift (decision
//! 0035).
//!
//! Prevents: a cloned actor's sideways part is the small part of a move that is mostly along
//! the axis, and after a refusal (which holds the depth, rule 5) it is all there is. On a deep,
//! tight bore it went away from the axis the demonstrators centre: in the bore it narrowed the
//! gap to the wall, the supervisor refused it for the wall margin and the policy asked the same
//! again until 20 refusals ended the episode; at the entrance, refused for the wall, it went
//! 0.1 mm further off and hovered there until the step limit.

use super::centred_as_demonstrated::demonstrators_centring_mm;
use super::deepest_move::holds_depth_after;
use super::{RuleContext, Shaped};

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    let observation = context.observation;
    if shaped.is_position() && holds_depth_after(observation.last_veto.as_ref()) {
        let centring = demonstrators_centring_mm(observation, context.step_limit_mm);
        shaped.action.translation_mm.x = centring.x;
        shaped.action.translation_mm.y = centring.y;
        shaped.exact_sideways = true;
    }
}
