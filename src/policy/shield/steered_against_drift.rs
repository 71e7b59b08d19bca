//! Rule 12: a learned policy's translation is steered against the sideways drift the cell's
//! state filter has learned of its robot, as `expert` steers its own (decision 0026).
//!
//! Prevents: the network says where {M} should go; a robot that drifts sideways as it moves
//! takes {M} elsewhere, and the next steps spend themselves correcting. The demonstrators the
//! policies learn from decide on the state alone and do not steer, so training runs without
//! this rule and it is added where a policy runs. A sideways part that another rule set to the
//! demonstrators' exact centring (rules 10, 11) is not steered.

use super::{RuleContext, Shaped};
use crate::policy::steered_against_drift;

pub(super) fn apply(context: &RuleContext<'_>, shaped: &mut Shaped) {
    if !shaped.exact_sideways {
        shaped.action.translation_mm = steered_against_drift(
            &context.observation.estimate.drift(),
            shaped.action.translation_mm,
        );
    }
}
