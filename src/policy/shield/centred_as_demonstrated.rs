//! Rule 3: a sideways move towards the axis covers the demonstrators' share of the offset, no
//! less and no more; on the approach a move goes neither away from the axis nor up (decisions
//! 0030, 0031, 0032).
//!
//! Prevents: a cloned actor's sideways move is the small part of a move that is mostly along
//! the axis, and it is off by about a hundredth of a millimetre. A policy centred to 0.01–0.02
//! mm where its demonstrator centres exactly, and its moves into the bore were refused or
//! shortened; on a loose, shallow cell one policy hovered 0.02 mm off the axis at the standoff,
//! moving sideways by 0.001 mm each way, until the step limit; on the approach the policy went
//! 3.9–4.5 mm sideways where its demonstrator goes the whole 5 mm. Past the centring move it
//! carried the engaged shaft across the axis and back (0030, 0031). On the approach the sideways
//! part of a 5 mm move down was off by about 1 % of the move, and the policy went up by up to
//! 0.7 mm between moves down (0032). At the standoff and in the bore, at four times the camera's
//! noise, a move partly away from the noisy estimate's axis is worth keeping: dropping it there
//! too ended 0.7 % more episodes (0032).

use super::{RuleContext, Shaped};
use crate::policy::expert::{ExpertTuning, engaged_middle_off_axis_mm};
use crate::sim::Observation;
use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// `[rules.centred_as_demonstrated]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CentredAsDemonstrated {
    pub enabled: bool,
    /// The shortest share of the offset to the axis that a demonstrator's sideways move
    /// covers: `expert` moves by 0.8 of it above the entrance within 0.5 mm of the axis, by
    /// all of it elsewhere.
    pub shortest_share: f64,
    /// The approach ends this many times the demonstrators' standoff (1 mm) above the
    /// entrance: half as much again, for the estimate's jitter there.
    pub approach_standoff_factor: f64,
}

impl Default for CentredAsDemonstrated {
    fn default() -> Self {
        CentredAsDemonstrated {
            enabled: true,
            shortest_share: 0.8,
            approach_standoff_factor: 1.5,
        }
    }
}

impl CentredAsDemonstrated {
    pub(super) fn apply(&self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        if shaped.is_position() {
            shaped.action.translation_mm = self.centred(
                context.observation,
                shaped.action.translation_mm,
                context.step_limit_mm,
            );
        }
    }

    /// Height of the tip above the bore's entrance (mm) above which a position move goes
    /// neither away from the axis nor up: 1.5 mm by default.
    pub fn approach_above_mm(&self) -> f64 {
        self.approach_standoff_factor * ExpertTuning::default().standoff_mm
    }

    /// `translation_mm` with each sideways component that moves towards the axis made at least
    /// [`Self::shortest_share`] of the demonstrators' centring move
    /// ([`demonstrators_centring_mm`]), up to `step_limit_mm`, and at most the whole centring
    /// move. On the approach, with the tip more than [`Self::approach_above_mm`] above the
    /// entrance, a component away from the axis and a move up are dropped, as no demonstrator
    /// makes them; lower down they are left as they are. A hold is left as it is.
    pub fn centred(
        &self,
        observation: &Observation,
        translation_mm: Vector3<f64>,
        step_limit_mm: f64,
    ) -> Vector3<f64> {
        let centring = demonstrators_centring_mm(observation, step_limit_mm);
        let approaching = observation.insertion_mm() < -self.approach_above_mm();
        let mut centred = translation_mm;
        for axis in 0..2 {
            let whole_mm = centring[axis].abs();
            let shortest_mm = (whole_mm * self.shortest_share).min(step_limit_mm);
            if centred[axis] * centring[axis] > 0.0 {
                // Towards the axis: between the shortest share and the whole move.
                centred[axis] = centred[axis]
                    .abs()
                    .clamp(shortest_mm, whole_mm)
                    .copysign(centring[axis]);
            } else if approaching {
                centred[axis] = 0.0;
            }
        }
        if approaching {
            centred.z = centred.z.min(0.0);
        }
        centred
    }
}

/// The demonstrators' centring move in the estimated state (x and y of {M}, mm): minus
/// [`engaged_middle_off_axis_mm`] for a step of `step_limit_mm`.
pub fn demonstrators_centring_mm(observation: &Observation, step_limit_mm: f64) -> Vector2<f64> {
    let s = &observation.state;
    -engaged_middle_off_axis_mm(
        Vector3::new(s[6], s[7], s[8]),
        Vector3::new(s[9], s[10], s[11]),
        observation.cell.bore_depth_mm,
        step_limit_mm,
    )
}
