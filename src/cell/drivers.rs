//! [`DriverBackend`]: a real cell behind the backend seam: a PI hexapod over GCS
//! ([`GcsRobot`], behind the collision supervisor) and an OpenIGTLink camera whose frames go
//! through camera ingestion's thread, the same fit, fusion and supervisor as the twin's.
//!
//! A step: the supervised move goes to the controller and the driver waits until it is on
//! target; then the camera captures (the robot still, so nothing remains of the move), and
//! ingestion starts on the frame. The episode is judged as the twin judges it, on the fused
//! estimate instead of a truth the cell does not have ([`Judge`]). Faults end in a named
//! reason: a drive error is a `robot_fault` step whose `detected` names it
//! (`controller_dropped`, `on_target_deadline`, …); a camera that is silent, drops or sends
//! garbage gives a frame with no points (the supervisor then vetoes every move, and the job
//! ends `stale_camera`), named the same way (`camera_silent`, `camera_garbage`, …).

use super::backend::{BackendError, CellBackend, DriverLatch, EmergencyStop};
use super::ingestion::Ingestion;
use crate::camera::ingest::{Estimate, Ingest, Shot};
use crate::camera::{CameraFrame, StateFilter};
use crate::collision::supervisor::{Supervisor, VetoReason};
use crate::config::cell::CellConfig;
use crate::drivers::DriverObserver;
use crate::drivers::gcs::{GcsError, GcsRobot, GcsSettings};
use crate::drivers::igtl::camera::{CameraSettings, IgtlCamera};
use crate::geometry::{Belief, CellFrames, Move};
use crate::kinematics::StewartGeometry;
use crate::robot::{Robot, RobotError, RobotFault, Supervised};
use crate::sim::env::{PendingMove, first_usable_estimate};
use crate::sim::judge::Judge;
use crate::sim::reward::{Ending, RewardTracker};
use crate::sim::{
    EnvError, FailureReason, InitialConditions, Observation, Outcome, PoseErrors, StepResult,
};
use std::sync::Arc;
use std::time::UNIX_EPOCH;

/// Where the drivers find the hardware, and how long they wait for it.
#[derive(Debug, Clone, PartialEq)]
pub struct DriverSettings {
    /// The controller, `host:port`.
    pub robot_address: String,
    pub robot: GcsSettings,
    /// The camera's OpenIGTLink server, `host:port`.
    pub camera_address: String,
    pub camera: CameraSettings,
    /// The controller is `celld twin-server`: each start draws the job's episode there.
    pub rehearsal: bool,
}

/// One episode's counters and state.
struct Episode {
    step: u32,
    consecutive_vetoes: u32,
    uncertain_holds: u32,
    belief: Option<StateFilter>,
    observation: Observation,
    reward: RewardTracker,
    errors: PoseErrors,
    pending: Option<PendingMove>,
    over: bool,
}

/// A real cell: the GCS robot, the OpenIGTLink camera, camera ingestion on its thread.
pub struct DriverBackend {
    cell: CellConfig,
    settings: DriverSettings,
    supervisor: Supervisor,
    nominal: StewartGeometry,
    frames: CellFrames,
    judge: Judge,
    robot: GcsRobot,
    camera: Option<IgtlCamera>,
    ingestion: Ingestion,
    /// Sequence numbers of earlier connections' frames, so a reconnected camera's continue.
    sequence_base: u64,
    last_sequence: u64,
    awaiting_estimate: bool,
    episode: Option<Episode>,
    /// Reset after an e-stop or a fault since the last episode (see `reset`).
    robot_suspect: bool,
    observer: Arc<dyn DriverObserver>,
}

impl DriverBackend {
    /// Connects to the controller (checking it is referenced with its servos on) and to the
    /// camera. Ingestion keeps to `cpu` when given.
    pub fn connect(
        cell: &CellConfig,
        settings: DriverSettings,
        cpu: Option<usize>,
    ) -> Result<DriverBackend, BackendError> {
        let frames = CellFrames::from_config(cell);
        let robot = GcsRobot::connect(&settings.robot_address, settings.robot, cell)?;
        let camera = IgtlCamera::connect(&settings.camera_address, settings.camera, &frames)?;
        Ok(DriverBackend {
            supervisor: Supervisor::new(cell),
            nominal: StewartGeometry::from_config(&cell.robot),
            judge: Judge::new(cell),
            // One robot, kept: each job starts from the drift the ones before learned.
            ingestion: Ingestion::spawn(Ingest::new(cell, &frames).remembering_drift(), cpu),
            frames,
            robot,
            camera: Some(camera),
            cell: cell.clone(),
            settings,
            sequence_base: 0,
            last_sequence: 0,
            awaiting_estimate: false,
            episode: None,
            robot_suspect: false,
            observer: Arc::new(crate::drivers::Unobserved),
        })
    }

    /// Reports the drivers' figures (round trips, frame ages, reconnections) to `observer`.
    pub fn observed_by(mut self, observer: Arc<dyn DriverObserver>) -> Self {
        self.robot.observe_with(observer.clone());
        self.observer = observer;
        self
    }

    pub fn robot(&self) -> &GcsRobot {
        &self.robot
    }

    /// One capture; a camera fault gives a frame with no points (numbered as the last, so
    /// ingestion takes it as unusable, not as out of order) and its name.
    fn capture(&mut self) -> (CameraFrame, Option<&'static str>) {
        if self.camera.is_none() {
            match IgtlCamera::connect(
                &self.settings.camera_address,
                self.settings.camera,
                &self.frames,
            ) {
                Ok(camera) => {
                    self.sequence_base = self.last_sequence;
                    self.camera = Some(camera);
                    self.observer.reconnected("camera");
                }
                Err(error) => {
                    tracing::warn!(%error, "camera");
                    return (self.empty_frame(), Some(error.code()));
                }
            }
        }
        let camera = self.camera.as_mut().expect("connected above");
        match camera.capture() {
            Ok(mut frame) => {
                if let Some(age_ms) = camera.frame_age_ms() {
                    self.observer.camera_frame_age(age_ms / 1e3);
                }
                frame.sequence += self.sequence_base;
                self.last_sequence = self.last_sequence.max(frame.sequence);
                (frame, None)
            }
            Err(error) => {
                tracing::warn!(%error, "camera");
                if error.ends_connection() {
                    self.camera = None;
                }
                (self.empty_frame(), Some(error.code()))
            }
        }
    }

    fn empty_frame(&self) -> CameraFrame {
        CameraFrame {
            points: Vec::new(),
            sequence: self.last_sequence,
            ..CameraFrame::default()
        }
    }

    fn episode(&mut self) -> Result<&mut Episode, BackendError> {
        self.episode
            .as_mut()
            .ok_or(EnvError::OutOfOrder("act before the episode's first estimate").into())
    }
}

/// The name of a robot fault for a step's `detected`.
fn fault_code(fault: &RobotFault) -> &'static str {
    match fault {
        RobotFault::Kinematics(_) => "unreachable",
        RobotFault::Drive(error) => error.code(),
    }
}

impl CellBackend for DriverBackend {
    fn name(&self) -> &str {
        "drivers"
    }

    fn start(
        &mut self,
        seed: u64,
        initial: InitialConditions,
    ) -> Result<Observation, BackendError> {
        if std::mem::take(&mut self.awaiting_estimate) {
            self.ingestion.receive()?;
        }
        self.episode = None;
        if let Some(latch) = self.robot.latched() {
            return Err(GcsError::AwaitingReset {
                cause: latch.error.to_string(),
            }
            .into());
        }
        if self.settings.rehearsal {
            self.robot
                .rehearse(seed, initial.offset_mm, initial.orientation_deg)?;
        } else {
            self.robot.refresh()?;
        }
        if let Some(camera) = &mut self.camera {
            camera.restart();
        }
        self.sequence_base = 0;
        self.last_sequence = 0;
        let estimate = first_usable_estimate(|first| {
            let (frame, _) = self.capture();
            self.ingestion.take(Shot {
                new_episode: first,
                forget_robot: first && std::mem::take(&mut self.robot_suspect),
                executed: None,
                remaining: None,
                frame,
            })
        })?;
        let observation = Observation {
            state: estimate.state,
            raw_state: estimate.raw_state,
            estimate: estimate.filter,
            step: 0,
            measurement_fresh: estimate.fresh,
            last_veto: None,
            cell: self.cell.shape(),
        };
        self.episode = Some(Episode {
            step: 0,
            consecutive_vetoes: 0,
            uncertain_holds: 0,
            belief: estimate.m_f.is_some().then_some(estimate.filter),
            reward: RewardTracker::new(&self.cell.reward, &observation.state),
            errors: estimate
                .m_f
                .map(|m_f| self.judge.errors(&m_f.inverse()))
                .unwrap_or_default(),
            observation: observation.clone(),
            pending: None,
            over: false,
        });
        Ok(observation)
    }

    fn act(&mut self, action: &Move) -> Result<(), BackendError> {
        let episode = self.episode()?;
        if episode.over {
            return Err(EnvError::EpisodeOver.into());
        }
        if episode.pending.is_some() {
            return Err(EnvError::OutOfOrder("act before the last move was settled").into());
        }
        episode.step += 1;
        let episode = self.episode.as_mut().expect("checked above");
        let mut pending = PendingMove::default();
        let mut robot = Supervised::new(&self.supervisor, &mut self.robot);
        let belief = episode.belief.as_ref().and_then(StateFilter::belief);
        robot.observe(belief.as_ref().map(|b| b as &dyn Belief));
        match robot.execute_cautiously(action) {
            Ok(step) => {
                episode.consecutive_vetoes = 0;
                episode.uncertain_holds = 0;
                pending.executed = Some(step);
                pending.commanded_legs_mm = Some(self.nominal.leg_lengths_mm(&robot.setpoint()));
            }
            Err(RobotError::Vetoed(reason @ VetoReason::Uncertain { .. })) => {
                episode.uncertain_holds += 1;
                pending.veto = Some(reason);
            }
            Err(RobotError::Vetoed(reason)) => {
                episode.consecutive_vetoes += 1;
                episode.uncertain_holds = 0;
                pending.veto = Some(reason);
            }
            Err(RobotError::Fault(fault)) => {
                tracing::warn!(%fault, "robot");
                episode.consecutive_vetoes = 0;
                pending.failure = Some(FailureReason::RobotFault);
                pending.detected = Some(fault_code(&fault));
            }
        }
        let (frame, camera_fault) = self.capture();
        let episode = self.episode.as_mut().expect("checked above");
        pending.detected = pending.detected.or(camera_fault);
        let executed = pending.executed;
        episode.pending = Some(pending);
        self.ingestion.send(Shot {
            new_episode: false,
            forget_robot: false,
            executed,
            remaining: None,
            frame,
        })?;
        self.awaiting_estimate = true;
        Ok(())
    }

    fn settle(&mut self) -> Result<StepResult, BackendError> {
        if !std::mem::take(&mut self.awaiting_estimate) {
            return Err(EnvError::OutOfOrder("settle without a move; call act first").into());
        }
        let estimate = self.ingestion.receive()?;
        let legs_mm = self.robot.encoders_mm();
        let move_time_s = self.robot.last_move_time_s();
        let Some(episode) = self.episode.as_mut() else {
            return Err(EnvError::OutOfOrder("settle before the episode's start").into());
        };
        let pending = episode.pending.take().ok_or(EnvError::OutOfOrder(
            "settle without a move; call act first",
        ))?;
        Ok(judge_step(
            &self.cell,
            &self.judge,
            episode,
            pending,
            &estimate,
            legs_mm,
            move_time_s,
        ))
    }

    fn hold(&mut self) {
        self.robot.hold();
    }

    fn emergency_stop(&self) -> Option<EmergencyStop> {
        let stop = self.robot.emergency_stop();
        Some(std::sync::Arc::new(move || {
            if !stop() {
                tracing::warn!("e-stop: STP could not be written; the control thread holds");
            }
        }))
    }

    /// The operator's reset: the robot driver reconnects if it must, checks the controller
    /// and unlatches. After an e-stop or a latched fault the robot may have hit something or
    /// been moved by hand, so the next episode forgets what the cell remembers of its drift.
    fn reset(&mut self) -> Result<(), BackendError> {
        self.robot_suspect = true;
        Ok(self.robot.reset()?)
    }

    fn latch(&self) -> Option<DriverLatch> {
        self.robot.latched().map(|latch| DriverLatch {
            code: latch.error.code().to_string(),
            reason: latch.error.to_string(),
            since_unix_ms: latch
                .since
                .duration_since(UNIX_EPOCH)
                .map_or(0, |since| since.as_millis() as u64),
        })
    }

    fn watch(&mut self) {
        self.robot.watch();
    }
}

/// Takes in a step's estimate and judges it as the twin does, on the estimate.
fn judge_step(
    cell: &CellConfig,
    judge: &Judge,
    episode: &mut Episode,
    pending: PendingMove,
    estimate: &Estimate,
    legs_mm: [f64; 6],
    move_time_s: f64,
) -> StepResult {
    let observation = &mut episode.observation;
    observation.state = estimate.state;
    observation.raw_state = estimate.raw_state;
    observation.estimate = estimate.filter;
    observation.measurement_fresh = estimate.fresh;
    observation.step = episode.step;
    observation.last_veto = pending.veto.clone();
    episode.belief = estimate.m_f.is_some().then_some(estimate.filter);
    let f_m = estimate.m_f.map(|m_f| m_f.inverse());
    if let Some(f_m) = &f_m {
        episode.errors = judge.errors(f_m);
    }
    let errors = episode.errors;
    let camera_failure = FailureReason::of_camera(estimate.detected);
    let detected = pending.detected.or(estimate.detected.map(|d| d.code()));
    let outcome = if let Some(reason) = pending.failure.or(camera_failure) {
        Some(Outcome::Failure(reason))
    } else if f_m.is_some() && judge.is_success(&errors) {
        Some(Outcome::Success)
    } else if episode.consecutive_vetoes >= cell.episode.max_consecutive_vetoes {
        Some(Outcome::Failure(FailureReason::CollisionLimit))
    } else if episode.uncertain_holds >= cell.supervisor.max_uncertain_holds {
        Some(Outcome::Failure(FailureReason::Uncertain))
    } else if f_m.is_some_and(|f_m| judge.outside_workspace(&f_m, &errors)) {
        Some(Outcome::Failure(FailureReason::MotionLimit))
    } else if episode.step >= cell.episode.max_steps {
        Some(Outcome::Failure(FailureReason::StepLimit))
    } else {
        None
    };
    episode.over = outcome.is_some();
    let ending = outcome.map(|o| match o {
        Outcome::Success => Ending::Success,
        Outcome::Failure(_) => Ending::Failure,
    });
    let tip_in_bore = estimate.m_f.is_some_and(|m_f| judge.tip_in_bore(&m_f));
    let reward = episode
        .reward
        .step(&episode.observation.state, tip_in_bore, ending);
    StepResult {
        observation: episode.observation.clone(),
        reward,
        veto: pending.veto,
        legs_mm,
        commanded_legs_mm: pending.commanded_legs_mm,
        detected,
        done: outcome.is_some(),
        outcome,
        // A real cell has no truth: the errors of its estimate.
        true_errors: errors,
        move_time_s,
    }
}
