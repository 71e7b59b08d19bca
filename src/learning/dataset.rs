//! Training data from demonstrations: input normalisation and the labels each network learns.
//!
//! A recorded move Δ (mm or deg, by actor) is split the way the policy composes it
//! (DESIGN.md §6: move = a · sigmoid(ω3) · step limit):
//! - the step-size label s = clamp(max|Δᵢ| / (0.9 · limit), s_min, 0.98), the target of
//!   sigmoid(ω3);
//! - the actor's label a = clamp(Δ / (s · limit), −0.95, 0.95), the target of its tanh output.
//!
//! The floor s_min decides which network carries the size of small moves. Below it the actor's
//! label is proportional to the move, a smooth function of the state that an MLP fits well;
//! above it the actor gives a direction and the selector the size. Orientation moves are short
//! (≤ 1 deg, proportional to the error), so their scale is held at 0.98 and the orientation
//! actor learns the whole move; position moves span 5 mm to microns, so their scale follows the
//! move down to 0.05 (0.25 mm), below which the position actor is proportional.
//!
//! The 0.9 keeps the labels off tanh's and the sigmoid's asymptotes, where a squared loss cannot
//! get to them; a full 5 mm step comes back as 0.95 · 0.98 · 5 = 4.66 mm.

use super::demos::{DemoEpisode, DemoStep};
use crate::policy::Actor;

/// Largest scale label.
const MAX_SCALE: f64 = 0.98;
/// Smallest position scale label: moves below 0.05 · 0.9 · limit are the actor's to size.
const MIN_POSITION_SCALE: f64 = 0.05;

/// Floor of the normalisation σ, so that a constant input does not divide by zero.
const MIN_STD: f64 = 1e-3;

/// Per-dimension mean and σ of the states, as stored in a policy file (`obs_mean`, `obs_std`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normaliser {
    pub mean: [f64; 12],
    pub std: [f64; 12],
}

impl Normaliser {
    /// From every state of the demonstrations.
    pub fn fit(episodes: &[DemoEpisode]) -> Self {
        let states: Vec<&[f64; 12]> = episodes
            .iter()
            .flat_map(|e| &e.steps)
            .map(|s| &s.state)
            .collect();
        let n = states.len().max(1) as f64;
        let mean: [f64; 12] = std::array::from_fn(|i| states.iter().map(|s| s[i]).sum::<f64>() / n);
        let std = std::array::from_fn(|i| {
            let variance = states.iter().map(|s| (s[i] - mean[i]).powi(2)).sum::<f64>() / n;
            variance.sqrt().max(MIN_STD)
        });
        Normaliser { mean, std }
    }

    pub fn apply(&self, state: &[f64; 12]) -> [f32; 12] {
        std::array::from_fn(|i| ((state[i] - self.mean[i]) / self.std[i]) as f32)
    }
}

/// The step limits a policy is trained with (mm, deg).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimits {
    pub position_mm: f64,
    pub orientation_deg: f64,
}

/// What the networks learn from one demonstrated step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLabels {
    pub actor: Actor,
    /// Target of sigmoid(ω3).
    pub scale: f64,
    /// Target of the acting actor's tanh output.
    pub direction: [f64; 3],
}

impl StepLabels {
    pub fn of(step: &DemoStep, limits: &StepLimits) -> Self {
        let (components, limit, min_scale) = match step.actor {
            Actor::Position => (&step.action[0..3], limits.position_mm, MIN_POSITION_SCALE),
            Actor::Orientation => (&step.action[3..6], limits.orientation_deg, MAX_SCALE),
        };
        let largest = components.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let scale = (largest / (0.9 * limit)).clamp(min_scale, MAX_SCALE);
        let direction =
            std::array::from_fn(|i| (components[i] / (scale * limit)).clamp(-0.95, 0.95));
        StepLabels {
            actor: step.actor,
            scale,
            direction,
        }
    }

    /// The move the labels stand for (what the policy does when it hits them exactly).
    pub fn to_action(&self, limits: &StepLimits) -> [f64; 6] {
        let mut action = [0.0; 6];
        let (offset, limit) = match self.actor {
            Actor::Position => (0, limits.position_mm),
            Actor::Orientation => (3, limits.orientation_deg),
        };
        for i in 0..3 {
            action[offset + i] = self.direction[i] * self.scale * limit;
        }
        action
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(actor: Actor, action: [f64; 6]) -> DemoStep {
        DemoStep {
            episode: 0,
            step: 0,
            state: [0.0; 12],
            action,
            actor,
            scale: 0.0,
        }
    }

    const LIMITS: StepLimits = StepLimits {
        position_mm: 5.0,
        orientation_deg: 1.0,
    };

    #[test]
    fn labels_recompose_the_move() {
        // A 2 mm / 1 mm / −0.5 mm move: s = 2 / 4.5, a = Δ / (s · 5): exact round trip.
        let labels = StepLabels::of(
            &step(Actor::Position, [2.0, 1.0, -0.5, 0.0, 0.0, 0.0]),
            &LIMITS,
        );
        assert!((labels.scale - 2.0 / 4.5).abs() < 1e-12);
        assert!((labels.direction[0] - 0.9).abs() < 1e-12);
        let back = labels.to_action(&LIMITS);
        for (a, b) in back.iter().zip([2.0, 1.0, -0.5, 0.0, 0.0, 0.0]) {
            assert!((a - b).abs() < 1e-12);
        }
        // A full step is kept off the asymptotes: 0.95 · 0.98 · 5 mm.
        let labels = StepLabels::of(
            &step(Actor::Position, [0.0, 0.0, -5.0, 0.0, 0.0, 0.0]),
            &LIMITS,
        );
        assert_eq!(labels.scale, 0.98);
        assert_eq!(labels.direction[2], -0.95);
        let orientation = StepLabels::of(
            &step(Actor::Orientation, [0.0, 0.0, 0.0, 0.0, 0.45, 0.0]),
            &LIMITS,
        );
        // Orientation: the scale is held, the actor carries the size (0.45 / 0.98).
        assert_eq!(orientation.scale, 0.98);
        assert!((orientation.direction[1] - 0.45 / 0.98).abs() < 1e-12);
        // A small position move: the scale stops at its floor, the actor is proportional.
        let fine = StepLabels::of(
            &step(Actor::Position, [0.01, -0.02, 0.0, 0.0, 0.0, 0.0]),
            &LIMITS,
        );
        assert_eq!(fine.scale, 0.05);
        assert!((fine.direction[1] + 0.02 / 0.25).abs() < 1e-12);
        assert!((orientation.to_action(&LIMITS)[4] - 0.45).abs() < 1e-12);
    }

    #[test]
    fn normaliser_centres_and_scales() {
        let mut a = step(Actor::Position, [0.0; 6]);
        let mut b = a.clone();
        a.state[6] = 1.0;
        b.state[6] = 3.0;
        let norm = Normaliser::fit(&[DemoEpisode {
            steps: vec![a.clone(), b],
            succeeded: true,
        }]);
        assert_eq!(norm.mean[6], 2.0);
        assert_eq!(norm.std[6], 1.0);
        assert_eq!(norm.std[0], MIN_STD);
        assert_eq!(norm.apply(&a.state)[6], -1.0);
    }
}
