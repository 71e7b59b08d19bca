//! Rule 4: a turn covers the demonstrators' share of the orientation error, no less and no
//! more (decision 0036).
//!
//! Prevents: a cloned actor's turn is a move of hundredths of a degree read off a tanh. Above
//! the entrance with a tilt just over the tolerance (0.016–0.024° against 0.0143°), the swift
//! cross-cell recipe's policy asked for turns of under 0.0005° at every step until the step
//! limit.

use super::actor_with_work::has_turn_to_make;
use super::{RuleContext, Shaped};
use crate::sim::Observation;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// `[rules.turned_as_demonstrated]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TurnedAsDemonstrated {
    pub enabled: bool,
    /// The shortest share of the orientation error that a demonstrator's turn covers:
    /// `expert` turns by 0.85–1 of it (a person's variability), by 0.9 of it below 0.2°.
    pub shortest_share: f64,
}

impl Default for TurnedAsDemonstrated {
    fn default() -> Self {
        TurnedAsDemonstrated {
            enabled: true,
            shortest_share: 0.85,
        }
    }
}

impl TurnedAsDemonstrated {
    pub(super) fn apply(&self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        if shaped.is_orientation() {
            shaped.action.rotation_deg = self.turned(
                context.observation,
                shaped.action.rotation_deg,
                context.step_limit_deg,
            );
        }
    }

    /// `rotation_deg` with every component made a turn towards level of at least
    /// [`Self::shortest_share`] of the error the estimate sees on that axis (O_x, O_y, O_z),
    /// up to `step_limit_deg`, and of at most the whole error. Only where there is a tilt or a
    /// roll to turn by the demonstrators' tolerances: elsewhere in the bore a chosen turn with
    /// nothing to turn stands for a hold while the estimate settles, and is left as it is.
    pub fn turned(
        &self,
        observation: &Observation,
        rotation_deg: Vector3<f64>,
        step_limit_deg: f64,
    ) -> Vector3<f64> {
        if !has_turn_to_make(observation, 1.0) {
            return rotation_deg;
        }
        Vector3::from_fn(|axis, _| {
            let error_deg = observation.state[9 + axis];
            let whole_deg = error_deg.abs();
            let shortest_deg = (whole_deg * self.shortest_share).min(step_limit_deg);
            (rotation_deg[axis] * error_deg.signum())
                .clamp(shortest_deg, whole_deg)
                .copysign(error_deg)
        })
    }
}
