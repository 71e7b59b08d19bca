//! [`GcsRobot`]: a PI hexapod controller as the cell's [`Robot`]. Wrapped in
//! [`Supervised`](crate::robot::Supervised), it sees only the moves the collision supervisor
//! allows.
//!
//! A move is `MOV` of the platform pose the step leads to (X Y Z in mm, U V W in deg, in the
//! cell's base frame {O}), `ERR?`, then `ONT?` until every axis is on target, within the
//! on-target deadline (the move's own time at the platform's speeds and a margin); past it the
//! driver sends `STP` and reports the deadline. `POS?` then reads the platform back, which must
//! be where the move was to put it.
//!
//! Nothing runs that the cell gave up on: a dropped connection, or an answer later than its
//! timeout, latches the driver; the connection given up gets `STP` written after whatever it
//! was sent, every new connection starts with `STP` before anything else, and then reads the
//! position and compares it with the last setpoint the cell knows (a difference latches the
//! driver as `position_mismatch`). It moves nothing until an operator reset
//! ([`GcsRobot::reset`]).

use super::client::{GcsClient, GcsSettings, Stopper};
use super::errors::{GcsError, STOPPED};
use super::protocol::{
    AXES, PIVOT_AXES, axes_to_pose, axis_flags, axis_values, command_with_values, pose_to_axes,
};
use super::twin::EPISODE;
use crate::config::cell::CellConfig;
use crate::drivers::{DriverObserver, Unobserved};
use crate::geometry::{CellFrames, Move, Pose};
use crate::kinematics::StewartGeometry;
use crate::robot::{PlatformSpeeds, Robot, RobotError, RobotFault};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime};

/// Why the driver holds until an operator reset, and since when.
#[derive(Debug, Clone, PartialEq)]
pub struct Latch {
    pub error: GcsError,
    pub since: SystemTime,
}

/// A hexapod behind a GCS 2.0 controller.
pub struct GcsRobot {
    address: String,
    settings: GcsSettings,
    client: Option<GcsClient>,
    /// The connection's `STP` handle, shared with [`GcsRobot::emergency_stop`]'s callers.
    stopper: Arc<Mutex<Option<Stopper>>>,
    identity: String,
    /// The cell's nominal kinematics: leg lengths of a pose, to refuse unreachable moves
    /// before the controller sees them and to report the legs.
    nominal: StewartGeometry,
    /// Segment I's frame {M} in the platform's {P}.
    p_m: Pose,
    setpoint: Pose,
    /// The setpoint is one the cell commanded or read (not the nominal home of a driver that
    /// never reached the controller), so a new connection can be checked against it.
    setpoint_known: bool,
    encoders_mm: [f64; 6],
    /// The platform's speeds: the cell file's, at the velocity the controller reports.
    speeds: PlatformSpeeds,
    /// The time the last move was allowed: its time at those speeds × the settings' factor, s.
    last_move_time_s: f64,
    /// Connections made since the driver was created (the first included).
    connections: u64,
    /// Why the driver stopped trusting the controller; cleared by an operator reset.
    latched: Option<Latch>,
    observer: Arc<dyn DriverObserver>,
}

impl GcsRobot {
    /// Connects to the controller at `address` (`host:port`) and checks it is ready: every
    /// axis referenced (`FRF?`) and its servo on (`SVO?`). The setpoint starts where `POS?`
    /// says the platform is.
    pub fn connect(
        address: &str,
        settings: GcsSettings,
        cell: &CellConfig,
    ) -> Result<GcsRobot, GcsError> {
        let nominal = StewartGeometry::from_config(&cell.robot);
        let home = nominal.home_pose();
        let mut robot = GcsRobot {
            address: address.to_string(),
            settings,
            client: None,
            stopper: Arc::default(),
            identity: String::new(),
            encoders_mm: nominal.leg_lengths_mm(&home),
            setpoint: home,
            setpoint_known: false,
            nominal,
            p_m: CellFrames::from_config(cell).p_m,
            speeds: PlatformSpeeds::of_cell(&cell.robot),
            last_move_time_s: 0.0,
            connections: 0,
            latched: None,
            observer: Arc::new(Unobserved),
        };
        robot.reset()?;
        Ok(robot)
    }

    /// The operator's reset: reconnects when the connection is gone, checks the controller
    /// is ready again (and sets the velocity, when the settings give one), takes the
    /// platform's position as the setpoint and unlatches. A platform this reset finds away
    /// from where the cell last put it fails the reset (`position_mismatch`, which the
    /// operator could not have seen yet); the next reset takes it where it is.
    pub fn reset(&mut self) -> Result<(), GcsError> {
        // A connection lost on the way is given up as any other.
        self.check_and_unlatch().map_err(|error| self.note(error))
    }

    fn check_and_unlatch(&mut self) -> Result<(), GcsError> {
        let acknowledged = self.mismatch_latched();
        if self.client.is_none() {
            self.reconnect()?;
        } else if self.latched.is_some() {
            // A connection made again while latched (a hold's) was checked then; a command
            // that arrived at the controller since would show now.
            self.check_position()?;
        }
        if !acknowledged && self.mismatch_latched() {
            let latch = self.latched.as_ref().expect("latched on the mismatch");
            return Err(latch.error.clone());
        }
        let velocity = self.settings.velocity_mm_s;
        let client = self.client_mut()?;
        let identity = client.query("*IDN?")?.trim().to_string();
        let servo = read_flags(client, "SVO?")?;
        let referenced = read_flags(client, "FRF?")?;
        if let Some(axis) = first_false(&servo) {
            return Err(GcsError::NotReady {
                axis,
                what: "switched on (SVO?)",
            });
        }
        if let Some(axis) = first_false(&referenced) {
            return Err(GcsError::NotReady {
                axis,
                what: "referenced (FRF?)",
            });
        }
        if let Some(velocity) = velocity {
            client.command(&format!("VLS {velocity}"))?;
        }
        let answer = client.query("VLS?")?;
        let velocity_mm_s = read_velocity(&answer).ok_or_else(|| GcsError::Answer {
            command: "VLS?".into(),
            answer: answer.clone(),
            problem: super::protocol::AnswerError::NotANumber {
                text: answer.trim().into(),
            },
        })?;
        let answer = client.query("SPI?")?;
        let pivot = axis_values(&answer, &PIVOT_AXES).map_err(|problem| GcsError::Answer {
            command: "SPI?".into(),
            answer: answer.clone(),
            problem,
        })?;
        if pivot != [0.0; 3] {
            let [r_mm, s_mm, t_mm] = pivot;
            return Err(GcsError::Pivot { r_mm, s_mm, t_mm });
        }
        self.identity = identity;
        self.speeds = self.speeds.at_velocity(velocity_mm_s);
        self.setpoint = self.read_position()?;
        self.setpoint_known = true;
        self.latched = None;
        Ok(())
    }

    fn mismatch_latched(&self) -> bool {
        self.latched
            .as_ref()
            .is_some_and(|latch| matches!(latch.error, GcsError::PositionMismatch { .. }))
    }

    /// Takes the platform's position (`POS?`) as the setpoint, as at an episode's start when
    /// someone else may have moved it.
    pub fn refresh(&mut self) -> Result<(), GcsError> {
        let result = self.read_position();
        match result {
            Ok(pose) => {
                self.setpoint = pose;
                self.setpoint_known = true;
                Ok(())
            }
            Err(error) => Err(self.note(error)),
        }
    }

    /// Asks `celld twin-server` to draw the episode of `seed` (its own `EPISODE` command, which
    /// a PI controller refuses with error 2), then takes the platform's new position.
    pub fn rehearse(
        &mut self,
        seed: u64,
        offset_mm: f64,
        orientation_deg: f64,
    ) -> Result<(), GcsError> {
        let command = format!("{EPISODE} {seed} {offset_mm} {orientation_deg}");
        let result = self
            .client_mut()
            .and_then(|client| client.command(&command));
        if let Err(error) = result {
            return Err(self.note(error));
        }
        self.refresh()
    }

    /// Reports round trips and reconnections to `observer` from the next connection on.
    pub fn observe_with(&mut self, observer: Arc<dyn DriverObserver>) {
        if let Some(client) = &mut self.client {
            client.observe_with(observer.clone());
        }
        self.observer = observer;
    }

    /// The controller's `*IDN?` answer.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// Why the driver holds until an operator reset, and since when, if it does.
    pub fn latched(&self) -> Option<&Latch> {
        self.latched.as_ref()
    }

    /// The time the last move was allowed: its time at the platform's speeds × the settings'
    /// `move_time_factor`, s.
    pub fn last_move_time_s(&self) -> f64 {
        self.last_move_time_s
    }

    /// The platform's speeds the time limits are taken from.
    pub fn speeds(&self) -> PlatformSpeeds {
        self.speeds
    }

    /// Connections to the controller since the driver started, the first included.
    pub fn connections(&self) -> u64 {
        self.connections
    }

    /// Notices a controller that closed the connection while the driver had nothing to ask
    /// (between jobs), without sending anything: the latch then shows at once instead of at
    /// the next job's start.
    pub fn watch(&mut self) {
        let closed = self.client.as_ref().and_then(GcsClient::closed_by_peer);
        if let Some(error) = closed {
            self.note(error);
        }
    }

    /// Writes `STP` on the wire from any thread (the e-stop's), even while this driver waits
    /// for an answer; answers whether it was written. The error code it leaves is read by
    /// the next command.
    pub fn emergency_stop(&self) -> impl Fn() -> bool + Send + Sync + 'static {
        let stopper = self.stopper.clone();
        move || {
            let guard = stopper.lock().unwrap_or_else(PoisonError::into_inner);
            guard.as_ref().is_some_and(|stopper| stopper.stop().is_ok())
        }
    }

    /// Moves the platform to `target` (in {O}), waits until it is on target, and checks the
    /// controller's position is the target's. The wait is the move's allowed time and the
    /// on-target deadline's margin.
    pub fn move_to(&mut self, target: &Pose) -> Result<(), GcsError> {
        let command = command_with_values("MOV", &AXES, &pose_to_axes(target));
        let move_time_s =
            self.speeds.move_time_s(&self.setpoint, target) * self.settings.move_time_factor;
        self.last_move_time_s = move_time_s;
        let deadline_ms = self.settings.on_target_deadline_ms + (move_time_s * 1e3).ceil() as u64;
        let poll = Duration::from_millis(self.settings.poll_interval_ms);
        let client = self.client_mut()?;
        let deadline = Instant::now() + Duration::from_millis(deadline_ms);
        if let Err(error) = client.command(&command) {
            if let GcsError::Controller { .. } = error {
                // The controller may have taken the move all the same (an error it reports can
                // be an earlier command's): stop it and take the platform where it is.
                client.send("STP")?;
                client.error_code()?;
                self.setpoint = self.read_position()?;
            }
            return Err(error);
        }
        while !read_flags(client, "ONT?")?.iter().all(|on| *on) {
            if Instant::now() >= deadline {
                client.send("STP")?;
                // STP sets error 10, which must not fail the next command.
                let code = client.error_code()?;
                if code != STOPPED && code != 0 {
                    return Err(GcsError::controller(code, "STP"));
                }
                self.setpoint = self.read_position()?;
                return Err(GcsError::Deadline { deadline_ms });
            }
            if !poll.is_zero() {
                std::thread::sleep(poll);
            }
        }
        let reached = self.read_position()?;
        if let Some(mismatch) = self.mismatch(&reached, target) {
            self.setpoint = reached;
            return Err(mismatch);
        }
        self.setpoint = *target;
        self.setpoint_known = true;
        Ok(())
    }

    /// The mismatch error when `read` is not `expected` within the settings' tolerances.
    fn mismatch(&self, read: &Pose, expected: &Pose) -> Option<GcsError> {
        let (read, expected) = (pose_to_axes(read), pose_to_axes(expected));
        let largest = |axes: std::ops::Range<usize>| {
            axes.map(|k| (read[k] - expected[k]).abs())
                .fold(0.0, f64::max)
        };
        let (distance_mm, angle_deg) = (largest(0..3), largest(3..6));
        let (tolerance_mm, tolerance_deg) = (
            self.settings.position_tolerance_mm,
            self.settings.orientation_tolerance_deg,
        );
        (!(distance_mm <= tolerance_mm && angle_deg <= tolerance_deg)).then_some(
            GcsError::PositionMismatch {
                distance_mm,
                angle_deg,
                tolerance_mm,
                tolerance_deg,
            },
        )
    }

    /// `POS?`: the platform's pose; the legs follow from the nominal kinematics.
    fn read_position(&mut self) -> Result<Pose, GcsError> {
        let client = self.client_mut()?;
        let answer = client.query("POS?")?;
        let axes = axis_values(&answer, &AXES).map_err(|problem| GcsError::Answer {
            command: "POS?".into(),
            answer: answer.clone(),
            problem,
        })?;
        let pose = axes_to_pose(&axes);
        self.encoders_mm = self.nominal.leg_lengths_mm(&pose);
        Ok(pose)
    }

    /// A new connection: `STP` before anything else, then the position, compared with the
    /// last setpoint the cell knows. A difference latches the driver (`position_mismatch`);
    /// the connection stays, for the operator's reset.
    fn reconnect(&mut self) -> Result<(), GcsError> {
        let mut client = GcsClient::connect(&self.address, self.settings)?;
        client.observe_with(self.observer.clone());
        self.connections += 1;
        if self.connections > 1 {
            self.observer.reconnected("robot");
        }
        client.send("STP")?;
        // STP leaves error 10 (or nothing, on a controller that was still).
        let code = client.error_code()?;
        if code != STOPPED && code != 0 {
            tracing::warn!(
                code,
                "the controller reports an error after STP on connecting"
            );
        }
        *self.stopper.lock().unwrap_or_else(PoisonError::into_inner) = client.stopper().ok();
        self.client = Some(client);
        self.check_position()
    }

    /// Reads the position and compares it with the last setpoint the cell knows (when it
    /// knows one): a difference latches the driver (`position_mismatch`) and becomes the
    /// setpoint, so that it is reported once.
    fn check_position(&mut self) -> Result<(), GcsError> {
        if !self.setpoint_known {
            return Ok(());
        }
        let read = self.read_position()?;
        if let Some(mismatch) = self.mismatch(&read, &self.setpoint) {
            tracing::warn!(%mismatch, "the platform is not where the cell left it");
            self.setpoint = read;
            self.latch(mismatch);
        }
        Ok(())
    }

    fn latch(&mut self, error: GcsError) {
        // A mismatch is the graver news: it replaces a lost connection as the reason.
        let graver = matches!(error, GcsError::PositionMismatch { .. });
        if self.latched.is_none() || graver {
            self.latched = Some(Latch {
                error,
                since: SystemTime::now(),
            });
        }
    }

    fn client_mut(&mut self) -> Result<&mut GcsClient, GcsError> {
        let cause = || match &self.latched {
            Some(latch) => latch.error.to_string(),
            None => "not connected".to_string(),
        };
        match self.client.as_mut() {
            Some(client) => Ok(client),
            None => Err(GcsError::AwaitingReset { cause: cause() }),
        }
    }

    /// Notes an error: a lost connection is given up (`STP` written after whatever it was
    /// sent) and dropped; it and a position mismatch latch the driver.
    fn note(&mut self, error: GcsError) -> GcsError {
        if error.is_connection_lost() {
            *self.stopper.lock().unwrap_or_else(PoisonError::into_inner) = None;
            if let Some(client) = self.client.take() {
                client.give_up();
            }
        }
        if error.latches() {
            self.latch(error.clone());
        }
        error
    }
}

fn read_flags(client: &mut GcsClient, query: &str) -> Result<[bool; 6], GcsError> {
    let answer = client.query(query)?;
    axis_flags(&answer).map_err(|problem| GcsError::Answer {
        command: query.into(),
        answer,
        problem,
    })
}

/// `VLS?`'s answer: the platform's velocity, mm/s (a bare number, or `name=number`).
fn read_velocity(answer: &str) -> Option<f64> {
    let text = answer.trim();
    let value = text.rsplit('=').next()?.trim();
    value
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite() && *v > 0.0)
}

fn first_false(flags: &[bool; 6]) -> Option<&'static str> {
    flags.iter().position(|on| !on).map(|k| AXES[k])
}

impl Robot for GcsRobot {
    fn setpoint(&self) -> Pose {
        self.setpoint
    }

    fn encoders_mm(&self) -> [f64; 6] {
        self.encoders_mm
    }

    /// Commands the platform pose that moves {M} by `step`; refuses one the nominal model
    /// cannot reach before the controller sees it.
    fn execute(&mut self, step: &Move) -> Result<(), RobotError> {
        if let Some(latch) = &self.latched {
            let cause = latch.error.to_string();
            return Err(RobotError::Fault(RobotFault::Drive(
                GcsError::AwaitingReset { cause },
            )));
        }
        let target = self.setpoint * self.p_m * step.as_pose() * self.p_m.inverse();
        self.nominal
            .inverse_checked(&target)
            .map_err(|e| RobotError::Fault(e.into()))?;
        self.move_to(&target)
            .map_err(|e| RobotError::Fault(self.note(e).into()))
    }

    /// Sends `STP` and clears the error it sets. Without a connection, reconnects (which
    /// sends `STP` first and checks the position); the latch stays until an operator reset.
    fn hold(&mut self) {
        if self.client.is_none() {
            if let Err(error) = self.reconnect() {
                tracing::warn!(%error, "hold: the controller is unreachable");
                self.note(error);
            }
            return;
        }
        let result = self.client_mut().and_then(|client| {
            client.send("STP")?;
            client.error_code()
        });
        match result {
            Ok(code) if code == STOPPED || code == 0 => {}
            Ok(code) => tracing::warn!(code, "hold: the controller reports an error after STP"),
            Err(error) => {
                tracing::warn!(%error, "hold: STP failed");
                self.note(error);
            }
        }
    }
}
