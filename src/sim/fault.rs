//! Faults injected into the twin, for evaluating the cell under mismatch between the twin and
//! the real cell (docs/configuration.md, "Model mismatch and faults").
//!
//! A [`Fault`] starts at an onset step drawn uniformly in [`ONSET_STEPS`] (mid-job: episodes
//! take about 46 steps) and lasts to the end of the episode. Everything about it (onset,
//! direction, which point) is drawn from a random stream of its own, seeded from the episode
//! seed ([`FAULT_SEED_SALT`]), never from the episode's main stream: an episode without a fault
//! is the same as before faults existed, and one with a fault is the same up to the onset.
//!
//! Camera faults act on each delivered frame through [`Injection::deliver`], which the
//! environment calls after every capture; robot faults are [`RobotFaults`] the environment hands
//! to the twin's robot (`sim::robot::TwinRobot::set_faults`) at every step.

use super::env::random_unit;
use crate::camera::{CameraFrame, Fixture};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::ops::RangeInclusive;

/// A fault the twin can inject, from its onset (a step drawn in 5..=35) to the end of the
/// episode: `camera_shift` (fixture C2's measured points moved 0.2 mm and 0.05° rigidly),
/// `occlusion` (one coded point missing), `frozen_camera` (the last frame before the onset
/// delivered again and again), `out_of_order` (every third frame two steps old), `robot_lag`
/// (seen and read half-way along each move) or `robot_short` (legs land at 70% of each change).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Fault {
    /// The camera is knocked out of calibration: every measured coded point of fixture C2 (on
    /// Segment II) is moved by one fixed rigid transform about the centroid of C2's points,
    /// [`CAMERA_SHIFT_MM`] in a random direction and [`CAMERA_SHIFT_DEG`] about a random axis
    /// (drawn once per episode). A rigid shift of the whole camera would leave the relative pose
    /// alone, so it shifts one fixture's frame.
    CameraShift,
    /// One coded point (a random fixture, a random id) is missing from every frame.
    Occlusion,
    /// Every frame delivered is an exact copy of the last frame captured before the onset (the
    /// same points and the same sequence number).
    FrozenCamera,
    /// Every [`OUT_OF_ORDER_PERIOD`]th step from the onset, the frame delivered is the one
    /// captured [`OUT_OF_ORDER_DELAY`] steps earlier (with its older sequence number) instead of
    /// the new one.
    OutOfOrder,
    /// The robot arrives late: after each move the camera sees the platform only
    /// [`ROBOT_LAG_FRACTION`] of the way along its true move (on top of the normal latency), and
    /// the encoders report the leg lengths of that pose; the robot completes the move before the
    /// next step (contact and success are judged on the full move).
    RobotLag,
    /// Every move's legs land at [`ROBOT_SHORT_FRACTION`] of the commanded change from their
    /// previous length (on top of the normal leg error); the encoders report what was reached.
    RobotShort,
}

/// Steps at which a fault may start, drawn uniformly.
pub const ONSET_STEPS: RangeInclusive<u32> = 5..=35;
/// The fault's random stream is seeded with the episode seed XOR this.
pub const FAULT_SEED_SALT: u64 = 0xFA17_0000_5EED_0001;
/// `camera_shift`: translation of fixture C2's points, mm.
pub const CAMERA_SHIFT_MM: f64 = 0.2;
/// `camera_shift`: rotation of fixture C2's points about their centroid, deg.
pub const CAMERA_SHIFT_DEG: f64 = 0.05;
/// `out_of_order`: one frame in this many, from the onset, is an old one.
pub const OUT_OF_ORDER_PERIOD: u32 = 3;
/// `out_of_order`: how many steps old the frame delivered out of order is.
pub const OUT_OF_ORDER_DELAY: u32 = 2;
/// `robot_lag`: how far along its move the camera sees the platform, as a fraction of what it
/// would see without the fault.
pub const ROBOT_LAG_FRACTION: f64 = 0.5;
/// `robot_short`: the fraction of the commanded change of each leg that is reached.
pub const ROBOT_SHORT_FRACTION: f64 = 0.7;

impl Fault {
    /// Every fault, in the order of their codes' documentation.
    pub const ALL: [Fault; 6] = [
        Fault::CameraShift,
        Fault::Occlusion,
        Fault::FrozenCamera,
        Fault::OutOfOrder,
        Fault::RobotLag,
        Fault::RobotShort,
    ];

    /// The fault's name on the command line, in JSON and in reports.
    pub fn code(&self) -> &'static str {
        match self {
            Fault::CameraShift => "camera_shift",
            Fault::Occlusion => "occlusion",
            Fault::FrozenCamera => "frozen_camera",
            Fault::OutOfOrder => "out_of_order",
            Fault::RobotLag => "robot_lag",
            Fault::RobotShort => "robot_short",
        }
    }

    /// Every fault's code, comma-separated (for messages and help).
    pub fn names() -> String {
        Fault::ALL.map(|f| f.code()).join(", ")
    }
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.code())
    }
}

/// A name that is not a fault's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown fault `{name}`: expected one of {}", Fault::names())]
pub struct UnknownFault {
    pub name: String,
}

impl std::str::FromStr for Fault {
    type Err = UnknownFault;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Fault::ALL
            .into_iter()
            .find(|f| f.code() == name)
            .ok_or_else(|| UnknownFault {
                name: name.to_string(),
            })
    }
}

/// The largest camera noise or calibration scale the twin is run at (× the data sheet's, × the
/// cell file's): an evaluation's mismatch, or the top of the noise range cells are drawn over.
pub const MAX_MISMATCH_SCALE: f64 = 16.0;

/// How an evaluation's twin departs from the cell file: the options of
/// [`EnvOptions`](super::EnvOptions) besides the initial conditions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Mismatch {
    /// Multiplies the camera's point noise (1: the spec).
    pub noise_scale: f64,
    /// Multiplies the robot's calibration error (1: the cell file's; 0: perfect).
    pub calibration_scale: f64,
    /// A fault injected mid-episode.
    pub fault: Option<Fault>,
}

impl Mismatch {
    /// The twin as the cell file describes it.
    pub const NONE: Mismatch = Mismatch {
        noise_scale: 1.0,
        calibration_scale: 1.0,
        fault: None,
    };

    /// Whether this is the twin as the cell file describes it.
    pub fn is_none(&self) -> bool {
        *self == Self::NONE
    }

    /// The mismatch `options` carry.
    pub fn of(options: &super::EnvOptions) -> Self {
        Mismatch {
            noise_scale: options.noise_scale,
            calibration_scale: options.calibration_scale,
            fault: options.fault,
        }
    }

    /// `options` with this mismatch.
    pub fn apply(&self, options: super::EnvOptions) -> super::EnvOptions {
        super::EnvOptions {
            noise_scale: self.noise_scale,
            calibration_scale: self.calibration_scale,
            fault: self.fault,
            ..options
        }
    }
}

impl Default for Mismatch {
    fn default() -> Self {
        Self::NONE
    }
}

/// What a robot fault does to the twin's robot at one step (none: a healthy robot).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RobotFaults {
    /// Each leg lands at this fraction of its commanded change (`robot_short`).
    pub short_fraction: Option<f64>,
    /// The camera sees the platform this fraction of the way along what it would see, and the
    /// encoders report that pose's legs until the next step (`robot_lag`).
    pub lag_fraction: Option<f64>,
}

/// What was drawn for one episode's fault.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Drawn {
    /// The rigid transform applied to C2's points in {W}.
    CameraShift(Isometry3<f64>),
    /// The coded point left out.
    Occlusion(Fixture, u16),
    Other,
}

/// One episode's fault: what was drawn for it, and the frames it holds back or replays.
#[derive(Debug, Clone)]
pub struct Injection {
    fault: Fault,
    onset: u32,
    drawn: Drawn,
    /// `frozen_camera`: the last frame captured before the onset.
    frozen: Option<CameraFrame>,
    /// `out_of_order`: the latest frames captured, with their steps (newest last).
    history: Vec<(u32, CameraFrame)>,
}

impl Injection {
    /// Draws `fault` for the episode seeded with `episode_seed`. `c2_centroid_w` is the centroid
    /// of fixture C2's coded points in the camera frame {W} (the centre of `camera_shift`'s
    /// rotation); `points_per_fixture` is the number of coded points on each fixture.
    pub fn draw(
        fault: Fault,
        episode_seed: u64,
        c2_centroid_w: Point3<f64>,
        points_per_fixture: usize,
    ) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(episode_seed ^ FAULT_SEED_SALT);
        let onset = rng.random_range(ONSET_STEPS);
        let drawn = match fault {
            Fault::CameraShift => {
                let direction = random_unit(&mut rng);
                let axis = random_unit(&mut rng);
                let rotation =
                    UnitQuaternion::from_scaled_axis(axis * CAMERA_SHIFT_DEG.to_radians());
                let centre = c2_centroid_w.coords;
                // p' = c + R (p − c) + t
                let transform = Translation3::from(centre + direction * CAMERA_SHIFT_MM)
                    * rotation
                    * Translation3::from(-centre);
                Drawn::CameraShift(transform)
            }
            Fault::Occlusion => {
                let fixture = if rng.random_bool(0.5) {
                    Fixture::C1
                } else {
                    Fixture::C2
                };
                let id = rng.random_range(0..points_per_fixture.max(1));
                Drawn::Occlusion(fixture, u16::try_from(id).unwrap_or(u16::MAX))
            }
            _ => Drawn::Other,
        };
        Injection {
            fault,
            onset,
            drawn,
            frozen: None,
            history: Vec::new(),
        }
    }

    pub fn fault(&self) -> Fault {
        self.fault
    }

    /// The first step the fault acts on (moves and captures of steps ≥ onset).
    pub fn onset(&self) -> u32 {
        self.onset
    }

    /// Whether the fault acts at `step`.
    pub fn active(&self, step: u32) -> bool {
        step >= self.onset
    }

    /// `camera_shift`: the rigid transform applied to C2's measured points, in {W}.
    pub fn camera_shift(&self) -> Option<Isometry3<f64>> {
        match self.drawn {
            Drawn::CameraShift(transform) => Some(transform),
            _ => None,
        }
    }

    /// `occlusion`: the coded point missing from every frame from the onset.
    pub fn occluded_point(&self) -> Option<(Fixture, u16)> {
        match self.drawn {
            Drawn::Occlusion(fixture, id) => Some((fixture, id)),
            _ => None,
        }
    }

    /// What the robot fault does at `step` (nothing before the onset, or for a camera fault).
    pub fn robot_faults(&self, step: u32) -> RobotFaults {
        if !self.active(step) {
            return RobotFaults::default();
        }
        match self.fault {
            Fault::RobotShort => RobotFaults {
                short_fraction: Some(ROBOT_SHORT_FRACTION),
                lag_fraction: None,
            },
            Fault::RobotLag => RobotFaults {
                short_fraction: None,
                lag_fraction: Some(ROBOT_LAG_FRACTION),
            },
            _ => RobotFaults::default(),
        }
    }

    /// Turns the frame captured at `step` into the frame delivered (in place). Call it once
    /// per capture, in order, every capture of the episode included.
    pub fn deliver(&mut self, step: u32, frame: &mut CameraFrame) {
        match self.fault {
            Fault::CameraShift if self.active(step) => {
                if let Drawn::CameraShift(transform) = self.drawn {
                    for point in frame.points.iter_mut() {
                        if point.fixture == Fixture::C2 {
                            point.position_mm = transform * point.position_mm;
                        }
                    }
                }
            }
            Fault::Occlusion if self.active(step) => {
                if let Drawn::Occlusion(fixture, id) = self.drawn {
                    frame
                        .points
                        .retain(|p| !(p.fixture == fixture && p.id == id));
                }
            }
            Fault::FrozenCamera => {
                if self.active(step) {
                    if let Some(frozen) = &self.frozen {
                        frame.clone_from(frozen);
                    }
                } else {
                    match &mut self.frozen {
                        Some(frozen) => frozen.clone_from(frame),
                        None => self.frozen = Some(frame.clone()),
                    }
                }
            }
            Fault::OutOfOrder => {
                // Keep the captures of the last OUT_OF_ORDER_DELAY steps (one per step: the
                // latest).
                self.history
                    .retain(|(s, _)| *s != step && *s + OUT_OF_ORDER_DELAY >= step);
                self.history.push((step, frame.clone()));
                let late = self.active(step)
                    && (step - self.onset).is_multiple_of(OUT_OF_ORDER_PERIOD)
                    && step >= OUT_OF_ORDER_DELAY;
                if late
                    && let Some((_, old)) = self
                        .history
                        .iter()
                        .find(|(s, _)| *s == step - OUT_OF_ORDER_DELAY)
                {
                    frame.clone_from(old);
                }
            }
            _ => {}
        }
    }
}

/// The centroid of fixture C2's coded points in {W}, for [`Injection::draw`].
pub fn c2_centroid_w(frames: &crate::geometry::CellFrames) -> Point3<f64> {
    let (_, w_f) = frames.world_poses(&crate::geometry::Pose::identity());
    let n = frames.c2_points_mm.len().max(1) as f64;
    let sum = frames.c2_points_mm.iter().fold(Vector3::zeros(), |sum, p| {
        sum + (w_f * frames.f_c2 * p).coords
    });
    Point3::from(sum / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::ingest::Ingest;
    use crate::config::cell::CellConfig;
    use crate::geometry::{CellFrames, Move, Pose};
    use crate::sim::env::first_usable_estimate;
    use crate::sim::{AssemblyEnv, EnvOptions, StepResult};

    /// One step of an episode: what was delivered, what came of it, and the true pose.
    struct Record {
        step: u32,
        frame: CameraFrame,
        result: StepResult,
        true_f_m: Pose,
    }

    /// An episode with `fault`, driven by `moves` (by step) for up to `steps` steps, with the
    /// camera's shots ingested outside the environment (as the cell does), so each delivered
    /// frame can be looked at. The supervisor is given the true pose instead of the cell's
    /// estimate, so that what the estimator makes of a fault (or whether it notices it) does not
    /// change where the robot goes. Answers the onset (if any), the encoders after the first
    /// capture, and each step.
    fn episode(
        cell: &CellConfig,
        options: EnvOptions,
        seed: u64,
        moves: impl Fn(u32) -> Move,
        steps: u32,
    ) -> (Option<u32>, [f64; 6], Vec<Record>) {
        let frames = CellFrames::from_config(cell);
        let mut ingest = Ingest::new(cell, &frames);
        let mut env = AssemblyEnv::new(cell, options);
        env.begin_episode(seed, options.initial).unwrap();
        let Ok(mut estimate) = first_usable_estimate(|first| {
            Ok::<_, std::convert::Infallible>(ingest.take(env.capture_still(first)))
        });
        estimate.m_f = Some(env.true_f_m().inverse());
        env.start_from(&estimate);
        let start_encoders = env.encoders_mm();
        let mut records = Vec::new();
        for step in 1..=steps {
            let shot = env.act(&moves(step)).unwrap().clone();
            let mut estimate = ingest.take(&shot);
            estimate.m_f = Some(env.true_f_m().inverse());
            let result = env.settle(&estimate).unwrap();
            assert_eq!(env.encoders_mm(), result.legs_mm);
            let done = result.done;
            records.push(Record {
                step,
                frame: shot.frame,
                result,
                true_f_m: env.true_f_m(),
            });
            if done {
                break;
            }
        }
        (env.fault_onset(), start_encoders, records)
    }

    /// Half a millimetre sideways and back (no move at every third step): far from the bore, so
    /// never vetoed and never in contact.
    fn zigzag(step: u32) -> Move {
        match step % 4 {
            0 | 1 => Move::translation(0.5, 0.0, 0.0),
            _ => Move::translation(-0.5, 0.0, 0.0),
        }
    }

    fn with_fault(cell: &CellConfig, fault: Option<Fault>) -> EnvOptions {
        EnvOptions {
            fault,
            ..EnvOptions::from_cell(cell)
        }
    }

    /// A robot without calibration or execution error: it goes exactly where it is sent.
    fn perfect_robot_cell() -> CellConfig {
        let mut cell = CellConfig::reference();
        cell.imperfections.calibration_error = false;
        cell.imperfections.execution_error = false;
        cell
    }

    const STEPS: u32 = 45;

    /// A frame as if captured at `step`: every point of both fixtures, numbered `step + 1`.
    fn synthetic_frame(step: u32) -> CameraFrame {
        let mut points = Vec::new();
        for fixture in [Fixture::C1, Fixture::C2] {
            for id in 0..6u16 {
                let offset = if fixture == Fixture::C1 { 0.0 } else { 500.0 };
                points.push(crate::camera::CodedPoint {
                    fixture,
                    id,
                    position_mm: nalgebra::Point3::new(
                        offset + 70.0 * f64::from(id).cos(),
                        70.0 * f64::from(id).sin() + f64::from(step),
                        2000.0 + f64::from(id % 2) * 10.0,
                    ),
                });
            }
        }
        CameraFrame {
            points,
            sequence: u64::from(step) + 1,
            ..CameraFrame::default()
        }
    }

    /// Each step's frame through `injection`, from step 0 to 60.
    fn delivered(injection: &mut Injection) -> Vec<CameraFrame> {
        (0..=60)
            .map(|step| {
                let mut frame = synthetic_frame(step);
                injection.deliver(step, &mut frame);
                frame
            })
            .collect()
    }

    fn draw(fault: Fault, seed: u64) -> Injection {
        let frames = CellFrames::from_config(&CellConfig::reference());
        Injection::draw(fault, seed, c2_centroid_w(&frames), 6)
    }

    #[test]
    fn injected_frames_frozen_late_occluded_or_shifted_from_the_onset() {
        for seed in 0..20 {
            // Frozen: the frame of the step before the onset, again and again.
            let mut frozen = draw(Fault::FrozenCamera, seed);
            let onset = frozen.onset();
            for (step, frame) in delivered(&mut frozen).iter().enumerate() {
                let step = step as u32;
                let expected = synthetic_frame(if step < onset { step } else { onset - 1 });
                assert!(frame == &expected, "seed {seed} step {step}");
            }
            // Out of order: every third step from the onset, the frame of two steps before.
            let mut late = draw(Fault::OutOfOrder, seed);
            let onset = late.onset();
            let frames = delivered(&mut late);
            for (step, frame) in frames.iter().enumerate() {
                let step = step as u32;
                let is_late = step >= onset && (step - onset).is_multiple_of(3);
                let expected = synthetic_frame(if is_late { step - 2 } else { step });
                assert!(frame == &expected, "seed {seed} step {step}");
                if is_late {
                    assert!(frame.sequence < frames[step as usize - 1].sequence);
                }
            }
            // Occlusion: one point missing, the rest as captured.
            let mut occluded = draw(Fault::Occlusion, seed);
            let onset = occluded.onset();
            let (fixture, id) = occluded.occluded_point().unwrap();
            assert!(id < 6);
            for (step, frame) in delivered(&mut occluded).iter().enumerate() {
                let step = step as u32;
                let mut expected = synthetic_frame(step);
                if step >= onset {
                    expected
                        .points
                        .retain(|p| !(p.fixture == fixture && p.id == id));
                    assert_eq!(frame.points.len(), 11);
                }
                assert!(frame == &expected, "seed {seed} step {step}");
            }
            // Camera shift: C2's points moved by one rigid transform, C1's left alone.
            let mut shifted = draw(Fault::CameraShift, seed);
            let onset = shifted.onset();
            let shift = shifted.camera_shift().unwrap();
            for (step, frame) in delivered(&mut shifted).iter().enumerate() {
                let step = step as u32;
                let captured = synthetic_frame(step);
                assert_eq!(frame.sequence, captured.sequence);
                for (p, q) in captured.points.iter().zip(&frame.points) {
                    if step >= onset && p.fixture == Fixture::C2 {
                        assert!((shift * p.position_mm - q.position_mm).norm() < 1e-9);
                        assert!(p.position_mm != q.position_mm);
                    } else {
                        assert_eq!(p.position_mm, q.position_mm);
                    }
                }
            }
            // The robot faults leave frames alone.
            for fault in [Fault::RobotLag, Fault::RobotShort] {
                let mut robot = draw(fault, seed);
                for (step, frame) in delivered(&mut robot).iter().enumerate() {
                    assert!(*frame == synthetic_frame(step as u32));
                }
            }
        }
    }

    #[test]
    fn robot_faults_act_from_the_onset_and_camera_faults_never() {
        for fault in Fault::ALL {
            let injection = draw(fault, 3);
            let onset = injection.onset();
            assert_eq!(injection.robot_faults(onset - 1), RobotFaults::default());
            let expected = match fault {
                Fault::RobotShort => RobotFaults {
                    short_fraction: Some(0.7),
                    lag_fraction: None,
                },
                Fault::RobotLag => RobotFaults {
                    short_fraction: None,
                    lag_fraction: Some(0.5),
                },
                _ => RobotFaults::default(),
            };
            assert_eq!(injection.robot_faults(onset), expected, "{fault}");
            assert_eq!(injection.robot_faults(onset + 20), expected, "{fault}");
        }
    }

    #[test]
    fn names_parse_print_and_serialise_the_same() {
        for fault in Fault::ALL {
            assert_eq!(fault.code().parse::<Fault>(), Ok(fault));
            assert_eq!(fault.to_string(), fault.code());
            assert_eq!(
                serde_json::to_value(fault).unwrap(),
                serde_json::json!(fault.code())
            );
            let back: Fault = serde_json::from_value(serde_json::json!(fault.code())).unwrap();
            assert_eq!(back, fault);
        }
        let error = "gravity".parse::<Fault>().unwrap_err().to_string();
        assert_eq!(
            error,
            "unknown fault `gravity`: expected one of camera_shift, occlusion, frozen_camera, \
             out_of_order, robot_lag, robot_short"
        );
    }

    #[test]
    fn the_onset_is_mid_job_and_drawn_from_the_seed_alone() {
        let frames = CellFrames::from_config(&CellConfig::reference());
        let centroid = c2_centroid_w(&frames);
        let mut onsets = std::collections::BTreeSet::new();
        for seed in 0..400 {
            let a = Injection::draw(Fault::Occlusion, seed, centroid, 6);
            let b = Injection::draw(Fault::Occlusion, seed, centroid, 6);
            assert_eq!(a.onset(), b.onset());
            assert_eq!(a.occluded_point(), b.occluded_point());
            assert!(ONSET_STEPS.contains(&a.onset()), "{}", a.onset());
            onsets.insert(a.onset());
        }
        assert_eq!(onsets.len(), 31, "every step in 5..=35 drawn: {onsets:?}");
    }

    #[test]
    fn the_default_options_have_no_mismatch() {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        assert_eq!(options.calibration_scale, 1.0);
        assert_eq!(options.fault, None);
        assert!(Mismatch::of(&options).is_none());
        assert_eq!(Mismatch::NONE.apply(options), options);
    }

    /// The fault's stream is its own: with the same moves, every fault leaves the episode as it
    /// is without one up to its onset, bit for bit (frames, results and true poses).
    #[test]
    fn a_fault_changes_nothing_before_its_onset() {
        let cell = CellConfig::reference();
        let seed = 11;
        let (none_onset, none_start, clean) =
            episode(&cell, with_fault(&cell, None), seed, zigzag, STEPS);
        assert_eq!(none_onset, None);
        assert_eq!(clean.len(), STEPS as usize, "the zigzag runs to the end");
        let (_, again_start, again) = episode(&cell, with_fault(&cell, None), seed, zigzag, STEPS);
        assert_eq!(none_start, again_start);
        for (a, b) in clean.iter().zip(&again) {
            assert!(a.frame == b.frame);
            assert_eq!(a.result, b.result);
        }
        // Sequence numbers count captures from 1 within the episode.
        let first = clean[0].frame.sequence;
        assert!(first >= 2, "the start's captures come first: {first}");
        for (k, record) in clean.iter().enumerate() {
            assert_eq!(record.frame.sequence, first + k as u64);
        }
        for fault in Fault::ALL {
            let (onset, start, faulty) =
                episode(&cell, with_fault(&cell, Some(fault)), seed, zigzag, STEPS);
            let onset = onset.unwrap();
            assert_eq!(start, none_start, "{fault}");
            for (a, b) in clean.iter().zip(&faulty).filter(|(a, _)| a.step < onset) {
                assert!(a.frame == b.frame, "{fault} at step {}", a.step);
                assert_eq!(a.result, b.result, "{fault} at step {}", a.step);
                assert_eq!(a.true_f_m, b.true_f_m, "{fault} at step {}", a.step);
            }
            let differs = clean
                .iter()
                .zip(&faulty)
                .any(|(a, b)| a.step >= onset && a.result != b.result);
            assert!(differs, "{fault} changed nothing after its onset {onset}");
        }
    }

    #[test]
    fn a_frozen_camera_delivers_the_last_frame_before_the_onset_again_and_again() {
        let cell = CellConfig::reference();
        let options = with_fault(&cell, Some(Fault::FrozenCamera));
        let (onset, _, records) = episode(&cell, options, 12, zigzag, STEPS);
        let onset = onset.unwrap();
        let last_before = &records[(onset - 2) as usize];
        assert_eq!(last_before.step, onset - 1);
        let after: Vec<&Record> = records.iter().filter(|r| r.step >= onset).collect();
        // The cell notices the third identical frame and ends the episode, holding.
        assert_eq!(
            after.len(),
            crate::camera::ingest::FROZEN_FRAMES as usize - 1
        );
        let last = after.last().unwrap();
        assert_eq!(last.result.detected, Some("frozen_camera"));
        assert_eq!(
            last.result.outcome,
            Some(crate::sim::Outcome::Failure(
                crate::sim::FailureReason::FrozenCamera
            ))
        );
        for record in after {
            assert!(record.frame == last_before.frame, "step {}", record.step);
        }
    }

    #[test]
    fn out_of_order_frames_arrive_two_steps_late_every_third_step() {
        let cell = CellConfig::reference();
        let seed = 13;
        let (_, _, clean) = episode(&cell, with_fault(&cell, None), seed, zigzag, STEPS);
        let options = with_fault(&cell, Some(Fault::OutOfOrder));
        let (onset, _, records) = episode(&cell, options, seed, zigzag, STEPS);
        let onset = onset.unwrap();
        let mut late = 0;
        for (i, record) in records.iter().enumerate() {
            let captured = clean[i].frame.sequence;
            if record.step >= onset && (record.step - onset).is_multiple_of(3) {
                late += 1;
                let earlier = &records[i - 2];
                assert_eq!(earlier.step + 2, record.step);
                assert_eq!(record.frame.sequence, captured - 2, "step {}", record.step);
                assert_eq!(record.frame.sequence, earlier.frame.sequence);
                assert!(record.frame.sequence < records[i - 1].frame.sequence);
                assert!(record.frame == earlier.frame);
            } else {
                assert_eq!(record.frame.sequence, captured, "step {}", record.step);
            }
        }
        assert!(late >= 3, "{late} late frames");
    }

    #[test]
    fn an_occluded_point_is_missing_from_every_frame_from_the_onset() {
        let mut cell = CellConfig::reference();
        cell.imperfections.dropped_points = false;
        let seed = 14;
        let (_, _, clean) = episode(&cell, with_fault(&cell, None), seed, zigzag, STEPS);
        let options = with_fault(&cell, Some(Fault::Occlusion));
        let (onset, _, records) = episode(&cell, options, seed, zigzag, STEPS);
        let onset = onset.unwrap();
        let frames = CellFrames::from_config(&cell);
        let injection = Injection::draw(
            Fault::Occlusion,
            seed,
            c2_centroid_w(&frames),
            frames.c2_points_mm.len(),
        );
        let (fixture, id) = injection.occluded_point().unwrap();
        let all = frames.c1_points_mm.len() + frames.c2_points_mm.len();
        for (a, b) in clean.iter().zip(&records) {
            let has = |frame: &CameraFrame| {
                frame
                    .points
                    .iter()
                    .any(|p| p.fixture == fixture && p.id == id)
            };
            assert!(has(&a.frame));
            assert_eq!(a.frame.points.len(), all);
            if b.step >= onset {
                assert!(!has(&b.frame), "step {}", b.step);
                assert_eq!(b.frame.points.len(), all - 1);
                // Everything else as captured.
                let mut rest = a.frame.clone();
                rest.points
                    .retain(|p| !(p.fixture == fixture && p.id == id));
                assert!(rest == b.frame, "step {}", b.step);
            } else {
                assert!(a.frame == b.frame);
            }
        }
    }

    #[test]
    fn a_camera_shift_moves_c2s_points_rigidly_by_a_fifth_of_a_millimetre() {
        let cell = CellConfig::reference();
        let seed = 15;
        let (_, _, clean) = episode(&cell, with_fault(&cell, None), seed, zigzag, STEPS);
        let options = with_fault(&cell, Some(Fault::CameraShift));
        let (onset, _, records) = episode(&cell, options, seed, zigzag, STEPS);
        let onset = onset.unwrap();
        let frames = CellFrames::from_config(&cell);
        let centroid = c2_centroid_w(&frames);
        let shift = Injection::draw(Fault::CameraShift, seed, centroid, 6)
            .camera_shift()
            .unwrap();
        assert!(((shift * centroid - centroid).norm() - CAMERA_SHIFT_MM).abs() < 1e-12);
        assert!((shift.rotation.angle().to_degrees() - CAMERA_SHIFT_DEG).abs() < 1e-9);
        let mut shifted = 0;
        // Up to the onset's frame: after it the cell holds back and stops, so the runs part.
        for (a, b) in clean.iter().zip(&records).filter(|(_, b)| b.step <= onset) {
            assert_eq!(a.frame.points.len(), b.frame.points.len());
            assert_eq!(a.frame.sequence, b.frame.sequence);
            for (p, q) in a.frame.points.iter().zip(&b.frame.points) {
                assert_eq!((p.fixture, p.id), (q.fixture, q.id));
                if b.step >= onset && p.fixture == Fixture::C2 {
                    let expected = shift * p.position_mm;
                    assert!((q.position_mm - expected).norm() < 1e-9);
                    let moved = (q.position_mm - p.position_mm).norm();
                    // 0.2 mm, give or take the rotation's 0.05° over the fixture's radius.
                    assert!((0.1..0.3).contains(&moved), "moved {moved} mm");
                    shifted += 1;
                } else {
                    assert_eq!(p.position_mm, q.position_mm);
                }
            }
            // Rigid: the distances between C2's points are kept.
            let c2 = |frame: &CameraFrame| -> Vec<nalgebra::Point3<f64>> {
                frame
                    .points
                    .iter()
                    .filter(|p| p.fixture == Fixture::C2)
                    .map(|p| p.position_mm)
                    .collect()
            };
            let (before, after) = (c2(&a.frame), c2(&b.frame));
            for i in 0..before.len() {
                for j in 0..i {
                    let d0 = (before[i] - before[j]).norm();
                    let d1 = (after[i] - after[j]).norm();
                    assert!((d0 - d1).abs() < 1e-9);
                }
            }
        }
        // The cell notices the jump (held back, then confirmed) and ends the episode, holding.
        assert!(shifted >= 6, "{shifted} points shifted");
        let last = records.last().unwrap();
        assert_eq!(last.result.detected, Some("camera_shift"));
        assert!(
            last.step <= onset + 3,
            "noticed at step {} of {onset}",
            last.step
        );
    }

    #[test]
    fn a_short_robot_reaches_seventy_percent_of_each_legs_commanded_change() {
        let cell = perfect_robot_cell();
        let options = with_fault(&cell, Some(Fault::RobotShort));
        let (onset, start, records) = episode(&cell, options, 16, zigzag, STEPS);
        let onset = onset.unwrap();
        let mut previous = start;
        let mut short = 0;
        // The cell notices the first short move and ends the episode at the next step without
        // moving.
        let last = records.last().unwrap();
        assert_eq!(last.result.detected, Some("robot_short"));
        assert_eq!(last.result.commanded_legs_mm, None);
        for record in &records[..records.len() - 1] {
            let commanded = record.result.commanded_legs_mm.unwrap();
            let reached = record.result.legs_mm;
            for leg in 0..6 {
                let expected = if record.step >= onset {
                    previous[leg] + ROBOT_SHORT_FRACTION * (commanded[leg] - previous[leg])
                } else {
                    commanded[leg]
                };
                assert!(
                    (reached[leg] - expected).abs() < 1e-9,
                    "step {} leg {leg}: {} against {expected}",
                    record.step,
                    reached[leg]
                );
            }
            if record.step >= onset {
                let gap = (0..6)
                    .map(|leg| (reached[leg] - commanded[leg]).abs())
                    .fold(0.0, f64::max);
                assert!(gap > 1e-3, "step {}: short by {gap} mm only", record.step);
                short += 1;
            }
            previous = reached;
        }
        assert_eq!(short, 1);
    }

    /// The camera sees the lagging platform half-way along its move and the encoders report the
    /// legs there; by the next step the robot is where it was sent (a move of nothing then
    /// finds the encoders on the last command), and the true pose is never behind.
    #[test]
    fn a_lagging_robot_is_seen_and_read_half_way_then_catches_up() {
        let mut cell = perfect_robot_cell();
        cell.imperfections.camera_noise = false;
        cell.imperfections.dropped_points = false;
        cell.imperfections.outliers = false;
        let seed = 17;
        let moves = |step: u32| {
            if step.is_multiple_of(2) {
                Move::default()
            } else {
                zigzag(step)
            }
        };
        let (_, _, clean) = episode(&cell, with_fault(&cell, None), seed, moves, STEPS);
        let options = with_fault(&cell, Some(Fault::RobotLag));
        let (onset, _, records) = episode(&cell, options, seed, moves, STEPS);
        let onset = onset.unwrap();
        let c1_centroid = |frame: &CameraFrame| {
            let points: Vec<_> = frame
                .points
                .iter()
                .filter(|p| p.fixture == Fixture::C1)
                .collect();
            points
                .iter()
                .map(|p| p.position_mm.coords)
                .sum::<Vector3<f64>>()
                / points.len() as f64
        };
        let (mut lagging, mut caught_up) = (0, 0);
        let mut previous_command = None;
        for (i, (a, b)) in clean.iter().zip(&records).enumerate() {
            // The same true pose (a hold and a move of nothing differ by rounding only).
            let apart = (a.true_f_m.inverse() * b.true_f_m)
                .translation
                .vector
                .norm()
                + (a.true_f_m.inverse() * b.true_f_m).rotation.angle();
            assert!(apart < 1e-9, "step {}: {apart}", b.step);
            let last_command = previous_command;
            previous_command = b.result.commanded_legs_mm.or(previous_command);
            let Some(commanded) = b.result.commanded_legs_mm else {
                // The cell held after a lagging move: the robot had arrived, so it was a lag.
                assert_eq!(b.result.detected, Some("robot_lag"), "step {}", b.step);
                caught_up += 1;
                continue;
            };
            let gap = (0..6)
                .map(|leg| (b.result.legs_mm[leg] - commanded[leg]).abs())
                .fold(0.0, f64::max);
            if b.step < onset {
                assert!(a.frame == b.frame);
                assert!(gap < 1e-9);
            } else if !b.step.is_multiple_of(2) {
                // A move: seen and read half-way.
                let previous: [f64; 6] = last_command.unwrap();
                let half = (0..6)
                    .map(|leg| {
                        (b.result.legs_mm[leg] - (previous[leg] + commanded[leg]) / 2.0).abs()
                    })
                    .fold(0.0, f64::max);
                assert!(gap > 1e-3, "step {}: {gap}", b.step);
                assert!(half < 1e-3, "step {}: {half} mm from half-way", b.step);
                let seen = c1_centroid(&b.frame);
                let midway = (c1_centroid(&clean[i - 1].frame) + c1_centroid(&a.frame)) / 2.0;
                assert!((seen - midway).norm() < 1e-9, "step {}", b.step);
                lagging += 1;
            } else {
                // No move: the last one has been completed.
                assert!(gap < 1e-6, "step {}: {gap}", b.step);
                caught_up += 1;
            }
        }
        assert!(lagging >= 5 && caught_up >= 5);
    }

    /// Calibration scale 0 takes the calibration error away; the episode's other draws stay.
    #[test]
    fn calibration_scale_zero_gives_a_robot_that_goes_where_commanded() {
        let mut cell = CellConfig::reference();
        cell.imperfections.execution_error = false;
        let seed = 18;
        let scaled = |scale: f64| EnvOptions {
            calibration_scale: scale,
            ..EnvOptions::from_cell(&cell)
        };
        // Away from the start (where the setpoint was read from the true legs).
        let away = |_| Move::translation(1.0, 0.0, 1.0);
        let (_, _, nominal) = episode(&cell, scaled(1.0), seed, away, 10);
        let (_, _, perfect) = episode(&cell, scaled(0.0), seed, away, 10);
        let (_, _, doubled) = episode(&cell, scaled(2.0), seed, away, 10);
        let mut perfect_cell = perfect_robot_cell();
        perfect_cell.imperfections.execution_error = false;
        let (_, _, reference) = episode(
            &perfect_cell,
            EnvOptions::from_cell(&perfect_cell),
            seed,
            away,
            10,
        );
        let (mut off_nominal, mut off_doubled) = (0.0, 0.0);
        for (((n, p), d), r) in nominal.iter().zip(&perfect).zip(&doubled).zip(&reference) {
            // Without calibration error the legs and the true pose are the perfect robot's.
            let commanded = p.result.commanded_legs_mm.unwrap();
            assert_eq!(p.result.legs_mm, commanded);
            let off =
                |x: &Record| (x.true_f_m.translation.vector - r.true_f_m.translation.vector).norm();
            assert!(off(p) < 1e-9, "step {}: {} mm", p.step, off(p));
            off_nominal += off(n);
            off_doubled += off(d);
        }
        assert!(off_nominal > 1e-3, "{off_nominal}");
        assert!(
            off_doubled > 1.5 * off_nominal,
            "{off_doubled} against {off_nominal}"
        );
    }
}
