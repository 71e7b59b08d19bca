//! [`GcsRobot`]: a PI hexapod controller as the cell's [`Robot`]. Wrapped in
//! [`Supervised`](crate::robot::Supervised), it sees only the moves the collision supervisor
//! allows.
//!
//! A move is `MOV` of the platform pose the step leads to (X Y Z in mm, U V W in deg, in the
//! cell's base frame {O}), `ERR?`, then `ONT?` until every axis is on target, within the
//! on-target deadline; past it the driver sends `STP` and reports the deadline. `POS?` then
//! reads the platform back. A dropped connection, or an answer later than its timeout, latches
//! the driver: it reconnects when asked to hold, but moves nothing until an operator reset
//! ([`GcsRobot::reset`]).

use super::client::{GcsClient, GcsSettings, Stopper};
use super::errors::{GcsError, STOPPED};
use super::protocol::{
    AXES, PIVOT_AXES, axes_to_pose, axis_flags, axis_values, command_with_values, pose_to_axes,
};
use super::twin::EPISODE;
use crate::config::cell::CellConfig;
use crate::geometry::{CellFrames, Move, Pose};
use crate::kinematics::StewartGeometry;
use crate::robot::{Robot, RobotError, RobotFault};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

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
    encoders_mm: [f64; 6],
    /// Why the driver stopped trusting the connection; cleared by an operator reset.
    latched: Option<GcsError>,
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
            nominal,
            p_m: CellFrames::from_config(cell).p_m,
            latched: None,
        };
        robot.reset()?;
        Ok(robot)
    }

    /// The operator's reset: reconnects when the connection is gone, checks the controller
    /// is ready again (and sets the velocity, when the settings give one), takes the
    /// platform's position as the setpoint and unlatches.
    pub fn reset(&mut self) -> Result<(), GcsError> {
        if self.client.is_none() {
            self.reconnect()?;
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
        self.setpoint = self.read_position()?;
        self.latched = None;
        Ok(())
    }

    /// Takes the platform's position (`POS?`) as the setpoint, as at an episode's start when
    /// someone else may have moved it.
    pub fn refresh(&mut self) -> Result<(), GcsError> {
        let result = self.read_position();
        match result {
            Ok(pose) => {
                self.setpoint = pose;
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

    /// The controller's `*IDN?` answer.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// Why the driver holds until an operator reset, if it does.
    pub fn latched(&self) -> Option<&GcsError> {
        self.latched.as_ref()
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

    /// Moves the platform to `target` (in {O}) and waits until it is on target.
    pub fn move_to(&mut self, target: &Pose) -> Result<(), GcsError> {
        let command = command_with_values("MOV", &AXES, &pose_to_axes(target));
        let deadline_ms = self.settings.on_target_deadline_ms;
        let poll = Duration::from_millis(self.settings.poll_interval_ms);
        let client = self.client_mut()?;
        let deadline = Instant::now() + Duration::from_millis(deadline_ms);
        client.command(&command)?;
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
        self.read_position()?;
        self.setpoint = *target;
        Ok(())
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

    fn reconnect(&mut self) -> Result<(), GcsError> {
        let client = GcsClient::connect(&self.address, self.settings)?;
        *self.stopper.lock().unwrap_or_else(PoisonError::into_inner) = client.stopper().ok();
        self.client = Some(client);
        Ok(())
    }

    fn client_mut(&mut self) -> Result<&mut GcsClient, GcsError> {
        let cause = || match &self.latched {
            Some(error) => error.to_string(),
            None => "not connected".to_string(),
        };
        match self.client.as_mut() {
            Some(client) => Ok(client),
            None => Err(GcsError::AwaitingReset { cause: cause() }),
        }
    }

    /// Notes an error: a lost connection drops the client and latches the driver.
    fn note(&mut self, error: GcsError) -> GcsError {
        if error.is_connection_lost() {
            self.client = None;
            *self.stopper.lock().unwrap_or_else(PoisonError::into_inner) = None;
            self.latched.get_or_insert(error.clone());
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
        if let Some(cause) = &self.latched {
            let cause = cause.to_string();
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

    /// Sends `STP` and clears the error it sets. Without a connection, reconnects first; the
    /// latch stays until an operator reset.
    fn hold(&mut self) {
        if self.client.is_none()
            && let Err(error) = self.reconnect()
        {
            tracing::warn!(%error, "hold: the controller is unreachable");
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
