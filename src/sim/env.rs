//! `AssemblyEnv`: one episode of the assembly in the digital twin, as `reset` / `step`.
//!
//! Each step is one camera cycle (4 Hz): the move goes to the imperfect robot through the
//! supervisor ([`Supervised`], which checks it against the cell's fused estimate of the relative
//! pose, its uncertainty and the robot's setpoint, and shortens or holds a move it is not sure
//! of); an allowed move is predicted by the state filter; the camera captures (possibly while
//! the robot is still moving, when the move takes longer than the cycle minus the latency);
//! camera ingestion ([`Ingest`]) fits the frame and fuses it into the state; the reward is
//! computed from that state. A robot whose encoders had not reached the last command at the
//! capture is given a step to arrive (a hold). The outcome is judged on the true pose: success
//! when the true insertion depth and hole alignment are within tolerance, failure on true
//! contact (the robot's protective stop), on too many vetoes or uncertain holds in a row, on a
//! fault the cell cannot work around (docs/estimation.md §5), on leaving the workspace, or on
//! running out of steps.

use super::fault::{Fault, Injection};
use super::reward::{Ending, RewardTerms, RewardTracker};
use super::robot::{TwinDrive, TwinRobot};
use crate::camera::ingest::{Detected, Estimate, Ingest, Shot};
use crate::camera::{FusionTuning, SimCamera, StateFilter};
use crate::collision::clearance::PartGeometry;
use crate::collision::obb::Obb;
use crate::collision::supervisor::{Supervisor, VetoReason, swept_clearance};
use crate::config::cell::{CellConfig, CellShape};
use crate::geometry::{Belief, CellFrames, Move, Pose, pose};
use crate::kinematics::KinematicsError;
use crate::robot::{RobotError, Supervised};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;

/// Initial conditions of an episode (docs/design.md §4, Table 5 protocol by default).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct InitialConditions {
    /// Offset of Segment I from the mouth pose (tip centred on the entrance), in a random
    /// direction on the outside half-space.
    pub offset_mm: f64,
    /// Orientation error about a random axis.
    pub orientation_deg: f64,
}

impl InitialConditions {
    pub fn from_cell(cell: &CellConfig) -> Self {
        InitialConditions {
            offset_mm: cell.episode.initial_offset_mm,
            orientation_deg: cell.episode.initial_orientation_deg,
        }
    }
}

/// Why an episode failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureReason {
    /// Too many supervisor vetoes in a row (the paper's 20 collision warnings).
    CollisionLimit,
    /// No success within the episode's step limit.
    StepLimit,
    /// Segment I left the workspace.
    MotionLimit,
    /// Real contact between the parts: the robot's protective stop.
    Contact,
    /// The robot could not execute a move (forward kinematics failed).
    RobotFault,
    /// The cell held for more frames too many times in a row: no move was sure enough to
    /// make (the supervisor's `uncertain` vetoes). The robot holds where it is.
    Uncertain,
    /// The camera's measurement jumped where the robot did not move: knocked out of
    /// calibration. The robot holds.
    CameraShift,
    /// The camera keeps sending the same frame. The robot holds.
    FrozenCamera,
    /// The robot stopped short of its setpoint and stays there. The robot holds.
    RobotShort,
}

impl FailureReason {
    pub fn code(&self) -> &'static str {
        match self {
            FailureReason::CollisionLimit => "collision_limit",
            FailureReason::StepLimit => "step_limit",
            FailureReason::MotionLimit => "motion_limit",
            FailureReason::Contact => "contact",
            FailureReason::RobotFault => "robot_fault",
            FailureReason::Uncertain => "uncertain",
            FailureReason::CameraShift => "camera_shift",
            FailureReason::FrozenCamera => "frozen_camera",
            FailureReason::RobotShort => "robot_short",
        }
    }

    /// The failure a camera fault noticed at a step ends the episode with, if it ends it.
    pub fn of_camera(detected: Option<Detected>) -> Option<FailureReason> {
        match detected {
            Some(Detected::CameraShift) => Some(FailureReason::CameraShift),
            Some(Detected::FrozenCamera) => Some(FailureReason::FrozenCamera),
            _ => None,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Outcome {
    Success,
    Failure(FailureReason),
}

/// What a controller sees before it decides.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    /// The 12-dim state of docs/design.md §5, from the cell's fused estimate (A from the last frame;
    /// P and O from the state filter, see `camera::fusion`).
    pub state: [f64; 12],
    /// The same state from the last camera frame alone.
    pub raw_state: [f64; 12],
    /// A snapshot of the cell's state filter: how sure it is, and the drift it has learned.
    pub estimate: StateFilter,
    /// Steps taken so far in this episode.
    pub step: u32,
    /// False when the last capture could not be used (the state is then the previous one).
    pub measurement_fresh: bool,
    /// The supervisor's veto of the previous move, if it was vetoed (a "collision warning").
    pub last_veto: Option<VetoReason>,
    /// The cell's depth, clearance and hole pitch (what a policy trained across cells reads).
    pub cell: CellShape,
}

impl Observation {
    /// How far the tip is past the bore's entrance by the estimate (mm; negative above it):
    /// P_z counts towards the seat, and the tip is the bore's depth below {M}'s origin at the
    /// shoulder.
    pub fn insertion_mm(&self) -> f64 {
        self.state[8] + self.cell.bore_depth_mm
    }
}

/// True pose errors of Segment I against the goal (only the twin knows them).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct PoseErrors {
    /// Lateral offset of the shoulder centre from the bore axis.
    pub lateral_mm: f64,
    /// Insertion depth minus the bore depth (negative: not deep enough).
    pub depth_error_mm: f64,
    /// Angle between the shaft and bore axes.
    pub tilt_deg: f64,
    /// Offset between matching connecting holes along the hole circle.
    pub hole_arc_mm: f64,
}

/// The result of one step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    pub observation: Observation,
    pub reward: RewardTerms,
    /// The supervisor's veto of this step's move, if any.
    pub veto: Option<VetoReason>,
    /// Leg encoder readings after the step, as the robot reports them (mm).
    pub legs_mm: [f64; 6],
    /// The nominal leg lengths the supervisor let through for this step's move (none: vetoed,
    /// or the robot could not take it).
    pub commanded_legs_mm: Option<[f64; 6]>,
    /// A fault noticed at this step (`occlusion`, `out_of_order`, `robot_lag`,
    /// `camera_shift_suspected`, or the code of the fault the episode ends on).
    pub detected: Option<&'static str>,
    pub done: bool,
    pub outcome: Option<Outcome>,
    pub true_errors: PoseErrors,
    /// The time the step's move was to take at the robot's speeds, s: the step's deadline
    /// allows for it. 0 in the twin, whose moves take no time of the control loop's.
    pub move_time_s: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EnvError {
    #[error("the episode is over; call reset")]
    EpisodeOver,
    #[error("out of order: {0}")]
    OutOfOrder(&'static str),
    #[error("initial pose unreachable: {0}")]
    Unreachable(KinematicsError),
}

/// Captures an episode's start may take to get a usable frame (dropped points).
const START_CAPTURE_TRIES: u32 = 10;

/// The cell waits for a usable frame before an episode starts; a few tries cover dropped
/// points. `capture_and_ingest(first)` takes one still capture (`first`: the episode's first)
/// and answers ingestion's estimate of it. With no usable frame the last estimate is returned
/// (its state all zeros).
pub fn first_usable_estimate<E>(
    mut capture_and_ingest: impl FnMut(bool) -> Result<Estimate, E>,
) -> Result<Estimate, E> {
    let mut estimate = capture_and_ingest(true)?;
    for _ in 1..START_CAPTURE_TRIES {
        if estimate.fresh {
            break;
        }
        estimate = capture_and_ingest(false)?;
    }
    Ok(estimate)
}

/// What a move did, between a backend's `act` and its `settle` (the twin's
/// [`AssemblyEnv::act`] and [`AssemblyEnv::settle`], and the driver backend's).
#[derive(Debug, Clone, Default)]
pub(crate) struct PendingMove {
    pub(crate) executed: Option<Move>,
    pub(crate) veto: Option<VetoReason>,
    pub(crate) failure: Option<FailureReason>,
    pub(crate) commanded_legs_mm: Option<[f64; 6]>,
    pub(crate) detected: Option<&'static str>,
}

/// Largest difference (mm) between a leg's reading and its command that counts as arrived:
/// 20 times the reference robot's leg resolution and random error.
const LEG_ARRIVAL_MM: f64 = 0.01;

/// Whether `encoders` are within [`LEG_ARRIVAL_MM`] of `command`.
fn arrived(encoders: &[f64; 6], command: &[f64; 6]) -> bool {
    encoders
        .iter()
        .zip(command)
        .all(|(e, c)| (e - c).abs() <= LEG_ARRIVAL_MM)
}

/// Options that are not part of the cell file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvOptions {
    /// Multiplies the camera's point noise (1 = the spec).
    pub noise_scale: f64,
    /// Multiplies the radius of the ball the robot's true joint centres are drawn in
    /// (`imperfections.calibration_error_mm`; 1 = the cell file's, 0 = perfect calibration).
    pub calibration_scale: f64,
    /// A fault injected mid-episode (`sim::fault`), none by default.
    pub fault: Option<Fault>,
    pub initial: InitialConditions,
    /// 0: every episode has a robot the cell has never seen (a new calibration error), and the
    /// cell remembers nothing of the last one. n ≥ 1: the cell keeps its robot, drawn from
    /// `robot_seed`, and starts each episode from the drift it learned in the ones before
    /// (docs/estimation.md §3a); an evaluation shares its episodes among n such robots.
    pub kept_robots: u32,
    /// Which robot is kept (with `kept_robots` ≥ 1).
    pub robot_seed: u64,
}

impl EnvOptions {
    pub fn from_cell(cell: &CellConfig) -> Self {
        EnvOptions {
            noise_scale: 1.0,
            calibration_scale: 1.0,
            fault: None,
            initial: InitialConditions::from_cell(cell),
            kept_robots: 0,
            robot_seed: 0,
        }
    }
}

/// Camera ingestion for a twin with `options`: remembering the robot's drift when the robot is
/// kept. Whoever runs ingestion outside the twin (the service's `TwinBackend`) builds it here
/// too, so that it matches the twin's robot.
pub fn ingest_for(cell: &CellConfig, frames: &CellFrames, options: &EnvOptions) -> Ingest {
    let ingest = Ingest::new(cell, frames);
    if options.kept_robots > 0 {
        ingest.remembering_drift()
    } else {
        ingest
    }
}

/// The digital twin of one cell, running one episode at a time. Deterministic under a seed.
#[derive(Debug, Clone)]
pub struct AssemblyEnv {
    cell: CellConfig,
    options: EnvOptions,
    frames: CellFrames,
    parts: PartGeometry,
    bore_obb: Obb,
    supervisor: Supervisor,
    robot: TwinRobot,
    camera: SimCamera,
    /// Camera ingestion, run inline by [`AssemblyEnv::step`].
    ingest: Ingest,
    /// The last capture, reused from step to step.
    shot: Shot,
    /// The episode's one random stream: initial pose, calibration, then per step the robot's
    /// leg errors and the camera's noise, in that order.
    rng: ChaCha8Rng,
    /// The episode's fault, drawn from a stream of its own (`sim::fault`).
    injection: Option<Injection>,
    /// Captures so far in this episode (each frame's sequence number).
    captures: u64,
    // Episode state.
    step: u32,
    /// Vetoes in a row for contact, reach or limits (the paper's collision warnings).
    consecutive_vetoes: u32,
    /// Holds in a row because no move was sure enough (`uncertain` vetoes).
    uncertain_holds: u32,
    /// The legs commanded by the last move, when the encoders had not reached them at its
    /// capture.
    unarrived: Option<[f64; 6]>,
    /// The fused estimate of {F} in {M} the supervisor judges the next move against (a snapshot
    /// of the state filter; none when the last capture could not be used).
    belief: Option<StateFilter>,
    /// The last episode ended in contact or a robot fault: the next one tells ingestion to
    /// forget what it remembers of the robot's drift.
    robot_suspect: bool,
    /// What [`AssemblyEnv::act`] found, until [`AssemblyEnv::settle`].
    pending: Option<PendingMove>,
    observation: Observation,
    reward: Option<RewardTracker>,
    outcome: Option<Outcome>,
}

impl AssemblyEnv {
    pub fn new(cell: &CellConfig, options: EnvOptions) -> Self {
        let frames = CellFrames::from_config(cell);
        let parts = PartGeometry::from_config(cell);
        let mut robot = TwinRobot::new(cell).with_calibration_scale(options.calibration_scale);
        if options.kept_robots > 0 {
            robot = robot.with_kept_calibration(options.robot_seed);
        }
        AssemblyEnv {
            camera: SimCamera::new(cell, &frames, options.noise_scale),
            ingest: ingest_for(cell, &frames, &options),
            supervisor: Supervisor::new(cell),
            robot,
            bore_obb: parts.bore_obb(),
            parts,
            frames,
            cell: cell.clone(),
            options,
            shot: Shot::default(),
            rng: ChaCha8Rng::seed_from_u64(0),
            injection: None,
            captures: 0,
            step: 0,
            consecutive_vetoes: 0,
            uncertain_holds: 0,
            unarrived: None,
            belief: None,
            robot_suspect: false,
            pending: None,
            observation: Observation {
                state: [0.0; 12],
                raw_state: [0.0; 12],
                estimate: StateFilter::new(FusionTuning::default()),
                step: 0,
                measurement_fresh: false,
                last_veto: None,
                cell: cell.shape(),
            },
            reward: None,
            outcome: Some(Outcome::Failure(FailureReason::StepLimit)),
        }
    }

    /// Puts another robot in the cell from the next episode on, kept and drawn from `seed`,
    /// without telling the cell: what it remembers of the last robot's drift is now wrong (a
    /// robot replaced or knocked between jobs).
    pub fn swap_robot(&mut self, seed: u64) {
        self.robot = self.robot.clone().with_kept_calibration(seed);
    }

    /// The next episode forgets what the cell remembers of its robot's drift: the robot may
    /// have been serviced or moved by hand (an operator's reset after an e-stop).
    pub fn forget_robot(&mut self) {
        self.robot_suspect = true;
    }

    /// What the cell remembers of its robot's drift (with kept robots, after the first episode).
    pub fn drift_memory(&self) -> Option<&crate::camera::DriftKnowledge> {
        self.ingest.drift_memory()
    }

    pub fn cell(&self) -> &CellConfig {
        &self.cell
    }

    pub fn options(&self) -> &EnvOptions {
        &self.options
    }

    /// Starts a new episode with the options' initial conditions.
    pub fn reset(&mut self, seed: u64) -> Result<Observation, EnvError> {
        self.reset_with(seed, self.options.initial)
    }

    /// Starts a new episode: Segment I at the given offset and orientation error from the mouth
    /// pose, drawn from `seed`.
    pub fn reset_with(
        &mut self,
        seed: u64,
        initial: InitialConditions,
    ) -> Result<Observation, EnvError> {
        self.begin_episode(seed, initial)?;
        let Ok(estimate) = first_usable_estimate(|first| {
            self.capture_still(first);
            Ok::<_, std::convert::Infallible>(self.ingest.take(&self.shot))
        });
        Ok(self.start_from(&estimate))
    }

    /// Executes one move (or has it vetoed) and returns what follows: [`AssemblyEnv::act`],
    /// ingestion of its capture, then [`AssemblyEnv::settle`].
    pub fn step(&mut self, action: &Move) -> Result<StepResult, EnvError> {
        self.act(action)?;
        let estimate = self.ingest.take(&self.shot);
        self.settle(&estimate)
    }

    /// The first part of a reset, for a caller that runs camera ingestion itself: draws the
    /// episode from `seed` and puts Segment I there. Then [`AssemblyEnv::capture_still`] until
    /// ingestion has a usable frame (or gives up), then [`AssemblyEnv::start_from`].
    pub fn begin_episode(&mut self, seed: u64, initial: InitialConditions) -> Result<(), EnvError> {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.captures = 0;
        self.injection = self.options.fault.map(|fault| {
            let centroid = super::fault::c2_centroid_w(&self.frames);
            Injection::draw(fault, seed, centroid, self.frames.c2_points_mm.len())
        });
        self.robot.set_faults(Default::default());
        let f_m = self.sample_initial(initial);
        self.robot
            .reset(self.frames.platform_for(&f_m), &mut self.rng)
            .map_err(EnvError::Unreachable)?;
        self.step = 0;
        self.consecutive_vetoes = 0;
        self.uncertain_holds = 0;
        self.unarrived = None;
        self.outcome = None;
        self.pending = None;
        self.reward = None;
        Ok(())
    }

    /// A capture with the robot still; `new_episode` on the first of an episode.
    pub fn capture_still(&mut self, new_episode: bool) -> &Shot {
        let platform = *self.robot.true_platform();
        self.capture(&platform, None, None);
        self.shot.new_episode = new_episode;
        self.shot.forget_robot = new_episode && std::mem::take(&mut self.robot_suspect);
        &self.shot
    }

    /// Ends a reset with ingestion's estimate of the last capture: the episode's first
    /// observation.
    pub fn start_from(&mut self, estimate: &Estimate) -> Observation {
        self.observe(estimate);
        self.observation.step = 0;
        self.observation.last_veto = None;
        self.reward = Some(RewardTracker::new(
            &self.cell.reward,
            &self.observation.state,
        ));
        self.observation.clone()
    }

    /// The first part of a step, for a caller that runs camera ingestion itself: the move goes
    /// to the robot through the supervisor, then the camera captures. Hand the shot to
    /// ingestion and its estimate to [`AssemblyEnv::settle`].
    pub fn act(&mut self, action: &Move) -> Result<&Shot, EnvError> {
        if self.outcome.is_some() {
            return Err(EnvError::EpisodeOver);
        }
        if self.reward.is_none() {
            return Err(EnvError::OutOfOrder(
                "act before the episode's first estimate",
            ));
        }
        if self.pending.is_some() {
            return Err(EnvError::OutOfOrder("act before the last move was settled"));
        }
        self.step += 1;
        // A lagging robot has completed its last move by now.
        self.robot.catch_up();
        if let Some(injection) = &self.injection {
            self.robot.set_faults(injection.robot_faults(self.step));
        }
        let before = *self.robot.true_platform();
        let mut pending = PendingMove::default();
        let mut capture_fraction = 1.0;
        let mut executed = *action;
        // A robot that had not reached its last setpoint at the capture: arrived since (it
        // lags: hold one step, so the next frame sees it still) or still short (end, holding).
        let hold = match self.unarrived.take() {
            None => false,
            Some(command) if arrived(self.robot.encoders_mm(), &command) => {
                pending.detected = Some("robot_lag");
                true
            }
            Some(_) => {
                pending.detected = Some(FailureReason::RobotShort.code());
                pending.failure = Some(FailureReason::RobotShort);
                true
            }
        };
        let mut robot = Supervised::new(
            &self.supervisor,
            TwinDrive {
                robot: &mut self.robot,
                rng: &mut self.rng,
            },
        );
        let belief = self.belief.as_ref().and_then(StateFilter::belief);
        robot.observe(belief.as_ref().map(|b| b as &dyn Belief));
        // A hold sends the robot nothing.
        let verdict = (!hold).then(|| robot.execute_cautiously(action));
        match verdict {
            None => {}
            Some(Ok(step)) => {
                executed = step;
                self.consecutive_vetoes = 0;
                self.uncertain_holds = 0;
                pending.executed = Some(executed);
                pending.commanded_legs_mm = self.robot.commanded_mm().copied();
                let after = *self.robot.true_platform();
                let path = swept_clearance(
                    &self.parts,
                    &self.bore_obb,
                    &self.frames.segment_for(&before),
                    &self.frames.segment_for(&after),
                );
                if !path.is_clear() {
                    pending.failure = Some(FailureReason::Contact);
                }
                capture_fraction = self.capture_fraction(&executed);
            }
            Some(Err(RobotError::Vetoed(reason @ VetoReason::Uncertain { .. }))) => {
                self.uncertain_holds += 1;
                pending.veto = Some(reason);
            }
            Some(Err(RobotError::Vetoed(reason))) => {
                self.consecutive_vetoes += 1;
                self.uncertain_holds = 0;
                pending.veto = Some(reason);
            }
            Some(Err(RobotError::Fault(_))) => {
                self.consecutive_vetoes = 0;
                pending.failure = Some(FailureReason::RobotFault);
            }
        }
        let after = *self.robot.true_platform();
        let lag = self
            .robot
            .faults()
            .lag_fraction
            .filter(|_| pending.executed.is_some());
        let seen = pose::interpolate(&before, &after, capture_fraction * lag.unwrap_or(1.0));
        if lag.is_some() {
            self.robot.report_lagging_at(&seen);
        }
        if let Some(command) = pending.commanded_legs_mm
            && !arrived(self.robot.encoders_mm(), &command)
        {
            self.unarrived = Some(command);
        }
        // The part of the commanded move still to come after the capture, in {M}.
        let remaining = (capture_fraction < 1.0).then(|| {
            let commanded = executed.as_pose();
            pose::interpolate(&Pose::identity(), &commanded, capture_fraction).inverse() * commanded
        });
        self.capture(&seen, pending.executed, remaining);
        self.shot.new_episode = false;
        self.pending = Some(pending);
        Ok(&self.shot)
    }

    /// The second part of a step: takes ingestion's estimate of the shot [`AssemblyEnv::act`]
    /// took, judges the outcome on the true pose and computes the reward.
    pub fn settle(&mut self, estimate: &Estimate) -> Result<StepResult, EnvError> {
        let pending = self.pending.take().ok_or(EnvError::OutOfOrder(
            "settle without a move; call act first",
        ))?;
        self.observe(estimate);
        let true_f_m = self.true_f_m();
        let errors = self.pose_errors(&true_f_m);
        let camera_failure = FailureReason::of_camera(estimate.detected);
        let detected = pending.detected.or(estimate.detected.map(|d| d.code()));
        let outcome = if let Some(reason) = pending.failure.or(camera_failure) {
            Some(Outcome::Failure(reason))
        } else if self.is_success(&errors) {
            Some(Outcome::Success)
        } else if self.consecutive_vetoes >= self.cell.episode.max_consecutive_vetoes {
            Some(Outcome::Failure(FailureReason::CollisionLimit))
        } else if self.uncertain_holds >= self.cell.supervisor.max_uncertain_holds {
            Some(Outcome::Failure(FailureReason::Uncertain))
        } else if self.outside_workspace(&true_f_m, &errors) {
            Some(Outcome::Failure(FailureReason::MotionLimit))
        } else if self.step >= self.cell.episode.max_steps {
            Some(Outcome::Failure(FailureReason::StepLimit))
        } else {
            None
        };
        self.outcome = outcome;
        // A robot that hit something or faulted may no longer be the robot the cell learned.
        self.robot_suspect |= matches!(
            outcome,
            Some(Outcome::Failure(
                FailureReason::Contact | FailureReason::RobotFault | FailureReason::RobotShort
            ))
        );
        let ending = outcome.map(|o| match o {
            Outcome::Success => Ending::Success,
            Outcome::Failure(_) => Ending::Failure,
        });
        self.observation.step = self.step;
        self.observation.last_veto = pending.veto.clone();
        let tip_in_bore = self.estimated_tip_in_bore();
        let reward = self.reward.as_mut().expect("reset before step").step(
            &self.observation.state,
            tip_in_bore,
            ending,
        );
        Ok(StepResult {
            observation: self.observation.clone(),
            reward,
            veto: pending.veto,
            legs_mm: *self.robot.encoders_mm(),
            commanded_legs_mm: pending.commanded_legs_mm,
            detected,
            done: outcome.is_some(),
            outcome,
            true_errors: errors,
            move_time_s: 0.0,
        })
    }

    /// The latest observation.
    pub fn observation(&self) -> &Observation {
        &self.observation
    }

    /// The episode's outcome, once it has one.
    pub fn outcome(&self) -> Option<Outcome> {
        self.outcome
    }

    /// The true pose of {M} in {F} (the twin's ground truth; a real cell has no such thing).
    pub fn true_f_m(&self) -> Pose {
        self.frames.segment_for(self.robot.true_platform())
    }

    /// The 12-dim state (docs/design.md §5) of the true pose: what a perfect camera would
    /// report. Only the twin has it; TD3's critics read it while training.
    pub fn true_state(&self) -> [f64; 12] {
        let (w_m, w_f) = self.frames.world_poses(self.robot.true_platform());
        crate::camera::state_vector(&w_m, &(w_m.inverse() * w_f), self.cell.hole_pitch_deg())
    }

    /// True errors against the goal.
    pub fn true_errors(&self) -> PoseErrors {
        self.pose_errors(&self.true_f_m())
    }

    pub fn steps(&self) -> u32 {
        self.step
    }

    /// The legs' encoder readings as the robot reports them now (mm).
    pub fn encoders_mm(&self) -> [f64; 6] {
        *self.robot.encoders_mm()
    }

    /// The step this episode's fault starts at (none without a fault).
    pub fn fault_onset(&self) -> Option<u32> {
        self.injection.as_ref().map(Injection::onset)
    }

    /// Where the capture happens along the move just executed: the camera takes its picture
    /// `latency_s` before the next decision, so a move longer than the cycle minus the latency
    /// is seen part-way.
    fn capture_fraction(&self, action: &Move) -> f64 {
        if !self.cell.imperfections.latency {
            return 1.0;
        }
        let duration = action.duration_s(self.cell.robot.speed_mm_s, self.cell.robot.speed_deg_s);
        let available = 1.0 / self.cell.camera.rate_hz - self.cell.camera.latency_s;
        if duration <= available {
            1.0
        } else {
            (available / duration).clamp(0.0, 1.0)
        }
    }

    /// Captures the scene with the platform at `platform` into the shot. A capture taken while
    /// the robot was still moving is carried forward by ingestion by the rest of the commanded
    /// move (`remaining`, in {M}), as the cell does with the robot's own motion; what is left
    /// of the latency is the difference between the commanded and the true motion.
    fn capture(&mut self, platform: &Pose, executed: Option<Move>, remaining: Option<Pose>) {
        let (w_m, w_f) = self.frames.world_poses(platform);
        self.camera
            .capture_into(&w_m, &w_f, &mut self.rng, &mut self.shot.frame);
        self.captures += 1;
        self.shot.frame.sequence = self.captures;
        if let Some(injection) = &mut self.injection {
            injection.deliver(self.step, &mut self.shot.frame);
        }
        self.shot.executed = executed;
        self.shot.remaining = remaining;
    }

    /// Takes in ingestion's estimate: the state the controller sees and the supervisor uses.
    fn observe(&mut self, estimate: &Estimate) {
        self.observation.state = estimate.state;
        self.observation.raw_state = estimate.raw_state;
        self.observation.estimate = estimate.filter;
        self.observation.measurement_fresh = estimate.fresh;
        self.belief = estimate.m_f.is_some().then_some(estimate.filter);
    }

    fn estimated_tip_in_bore(&self) -> bool {
        self.belief.and_then(|b| b.m_f()).is_some_and(|m_f| {
            let tip = m_f.inverse() * Point3::new(0.0, 0.0, -self.parts.shaft_length_mm);
            tip.z < 0.0
        })
    }

    fn pose_errors(&self, f_m: &Pose) -> PoseErrors {
        let tip = f_m * Point3::new(0.0, 0.0, -self.parts.shaft_length_mm);
        let axis = f_m.rotation * Vector3::z();
        let q = f_m.rotation.quaternion();
        // Twist about the bore axis (swing-twist decomposition), wrapped to the hole pitch.
        let twist_deg = (2.0 * q.k.atan2(q.w)).to_degrees();
        let pitch = self.cell.hole_pitch_deg();
        let wrapped = (twist_deg + pitch / 2.0).rem_euclid(pitch) - pitch / 2.0;
        PoseErrors {
            lateral_mm: f_m.translation.vector.xy().norm(),
            depth_error_mm: -tip.z - self.cell.bore.depth_mm,
            tilt_deg: axis.z.clamp(-1.0, 1.0).acos().to_degrees(),
            hole_arc_mm: self.parts.bore_radius_mm * wrapped.abs().to_radians(),
        }
    }

    fn is_success(&self, errors: &PoseErrors) -> bool {
        errors.depth_error_mm.abs() <= self.cell.success.depth_tolerance_mm
            && errors.hole_arc_mm <= self.cell.success.hole_arc_tolerance_mm
    }

    fn outside_workspace(&self, f_m: &Pose, errors: &PoseErrors) -> bool {
        f_m.translation.vector.norm() > self.cell.episode.workspace_radius_mm
            || errors.tilt_deg > self.cell.episode.workspace_tilt_deg
    }

    fn sample_initial(&mut self, initial: InitialConditions) -> Pose {
        sample_initial(
            &mut self.rng,
            &self.parts,
            self.cell.episode.initial_min_clearance_mm,
            initial,
        )
    }
}

/// Draws the initial pose of {M} in {F}: the mouth pose (tip centred on the entrance) moved by
/// `offset_mm` in a random direction of the outside half-space and turned by `orientation_deg`
/// about a random axis. If that would put the shaft into Segment II, it is moved out along the
/// bore axis until its lowest point clears the entrance face by `min_clearance_mm`. The twin
/// and the twin-server's rig draw their episodes with it.
pub(crate) fn sample_initial(
    rng: &mut impl Rng,
    parts: &PartGeometry,
    min_clearance_mm: f64,
    initial: InitialConditions,
) -> Pose {
    let direction = random_unit(rng);
    let offset = Vector3::new(direction.x, direction.y, direction.z.abs()) * initial.offset_mm;
    let axis = random_unit(rng);
    let rotation = UnitQuaternion::from_scaled_axis(axis * initial.orientation_deg.to_radians());
    let length = parts.shaft_length_mm;
    let mut f_m = Isometry3::from_parts(
        Translation3::from(Vector3::new(0.0, 0.0, length) + offset),
        rotation,
    );
    let tip_centre = f_m * Point3::new(0.0, 0.0, -length);
    let normal = f_m.rotation * Vector3::z();
    let lowest = tip_centre.z - parts.shaft_radius_mm * (1.0 - normal.z * normal.z).max(0.0).sqrt();
    if lowest < min_clearance_mm {
        f_m.translation.vector.z += min_clearance_mm - lowest;
    }
    f_m
}

/// A direction drawn uniformly on the unit sphere.
pub(crate) fn random_unit(rng: &mut impl Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::<f64>::from_fn(|_, _| rng.sample(StandardNormal));
        let norm = v.norm();
        if norm > 1e-9 {
            return v / norm;
        }
    }
}
