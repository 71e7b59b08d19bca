//! The scripted knowledge-guided expert (docs/design.md §5): what a skilled operator does when guiding
//! Segment I by hand — orientation first, then lateral alignment above the entrance, then
//! insertion, with steps that shrink near the goal and a person's variability in step length.
//!
//! It stands in for the recorded human demonstrations in the twin. Each decision says which actor
//! (position or orientation) it used and its step scale, the labels the LSTM selector learns.

use super::{Actor, Controller, Decision, clamp_components, steered_against_drift};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::geometry::pose::pose_from_mm_deg;
use crate::sim::Observation;
use nalgebra::{Point3, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Height of the tip above the bore's entrance (mm) where the demonstrators finish the
/// sideways alignment before going in ([`ExpertTuning::standoff_mm`]'s default).
pub const STANDOFF_MM: f64 = 1.0;

/// Tuning of the expert; the defaults are what the tests and the bundled results use.
#[derive(Debug, Clone, Copy)]
pub struct ExpertTuning {
    /// Tilt (deg) above which the orientation is corrected before moving on, outside the bore.
    pub tilt_tolerance_deg: f64,
    /// Outside the bore and in it, the tilt is also corrected down to this share of the tilt
    /// at which the seated shaft would touch the wall margin (the radial clearance beside the
    /// margin over the bore's depth): a deep, tight bore takes less tilt than a shallow, loose
    /// one. On the reference cell that is 0.014°; on a Φ100 bore 100 mm deep with 0.03 mm
    /// clearance, 0.003°, where the fixed 0.02° left the seated shaft against the margin and
    /// `expert` succeeded 0.737 instead of 0.998 (decision 0019). In the bore, that cell's
    /// robot tilts the shaft by up to 0.015° with every step down; with only the fixed 0.05°
    /// there, `expert-careful` stuck against the margin or ran out of steps in 0.038 of its
    /// episodes, and 0.0065 with the share (decision 0021).
    pub tilt_clearance_share: f64,
    /// Tilt tolerated once the tip is in the bore, where a correction swings the tip, on a
    /// cell that takes more than twice it.
    pub tilt_tolerance_inside_deg: f64,
    /// Hole misalignment (deg about the axis) above which the roll is corrected.
    pub roll_tolerance_deg: f64,
    /// Lateral error (mm) below which insertion may start.
    pub lateral_tolerance_mm: f64,
    /// Height of the tip above the entrance where the lateral alignment is finished (mm).
    pub standoff_mm: f64,
    /// The lateral estimate's σ (mm) must be this small before insertion starts: a careful
    /// operator looks a few more times before committing.
    pub lateral_certainty_mm: f64,
    /// Longest insertion step: one after which the lateral estimate's σ (mm) stays below this.
    pub insertion_certainty_mm: f64,
    /// Height of the tip above the entrance down to which Segment I may come while it is still
    /// more than 1 mm off sideways (mm).
    pub prestandoff_mm: f64,
    /// Human variability: each step's length is scaled by a factor drawn from [this, 1]. It
    /// also shows a learner the states around the demonstrator's path: a policy learnt from
    /// `expert-careful` without it stalled near the bottom (docs/learning-reference.md).
    pub min_step_factor: f64,
    /// What decides that the shaft may go in, and how long the insertion steps are.
    pub insertion_gate: InsertionGate,
    /// Steer against the sideways drift the cell's state filter has learned (a filter
    /// quantity, not in the 12-value state).
    pub compensate_drift: bool,
}

/// When the expert commits to insertion, once aligned at the standoff.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InsertionGate {
    /// When the state filter's lateral σ is below `lateral_certainty_mm`; each insertion step
    /// is as long as the σ stays below `insertion_certainty_mm` over. Both are the filter's,
    /// not in the 12-value state a policy sees.
    FilterCertainty,
    /// After holding still for `holds` fresh frames at the standoff (once per episode), with
    /// insertion steps of at most `max_step_mm`, and of at most `careful_step_mm` while the
    /// shaft is less than `careful_depth_mm` in: a rule of the state and a count, which an LSTM
    /// policy can learn.
    Holds {
        holds: u32,
        max_step_mm: f64,
        careful_depth_mm: f64,
        careful_step_mm: f64,
    },
}

impl Default for ExpertTuning {
    fn default() -> Self {
        ExpertTuning {
            tilt_tolerance_deg: 0.02,
            tilt_clearance_share: 0.5,
            tilt_tolerance_inside_deg: 0.05,
            roll_tolerance_deg: 0.025,
            lateral_tolerance_mm: 0.012,
            standoff_mm: STANDOFF_MM,
            prestandoff_mm: 20.0,
            lateral_certainty_mm: 0.009,
            insertion_certainty_mm: 0.013,
            min_step_factor: 0.85,
            insertion_gate: InsertionGate::FilterCertainty,
            compensate_drift: true,
        }
    }
}

impl ExpertTuning {
    /// The tilt (deg) above which the expert turns before it moves, on a cell whose clearance
    /// tilt is `clearance_tilt_deg`, with the tip in the bore (`inside`) or above it.
    pub fn tilt_tolerance_deg_on(&self, clearance_tilt_deg: f64, inside: bool) -> f64 {
        let fixed = if inside {
            self.tilt_tolerance_inside_deg
        } else {
            self.tilt_tolerance_deg
        };
        fixed.min(self.tilt_clearance_share * clearance_tilt_deg)
    }

    /// The demonstrator `celld train` records by default (`expert-state-only`): it decides
    /// on the 12-value state and a count of holds alone: 5 holds at the standoff, insertion
    /// steps of at most 3 mm, no drift compensation. On the Table 5 protocol it is as good as
    /// the default expert (docs/learning-reference.md).
    pub fn state_only() -> Self {
        ExpertTuning {
            insertion_gate: InsertionGate::Holds {
                holds: 5,
                max_step_mm: 3.0,
                careful_depth_mm: 0.0,
                careful_step_mm: 3.0,
            },
            compensate_drift: false,
            ..ExpertTuning::default()
        }
    }

    /// `expert-careful`: the state-only expert with 3 holds at the standoff and insertion steps
    /// of at most 2 mm over the first 35 mm, 5 mm after. The filter learns the sideways drift
    /// per mm of insertion from the insertion itself, so a long step early in the bore carries
    /// a lateral error the clearance cannot take; the `expert` shortens those steps by the
    /// filter's σ, this one by the depth it sees (docs/learning-reference.md).
    pub fn careful() -> Self {
        ExpertTuning {
            insertion_gate: InsertionGate::Holds {
                holds: 3,
                max_step_mm: 5.0,
                careful_depth_mm: CAREFUL_DEPTH_MM,
                careful_step_mm: CAREFUL_STEP_MM,
            },
            ..ExpertTuning::state_only()
        }
    }

    /// `expert-swift`: the state-only expert with no holds at the standoff and insertion steps
    /// of up to the 5 mm step limit. Once the cell knows its robot (decision 0017) the
    /// supervisor's bound on the probability of contact paces the insertion, not the
    /// demonstrator's holds: on the reference cell with 10 kept robots it succeeds 1.000 in
    /// 28.2 steps against `expert-careful`'s 41.9, and as often at twice and four times the
    /// noise (docs/learning-reference.md). Like `expert-careful` it decides on the 12-value state alone,
    /// and with no count of holds the selector has less to learn.
    pub fn swift() -> Self {
        ExpertTuning {
            insertion_gate: InsertionGate::Holds {
                holds: 0,
                max_step_mm: 5.0,
                careful_depth_mm: 0.0,
                careful_step_mm: 5.0,
            },
            ..ExpertTuning::state_only()
        }
    }
}

/// How far into the bore (mm past the entrance) `expert-careful` keeps its insertion steps to
/// [`CAREFUL_STEP_MM`].
pub const CAREFUL_DEPTH_MM: f64 = 35.0;

/// `expert-careful`'s longest insertion step (mm) over the first [`CAREFUL_DEPTH_MM`].
pub const CAREFUL_STEP_MM: f64 = 2.0;

/// Whether the tip counts as in the bore, `insertion_mm` past the entrance (negative above
/// it): from 0.2 mm above the entrance on, as the demonstrators decide.
pub fn tip_in_bore(insertion_mm: f64) -> bool {
    insertion_mm > -0.2
}

/// How far off the bore's axis (mm, x and y) the point the demonstrators centre is, for the
/// estimated pose P (mm) and O (deg) of a shaft `shaft_length_mm` long: the middle of the part
/// of the shaft that will be in the bore after a step of `limit_mm`, not the shoulder, since a
/// small tilt swings the tip sideways. Moving by minus this centres that point.
pub fn engaged_middle_off_axis_mm(
    p: Vector3<f64>,
    o: Vector3<f64>,
    shaft_length_mm: f64,
    limit_mm: f64,
) -> Vector2<f64> {
    // P is {F}'s origin in {M}: the tip is in the bore once P_z > -L.
    let insertion_mm = p.z + shaft_length_mm;
    let engaged_mm = (insertion_mm.max(0.0) + limit_mm).min(shaft_length_mm);
    let reference = Point3::new(0.0, 0.0, -shaft_length_mm + engaged_mm / 2.0);
    (pose_from_mm_deg(p, o).inverse() * reference).coords.xy()
}

pub struct Expert {
    name: &'static str,
    tuning: ExpertTuning,
    /// Holds made at the standoff this episode ([`InsertionGate::Holds`]).
    holds: u32,
    limit_mm: f64,
    limit_deg: f64,
    shaft_length_mm: f64,
    /// The tilt (deg) at which a shaft seated in the bore would touch the supervisor's wall
    /// margin: the radial clearance beside the margin over the bore's depth.
    clearance_tilt_deg: f64,
    rng: ChaCha8Rng,
}

impl Expert {
    /// The `expert` controller.
    pub fn new(cell: &CellConfig) -> Self {
        Self::with_tuning(cell, ExpertTuning::default())
    }

    /// The `expert-state-only` controller ([`ExpertTuning::state_only`]).
    pub fn state_only(cell: &CellConfig) -> Self {
        Expert {
            name: "expert-state-only",
            ..Self::with_tuning(cell, ExpertTuning::state_only())
        }
    }

    /// The `expert-careful` controller ([`ExpertTuning::careful`]).
    pub fn careful(cell: &CellConfig) -> Self {
        Expert {
            name: "expert-careful",
            ..Self::with_tuning(cell, ExpertTuning::careful())
        }
    }

    /// The `expert-swift` controller ([`ExpertTuning::swift`]).
    pub fn swift(cell: &CellConfig) -> Self {
        Expert {
            name: "expert-swift",
            ..Self::with_tuning(cell, ExpertTuning::swift())
        }
    }

    pub fn with_tuning(cell: &CellConfig, tuning: ExpertTuning) -> Self {
        Expert {
            name: "expert",
            tuning,
            holds: 0,
            limit_mm: cell.steps.position_mm,
            limit_deg: cell.steps.orientation_deg,
            shaft_length_mm: cell.shaft.engaged_length_mm,
            clearance_tilt_deg: ((cell.radial_clearance_mm() - cell.supervisor.wall_margin_mm)
                / cell.bore.depth_mm)
                .atan()
                .to_degrees(),
            rng: ChaCha8Rng::seed_from_u64(0),
        }
    }

    fn human_factor(&mut self) -> f64 {
        self.rng.random_range(self.tuning.min_step_factor..=1.0)
    }

    fn decide(&mut self, observation: &Observation) -> Decision {
        let s = &observation.state;
        let p = Vector3::new(s[6], s[7], s[8]);
        let o = Vector3::new(s[9], s[10], s[11]);
        let estimate = &observation.estimate;
        let t = self.tuning;
        // P is {F}'s origin in {M}: the tip is in the bore once P_z > -L.
        let insertion_mm = p.z + self.shaft_length_mm;
        let inside = tip_in_bore(insertion_mm);
        let tilt = o.xy().norm();
        let tilt_tolerance = t.tilt_tolerance_deg_on(self.clearance_tilt_deg, inside);
        if tilt > tilt_tolerance || o.z.abs() > t.roll_tolerance_deg {
            let factor = if o.norm() > 0.2 {
                self.human_factor()
            } else {
                0.9
            };
            let theta = clamp_components(o * factor, self.limit_deg);
            return Decision {
                action: Move {
                    translation_mm: Vector3::zeros(),
                    rotation_deg: theta,
                },
                actor: Some(Actor::Orientation),
                scale: Some(theta.amax() / self.limit_deg),
                shield: None,
            };
        }
        let off_axis = engaged_middle_off_axis_mm(p, o, self.shaft_length_mm, self.limit_mm);
        let lateral = off_axis.norm();
        // Height of the tip above the entrance (negative once inside).
        let height_mm = -insertion_mm;
        let sure = match t.insertion_gate {
            InsertionGate::FilterCertainty => estimate.lateral_sd_mm() <= t.lateral_certainty_mm,
            InsertionGate::Holds { holds, .. } => {
                let at_standoff = !inside
                    && lateral <= t.lateral_tolerance_mm
                    && height_mm <= t.standoff_mm + 0.01;
                if at_standoff && self.holds < holds {
                    self.holds += 1;
                    return Decision {
                        action: Move::default(),
                        actor: Some(Actor::Position),
                        scale: Some(0.0),
                        shield: None,
                    };
                }
                self.holds >= holds
            }
        };
        let inserting = inside || (lateral <= t.lateral_tolerance_mm && sure);
        let mut dz = if inserting {
            // Aligned: insert (the first step crosses the entrance), shrinking near the bottom.
            p.z
        } else {
            // Not aligned yet: come down, but only to the pre-standoff height while far off
            // sideways, then to the standoff; never lower before the alignment is done.
            let floor_mm = if lateral > 1.0 {
                t.prestandoff_mm
            } else {
                t.standoff_mm
            };
            (floor_mm - height_mm).min(0.0)
        };
        let mut lateral_move = -off_axis * if inside || lateral >= 0.5 { 1.0 } else { 0.8 };
        // Long moves come with a person's variability; short ones are placed with care.
        if dz.abs() > 1.0 {
            dz *= self.human_factor();
        }
        if lateral_move.amax() > 1.0 {
            lateral_move *= self.human_factor();
        }
        let mut dz = dz.clamp(-self.limit_mm, self.limit_mm);
        if inserting {
            match t.insertion_gate {
                // Going in: no longer a step than the lateral estimate stays sure over, given
                // what is known of the sideways drift (steps grow as the drift is learned).
                InsertionGate::FilterCertainty => {
                    while dz.abs() > 0.5
                        && estimate.lateral_sd_after_mm(dz) > t.insertion_certainty_mm
                    {
                        dz *= 0.7;
                    }
                }
                InsertionGate::Holds {
                    max_step_mm,
                    careful_depth_mm,
                    careful_step_mm,
                    ..
                } => {
                    let longest = if insertion_mm < careful_depth_mm {
                        careful_step_mm
                    } else {
                        max_step_mm
                    };
                    dz = dz.clamp(-longest, longest);
                }
            }
        }
        // Steer against the sideways drift the cell's state filter has learned.
        let wanted = Vector3::new(lateral_move.x, lateral_move.y, dz);
        let delta = if t.compensate_drift {
            steered_against_drift(&estimate.drift(), wanted)
        } else {
            wanted
        };
        let delta = clamp_components(delta, self.limit_mm);
        Decision {
            action: Move {
                translation_mm: delta,
                rotation_deg: Vector3::zeros(),
            },
            actor: Some(Actor::Position),
            scale: Some(delta.amax() / self.limit_mm),
            shield: None,
        }
    }
}

impl Controller for Expert {
    fn name(&self) -> &str {
        self.name
    }

    fn reset(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.holds = 0;
    }

    fn act(&mut self, observation: &Observation) -> Decision {
        if observation.measurement_fresh {
            self.decide(observation)
        } else {
            Decision::hold()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{FusionTuning, StateFilter};
    use crate::sim::{AssemblyEnv, EnvOptions};

    /// Runs one episode of `expert`; returns (insertion depth before the move in mm, the
    /// decision) for every decision taken on a fresh frame, and whether it succeeded.
    fn episode(cell: &CellConfig, expert: &mut Expert, seed: u64) -> (Vec<(f64, Decision)>, bool) {
        let mut env = AssemblyEnv::new(cell, EnvOptions::from_cell(cell));
        expert.reset(seed);
        let mut observation = env.reset(seed).unwrap();
        let mut decisions = Vec::new();
        loop {
            let decision = expert.act(&observation);
            if observation.measurement_fresh {
                let depth_mm = observation.state[8] + cell.shaft.engaged_length_mm;
                decisions.push((depth_mm, decision));
            }
            let result = env.step(&decision.action).unwrap();
            observation = result.observation;
            if let Some(outcome) = result.outcome {
                return (decisions, outcome == crate::sim::Outcome::Success);
            }
        }
    }

    #[test]
    fn the_careful_expert_holds_three_times_and_shortens_its_steps_in_the_first_35_mm() {
        let cell = CellConfig::reference();
        let mut expert = Expert::careful(&cell);
        let (mut careful_steps, mut long_steps) = (0, 0);
        for seed in 0..5 {
            let (decisions, succeeded) = episode(&cell, &mut expert, seed);
            assert!(succeeded, "episode {seed}");
            let holds = decisions
                .iter()
                .filter(|(_, d)| d.scale == Some(0.0))
                .count();
            assert_eq!(holds, 3, "episode {seed}");
            for (depth_mm, decision) in &decisions {
                let dz = decision.action.translation_mm.z;
                if *depth_mm < -0.2 || dz >= 0.0 || decision.actor != Some(Actor::Position) {
                    continue;
                }
                if *depth_mm < 35.0 {
                    assert!(-dz <= 2.0 + 1e-9, "{dz} mm at {depth_mm} mm in");
                    careful_steps += usize::from(-dz > 1.9);
                } else {
                    assert!(-dz <= 5.0 + 1e-9, "{dz} mm at {depth_mm} mm in");
                    long_steps += usize::from(-dz > 2.5);
                }
            }
        }
        assert!(
            careful_steps > 20 && long_steps > 5,
            "{careful_steps} {long_steps}"
        );
    }

    #[test]
    fn the_swift_expert_never_holds_on_a_fresh_frame_and_inserts_in_steps_of_up_to_5_mm() {
        let cell = CellConfig::reference();
        let mut expert = Expert::swift(&cell);
        let mut long_steps = 0;
        for seed in 0..5 {
            let (decisions, succeeded) = episode(&cell, &mut expert, seed);
            assert!(succeeded, "episode {seed}");
            assert!(
                decisions.iter().all(|(_, d)| d.scale != Some(0.0)),
                "episode {seed} held"
            );
            for (depth_mm, decision) in &decisions {
                let dz = decision.action.translation_mm.z;
                if *depth_mm >= -0.2 && dz < 0.0 {
                    assert!(-dz <= 5.0 + 1e-9, "{dz} mm at {depth_mm} mm in");
                    long_steps += usize::from(-dz > 2.5);
                }
            }
        }
        // The careful expert's first 35 mm allow no step over 2 mm: the swift one's do.
        assert!(long_steps > 20, "{long_steps}");
    }

    #[test]
    fn the_tilt_is_corrected_to_half_what_the_seated_shaft_could_take_above_and_in_the_bore() {
        // The reference cell: (0.05 − 0.02) mm of clearance beside the wall margin over 60 mm
        // is 0.0286°, half of it 0.0143°. A Φ100 bore 100 mm deep with 0.03 mm: (0.03 − 0.02)
        // mm over 100 mm is 0.0057°, half of it 0.0029°.
        let reference = CellConfig::reference();
        let mut deep = reference.clone();
        deep.bore.depth_mm = 100.0;
        deep.shaft.engaged_length_mm = 100.0;
        deep.shaft.diameter_mm = deep.bore.diameter_mm - 0.06;
        let actor_at = |cell: &CellConfig, tilt_deg: f64, above_entrance_mm: f64| {
            // The tip `above_entrance_mm` above the entrance (negative: in the bore), on the axis.
            let z_mm = -cell.shaft.engaged_length_mm - above_entrance_mm;
            let state = [
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, z_mm, tilt_deg, 0.0, 0.0,
            ];
            let observation = Observation {
                state,
                raw_state: state,
                estimate: StateFilter::new(FusionTuning::default()),
                step: 3,
                measurement_fresh: true,
                last_veto: None,
                cell: cell.shape(),
            };
            let mut expert = Expert::swift(cell);
            expert.reset(1);
            expert.act(&observation).actor
        };
        let actor = |cell: &CellConfig, tilt_deg: f64| actor_at(cell, tilt_deg, 20.0);
        assert_eq!(actor(&reference, 0.013), Some(Actor::Position));
        assert_eq!(actor(&reference, 0.016), Some(Actor::Orientation));
        assert_eq!(actor(&deep, 0.0027), Some(Actor::Position));
        assert_eq!(actor(&deep, 0.0031), Some(Actor::Orientation));
        // Beyond 0.02° it is corrected whatever the cell.
        let mut loose = reference.clone();
        loose.bore.depth_mm = 40.0;
        loose.shaft.diameter_mm = loose.bore.diameter_mm - 0.2;
        assert_eq!(actor(&loose, 0.019), Some(Actor::Position));
        assert_eq!(actor(&loose, 0.021), Some(Actor::Orientation));
        // 30 mm into the bore the same share holds, with 0.05° in place of 0.02°: the other
        // two cells take what they take above, the loose one 0.05° (half of its 0.115°).
        let inside = |cell: &CellConfig, tilt_deg: f64| actor_at(cell, tilt_deg, -30.0);
        assert_eq!(inside(&reference, 0.013), Some(Actor::Position));
        assert_eq!(inside(&reference, 0.016), Some(Actor::Orientation));
        assert_eq!(inside(&deep, 0.0027), Some(Actor::Position));
        assert_eq!(inside(&deep, 0.0031), Some(Actor::Orientation));
        assert_eq!(inside(&loose, 0.045), Some(Actor::Position));
        assert_eq!(inside(&loose, 0.051), Some(Actor::Orientation));
    }

    #[test]
    fn the_swift_expert_decides_on_the_state_alone() {
        // The same state and seed with the filter's snapshot of another episode gives the same
        // move: nothing of the filter (its σ, its learned drift) enters the decision, so a
        // policy that reads the state can learn it.
        let cell = CellConfig::reference();
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        let first = env.reset(1).unwrap();
        let mut other = env.reset(2).unwrap();
        for _ in 0..5 {
            other = env.step(&Move::default()).unwrap().observation;
        }
        assert_ne!(other.estimate, first.estimate);
        let with_other_filter = Observation {
            estimate: other.estimate,
            ..first.clone()
        };
        let decide = |observation: &Observation| {
            let mut expert = Expert::swift(&cell);
            expert.reset(7);
            expert.act(observation)
        };
        assert_eq!(decide(&with_other_filter), decide(&first));
    }
}
