//! Training data from demonstrations: input normalisation and the labels each network learns.
//!
//! A recorded move Δ (mm or deg, by actor) is split the way the policy composes it
//! (docs/design.md §6: move = a · sigmoid(ω3) · step limit):
//! - the step-size label s = clamp(max|Δᵢ| / (0.9 · limit), s_min, 0.98), the target of
//!   sigmoid(ω3);
//! - the actor's label a = clamp(Δ / (s · limit), −0.95, 0.95), the target of its tanh output.
//!
//! The floor s_min decides which network carries the size of small moves. Below it the actor's
//! label is proportional to the move, a smooth function of the state that an MLP fits well;
//! above it the actor gives a direction and the selector the size. A lower floor makes the
//! selector size the fine moves, and a sigmoid output is not precise enough for that: the last
//! insertion step overshot and tilts of 0.02–0.04° were never corrected (docs/learning-reference.md:
//! success 0.135 with floors of 0.05 / 0.98, 0.374 with 0.2 / 0.2). The position
//! floor is 0.2 (1 mm); the orientation floor is 0.5 (0.45°), so that the selector gives every
//! tilt correction below 0.45° the same step size and the orientation actor sizes them all
//! (0.958 success in 50.9 steps against 0.935 in 58.1 with 0.2; docs/learning-reference.md).
//!
//! A hold (the expert's deliberate zero move, looking again before it goes in) is labelled with
//! the scale [`HOLD_SCALE`] and no direction: the selector learns to wait, the actors never see
//! it.
//!
//! The 0.9 keeps the labels off tanh's and the sigmoid's asymptotes, where a squared loss cannot
//! get to them; a full 5 mm step comes back as 0.95 · 0.98 · 5 = 4.66 mm, which the policy reads
//! as the full step (the shield's `full_step` rule). With the direction's limit at 0.98 and
//! the scale's at 0.995, the policy stalled on the approach and at the bottom (success 0.953 in
//! 64 steps against 0.988 in 48.7; docs/learning-reference.md).

use super::demos::{DemoEpisode, DemoStep};
use crate::policy::Actor;
use crate::policy::inputs::PolicyInputs;

/// Ceiling of the step-size label (the target of sigmoid(ω3)) behaviour cloning gives a move.
pub const MAX_SCALE_LABEL: f64 = 0.98;
/// Ceiling of each component of the direction label (the target of an actor's tanh output).
pub const MAX_DIRECTION_LABEL: f64 = 0.95;

/// Smallest scale label of a position move: moves below 0.2 · 0.9 · limit are the actor's to
/// size.
const MIN_POSITION_SCALE: f64 = 0.2;
/// Smallest scale label of an orientation move: tilts below 0.5 · 0.9 · limit are the actor's
/// to size.
const MIN_ORIENTATION_SCALE: f64 = 0.5;

/// Scale label of a hold: almost no move, whatever the actor's output.
pub const HOLD_SCALE: f64 = 0.002;

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

    /// Centres the relative pose on the goal (P = 0, O_x = O_y = 0) with fixed σ, keeping the
    /// fitted mean and σ of A1..A6 and O_z. Fitted over the demonstrations, the σ of P_x, P_y
    /// is millimetres and that of the tilt degrees, so the micrometre and hundredth-of-a-degree
    /// errors that decide insertion would be lost in the actors' first layer.
    /// Cell-relative inputs (`policy::inputs`) have the distance from seated in slot 0 and the
    /// depth below the entrance in slot 8: both are centred (on seated and on the entrance)
    /// with the depth's σ, the last step before seated and the first into the bore each as
    /// finely resolved as P_z is in the paper's state. Their sideways error in clearances
    /// (slots 4, 5) is centred with σ one clearance.
    pub fn goal_centred(mut self, scales: GoalScales, inputs: PolicyInputs) -> Self {
        let relative: &[(usize, f64)] = match inputs {
            PolicyInputs::Absolute => &[],
            PolicyInputs::CellRelative | PolicyInputs::CellScaled => {
                &[(0, scales.depth_mm), (4, 1.0), (5, 1.0)]
            }
        };
        let fixed = [
            (6, scales.lateral_mm),
            (7, scales.lateral_mm),
            (8, scales.depth_mm),
            (9, scales.tilt_deg),
            (10, scales.tilt_deg),
        ];
        for (i, std) in fixed.into_iter().chain(relative.iter().copied()) {
            self.mean[i] = 0.0;
            self.std[i] = std;
        }
        self
    }

    pub fn apply(&self, state: &[f64; 12]) -> [f32; 12] {
        std::array::from_fn(|i| ((state[i] - self.mean[i]) / self.std[i]) as f32)
    }
}

/// The σ of [`Normaliser::goal_centred`]: P_x, P_y (mm), P_z (mm), O_x, O_y (deg).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GoalScales {
    pub lateral_mm: f64,
    pub depth_mm: f64,
    pub tilt_deg: f64,
}

impl Default for GoalScales {
    /// The best of docs/learning-reference.md's experiments with the normaliser.
    fn default() -> Self {
        GoalScales {
            lateral_mm: 0.3,
            depth_mm: 5.0,
            tilt_deg: 0.03,
        }
    }
}

/// The step limits a policy is trained with (mm, deg), and the inputs that say in which unit
/// the orientation actor tilts (`PolicyInputs::move_in_units`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepLimits {
    pub position_mm: f64,
    pub orientation_deg: f64,
    pub inputs: PolicyInputs,
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
        Self::of_move(step.actor, &step.action, &step.state, limits)
    }

    /// The labels of a move `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg) made by `actor` where the
    /// policy reads `inputs`.
    pub fn of_move(
        actor: Actor,
        action: &[f64; 6],
        inputs: &[f64; 12],
        limits: &StepLimits,
    ) -> Self {
        let action = limits.inputs.move_in_units(inputs, *action);
        let (components, limit, floor) = match actor {
            Actor::Position => (&action[0..3], limits.position_mm, MIN_POSITION_SCALE),
            Actor::Orientation => (&action[3..6], limits.orientation_deg, MIN_ORIENTATION_SCALE),
        };
        let largest = components.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        if largest == 0.0 {
            return StepLabels {
                actor,
                scale: HOLD_SCALE,
                direction: [0.0; 3],
            };
        }
        let scale = (largest / (0.9 * limit)).clamp(floor, MAX_SCALE_LABEL);
        let direction = std::array::from_fn(|i| {
            (components[i] / (scale * limit)).clamp(-MAX_DIRECTION_LABEL, MAX_DIRECTION_LABEL)
        });
        StepLabels {
            actor,
            scale,
            direction,
        }
    }

    /// Whether the step is a hold (no move: no direction to learn).
    pub fn is_hold(&self) -> bool {
        self.direction == [0.0; 3]
    }

    /// The move the labels stand for where the policy reads `inputs` (what it does when it
    /// hits them exactly).
    pub fn to_action(&self, inputs: &[f64; 12], limits: &StepLimits) -> [f64; 6] {
        let mut action = [0.0; 6];
        let (offset, limit) = match self.actor {
            Actor::Position => (0, limits.position_mm),
            Actor::Orientation => (3, limits.orientation_deg),
        };
        for i in 0..3 {
            action[offset + i] = self.direction[i] * self.scale * limit;
        }
        limits.inputs.move_from_units(inputs, action)
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
        inputs: PolicyInputs::Absolute,
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
        let back = labels.to_action(&[0.0; 12], &LIMITS);
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
        // Orientation 0.72 deg: s = 0.72 / 0.9, a = 0.9.
        let orientation = StepLabels::of(
            &step(Actor::Orientation, [0.0, 0.0, 0.0, 0.0, 0.72, 0.0]),
            &LIMITS,
        );
        assert!((orientation.scale - 0.8).abs() < 1e-12);
        assert!((orientation.direction[1] - 0.9).abs() < 1e-12);
        assert!((orientation.to_action(&[0.0; 12], &LIMITS)[4] - 0.72).abs() < 1e-12);
        // Small moves: the scale stops at its floor (0.2 for position, 0.5 for orientation),
        // the actor is proportional.
        let fine = StepLabels::of(
            &step(Actor::Position, [0.01, -0.02, 0.0, 0.0, 0.0, 0.0]),
            &LIMITS,
        );
        assert_eq!(fine.scale, 0.2);
        assert!((fine.direction[1] + 0.02 / 1.0).abs() < 1e-12);
        let fine_tilt = StepLabels::of(
            &step(Actor::Orientation, [0.0, 0.0, 0.0, -0.03, 0.0, 0.0]),
            &LIMITS,
        );
        assert_eq!(fine_tilt.scale, 0.5);
        assert!((fine_tilt.direction[0] + 0.03 / 0.5).abs() < 1e-12);
        assert!(!fine_tilt.is_hold());
    }

    #[test]
    fn cell_scaled_labels_measure_the_tilt_in_the_cells_unit() {
        // On a cell whose tilt unit is 0.2, a 0.004° tilt about x is 0.02 units: the scale's
        // floor 0.5 and a = 0.02 / 0.5 = 0.04, five times its label in degrees. The roll and
        // the position moves keep their units, and the labels give back the move.
        let scaled = StepLimits {
            inputs: PolicyInputs::CellScaled,
            ..LIMITS
        };
        let mut tilt = step(Actor::Orientation, [0.0, 0.0, 0.0, -0.004, 0.0, 0.01]);
        tilt.state[3] = 0.2;
        let labels = StepLabels::of(&tilt, &scaled);
        assert_eq!(labels.scale, 0.5);
        assert!((labels.direction[0] + 0.04).abs() < 1e-12);
        assert!((labels.direction[2] - 0.02).abs() < 1e-12);
        let back = labels.to_action(&tilt.state, &scaled);
        for (a, b) in back.iter().zip(tilt.action) {
            assert!((a - b).abs() < 1e-12);
        }
        let in_degrees = StepLabels::of(&tilt, &LIMITS);
        assert!((in_degrees.direction[0] + 0.008).abs() < 1e-12);
        let mut shift = step(Actor::Position, [0.01, -0.02, 0.0, 0.0, 0.0, 0.0]);
        shift.state[3] = 0.2;
        assert_eq!(
            StepLabels::of(&shift, &scaled),
            StepLabels::of(&shift, &LIMITS)
        );
    }

    /// A full step survives the round trip through its labels: labelled off the asymptotes,
    /// the labels' move is read back as the full step.
    #[test]
    fn a_full_steps_labels_come_back_as_the_full_step() {
        use crate::policy::shield::{FULL_STEP_LABEL_SHARE, FullStep};
        use nalgebra::Vector3;
        assert_eq!(FULL_STEP_LABEL_SHARE, MAX_SCALE_LABEL * MAX_DIRECTION_LABEL);
        for action in [
            [0.0, 0.0, -5.0, 0.0, 0.0, 0.0],
            [5.0, -5.0, 0.0, 0.0, 0.0, 0.0],
        ] {
            let labels = StepLabels::of(&step(Actor::Position, action), &LIMITS);
            let back = labels.to_action(&[0.0; 12], &LIMITS);
            assert!(back[0..3].iter().all(|v| v.abs() < 4.7), "{back:?}");
            let read = FullStep::default().stretched(Vector3::new(back[0], back[1], back[2]), 5.0);
            assert!((read - Vector3::new(action[0], action[1], action[2])).norm() < 1e-9);
        }
    }

    #[test]
    fn a_hold_is_a_tiny_scale_and_no_direction() {
        let hold = StepLabels::of(&step(Actor::Position, [0.0; 6]), &LIMITS);
        assert!(hold.is_hold());
        assert_eq!(hold.scale, HOLD_SCALE);
        assert_eq!(hold.to_action(&[0.0; 12], &LIMITS), [0.0; 6]);
    }

    #[test]
    fn goal_centred_normaliser_fixes_the_relative_pose_and_keeps_the_rest() {
        let mut a = step(Actor::Position, [0.0; 6]);
        let mut b = a.clone();
        (a.state[0], b.state[0]) = (10.0, 14.0);
        (a.state[7], b.state[7]) = (-50.0, 30.0);
        let fitted = Normaliser::fit(&[DemoEpisode {
            steps: vec![a.clone(), b],
            succeeded: true,
        }]);
        let norm = fitted.goal_centred(GoalScales::default(), PolicyInputs::Absolute);
        assert_eq!((norm.mean[0], norm.std[0]), (12.0, 2.0), "A1 as fitted");
        assert_eq!((norm.mean[7], norm.std[7]), (0.0, 0.3));
        assert_eq!((norm.mean[8], norm.std[8]), (0.0, 5.0));
        assert_eq!((norm.mean[10], norm.std[10]), (0.0, 0.03));
        assert_eq!(norm.std[11], fitted.std[11], "O_z as fitted");
        // 30 µm of lateral error is 0.1 of an input unit.
        a.state[7] = 0.03;
        assert!((norm.apply(&a.state)[7] - 0.1).abs() < 1e-6);
        // Cell-relative inputs: slot 0 is the distance from seated, centred like slot 8.
        let relative = fitted.goal_centred(GoalScales::default(), PolicyInputs::CellRelative);
        assert_eq!((relative.mean[0], relative.std[0]), (0.0, 5.0));
        assert_eq!((relative.mean[8], relative.std[8]), (0.0, 5.0));
        assert_eq!((relative.mean[4], relative.std[5]), (0.0, 1.0));
        assert_eq!(
            relative.std[1..4],
            fitted.std[1..4],
            "the cell's numbers as fitted"
        );
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
