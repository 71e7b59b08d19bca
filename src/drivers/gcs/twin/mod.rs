//! The twin's platform as a GCS 2.0 hexapod controller: the commands a PI hexapod (C-887)
//! answers, executed on a [`TwinRig`]. Pure: one command and the time in, its answer (if it
//! has one) out; the TCP server and its clock are `celld twin-server`'s.
//!
//! Moves take time: the platform goes along the straight line to its target at the system
//! velocity (`VLS`, mm/s; rotations at the cell's `speed_deg_s` scaled alike) ([`motion`]).
//! While it moves `ONT?` answers 0, `#5` names the moving axes and `POS?` where the platform
//! is; the rig itself moves when the move ends, is stopped, or a capture needs it
//! ([`TwinController::place`]). With instant moves (for tests) it arrives at once. Errors are
//! kept as a controller keeps them: the first since the last `ERR?`.

mod catalogue;
mod commands;
mod limits;
mod motion;
#[cfg(test)]
mod tests;

pub use catalogue::{COMMANDS, Parameter};
pub use limits::TravelLimits;
pub use motion::{Motion, Speeds};

use super::errors::{self, NO_ERROR};
use super::protocol::{AXES, Request, pose_to_axes};
use crate::geometry::Pose;
use crate::sim::rig::TwinRig;
use nalgebra::{Translation3, Vector3};
use std::collections::VecDeque;

/// `*IDN?`'s answer.
pub const IDENTITY: &str = "celld, twin hexapod (GCS 2.0), 0, celld";
/// `SSN?`'s answer: the serial number `*IDN?` gives.
pub const SERIAL_NUMBER: &str = "0";
/// `CST?`'s answer for each axis: the twin's Stewart platform.
pub const STAGE_TYPE: &str = "TWIN-6SPS";
/// The coordinate system a C-887 starts in, and the only one the twin has.
pub const ZERO_SYSTEM: &str = "ZERO";

/// A single-character query: the status register, hex (`#4`).
pub const STATUS_CHAR: u8 = 4;
/// A single-character query: motion status, as a hex bit mask of moving axes (`#5`).
pub const MOTION_STATUS_CHAR: u8 = 5;
/// A single-character query: controller ready (answers 0xB1 when ready) (`#7`).
pub const READY_CHAR: u8 = 7;
/// A single-character command: stop all axes, like `STP` (`#24`).
pub const STOP_CHAR: u8 = 24;

/// The twin's own command (no PI controller has it): `EPISODE SEED OFFSET_MM ORIENTATION_DEG`
/// draws a new episode, as the in-process twin does at a job's start.
pub const EPISODE: &str = "EPISODE";

/// The fastest `VLS` accepted, mm/s, unless the cell's own speed is faster.
const MAX_VELOCITY_MM_S: f64 = 50.0;
/// How many accepted moves [`TwinController::moves_started`] remembers.
const MOVE_LOG: usize = 4096;

/// The controller's state: servos, reference, target, the move under way, the pending error.
#[derive(Debug, Clone)]
pub struct TwinController {
    /// A hexapod's servos switch on and off together.
    servo: bool,
    referenced: bool,
    /// The last commanded target, X Y Z U V W.
    target: [f64; 6],
    /// The move under way (none when the platform stands still).
    motion: Option<Motion>,
    /// Moves arrive at once instead of taking time.
    instant: bool,
    velocity_mm_s: f64,
    max_velocity_mm_s: f64,
    /// The cell's speeds: at `VLS` = `speed.mm_s`, rotations go at `speed.deg_s`.
    speed: Speeds,
    /// The pivot point R S T, mm, in the platform frame.
    pivot_mm: [f64; 3],
    limits: TravelLimits,
    command_level: u8,
    moves: VecDeque<(f64, [f64; 6])>,
    error: i32,
}

impl TwinController {
    /// A controller as after power-on (`ready`: false), or referenced with its servos on;
    /// its moves take time at the cell's speeds.
    pub fn new(rig: &TwinRig, ready: bool) -> Self {
        let robot = &rig.cell().robot;
        TwinController {
            servo: ready,
            referenced: ready,
            target: pose_to_axes(&rig.setpoint()),
            motion: None,
            instant: false,
            velocity_mm_s: robot.speed_mm_s,
            max_velocity_mm_s: MAX_VELOCITY_MM_S.max(robot.speed_mm_s),
            speed: Speeds {
                mm_s: robot.speed_mm_s,
                deg_s: robot.speed_deg_s,
            },
            pivot_mm: [0.0; 3],
            limits: TravelLimits::of(rig),
            command_level: 0,
            moves: VecDeque::new(),
            error: NO_ERROR,
        }
    }

    /// The same controller with moves that arrive at once (`ONT?` 1 right after `MOV`).
    pub fn with_instant_moves(mut self, instant: bool) -> Self {
        self.instant = instant;
        self
    }

    /// The platform moved outside the controller's knowledge (a new episode): any move is
    /// abandoned and the target follows the platform.
    pub fn follow(&mut self, rig: &TwinRig) {
        self.motion = None;
        self.target = self.axes_of(&rig.setpoint());
    }

    /// The moves accepted (`MOV`, `MVR`), oldest first: when (the `now_s` they came with) and
    /// their target X Y Z U V W. The last 4096 are kept.
    pub fn moves_started(&self) -> impl Iterator<Item = &(f64, [f64; 6])> {
        self.moves.iter()
    }

    /// Whether the platform is moving at `now_s`.
    pub fn is_moving(&self, now_s: f64) -> bool {
        self.motion.as_ref().is_some_and(|m| !m.done(now_s))
    }

    /// Puts `rig`'s platform where it is at `now_s` (mid-move: the interpolated pose), so a
    /// capture sees it there. Mid-move this is one more execution of the twin's legs, with its
    /// random error, so a capture during a move changes the episode's random stream.
    pub fn place(&mut self, rig: &mut TwinRig, now_s: f64) {
        self.advance(rig, now_s);
        if let Some(motion) = &self.motion {
            let here = motion.at(now_s);
            self.execute(&here, rig);
        }
    }

    /// Answers one single-character command (`#4`, `#5`, `#7`, `#24`) at `now_s` (seconds).
    pub fn handle_char(&mut self, byte: u8, rig: &mut TwinRig, now_s: f64) -> Option<Vec<u8>> {
        self.advance(rig, now_s);
        match byte {
            STOP_CHAR => {
                self.stop(rig, now_s);
                None
            }
            STATUS_CHAR => Some(format!("0x{:X}\n", self.status(now_s)).into_bytes()),
            MOTION_STATUS_CHAR => Some(format!("{:X}\n", self.moving_mask(now_s)).into_bytes()),
            READY_CHAR => Some(vec![0xB1, b'\n']),
            _ => {
                self.fail(errors::UNKNOWN_COMMAND);
                None
            }
        }
    }

    /// Executes one command line (without its LF) on `rig` at `now_s` (seconds, on the clock
    /// every call uses); the answer of a query.
    pub fn handle(&mut self, line: &str, rig: &mut TwinRig, now_s: f64) -> Option<String> {
        self.advance(rig, now_s);
        let request = Request::parse(line)?;
        commands::dispatch(self, &request, rig, now_s)
    }

    /// The status register (`#4`): on target, in motion, servo on, an error pending.
    fn status(&self, now_s: f64) -> u32 {
        use catalogue::status;
        let mut register = 0;
        if self.error != NO_ERROR {
            register |= status::ERROR;
        }
        if self.servo {
            register |= status::SERVO_ON;
        }
        register |= if self.is_moving(now_s) {
            status::IN_MOTION
        } else {
            status::ON_TARGET
        };
        register
    }

    fn moving_mask(&self, now_s: f64) -> u32 {
        self.motion.as_ref().map_or(0, |m| m.moving_mask(now_s))
    }

    /// Ends a move whose time is up: the rig's legs execute its target.
    fn advance(&mut self, rig: &mut TwinRig, now_s: f64) {
        if let Some(motion) = self.motion.take_if(|m| m.done(now_s)) {
            self.execute(&motion.target(), rig);
        }
    }

    /// The axis values of the platform at `now_s`.
    fn position(&self, rig: &TwinRig, now_s: f64) -> [f64; 6] {
        match &self.motion {
            Some(motion) => motion.at(now_s),
            None => self.axes_of(&rig.setpoint()),
        }
    }

    /// Moves the rig's platform to `axes` at once.
    fn execute(&mut self, axes: &[f64; 6], rig: &mut TwinRig) -> bool {
        let ok = rig.move_to(&self.pose_of(axes)).is_ok();
        if !ok {
            self.fail(errors::POSITION_OUT_OF_LIMITS);
        }
        ok
    }

    /// `STP`, `HLT`, `#24`: the platform stays where it is now; error 10.
    fn stop(&mut self, rig: &mut TwinRig, now_s: f64) {
        self.halt(rig, now_s);
        self.fail(errors::STOPPED);
    }

    /// Ends any move where the platform is at `now_s`; the target becomes that pose.
    fn halt(&mut self, rig: &mut TwinRig, now_s: f64) {
        if let Some(motion) = self.motion.take() {
            self.execute(&motion.at(now_s), rig);
        }
        self.target = self.axes_of(&rig.setpoint());
    }

    /// Starts the move to `target` (already checked) at `now_s`.
    fn start_move(&mut self, target: [f64; 6], rig: &mut TwinRig, now_s: f64) {
        let from = self.position(rig, now_s);
        let motion = Motion::new(from, target, now_s, self.speeds());
        if self.instant || motion.done(now_s) {
            self.motion = None;
            if !self.execute(&target, rig) {
                return;
            }
        } else {
            self.motion = Some(motion);
        }
        self.target = target;
        if self.moves.len() == MOVE_LOG {
            self.moves.pop_front();
        }
        self.moves.push_back((now_s, target));
    }

    /// The platform's speeds at the system velocity: rotations scale with it.
    fn speeds(&self) -> Speeds {
        let scale = self.velocity_mm_s / self.speed.mm_s;
        Speeds {
            mm_s: self.velocity_mm_s,
            deg_s: self.speed.deg_s * scale,
        }
    }

    /// Keeps the first error since the last `ERR?`.
    fn fail(&mut self, code: i32) {
        if self.error == NO_ERROR {
            self.error = code;
        }
    }

    /// The platform pose of axis values: U V W turn about the pivot point.
    fn pose_of(&self, axes: &[f64; 6]) -> Pose {
        let rotated = super::protocol::axes_to_pose(axes);
        let pivot = Vector3::from(self.pivot_mm);
        let shift = pivot - rotated.rotation * pivot;
        Translation3::from(shift) * rotated
    }

    /// The axis values of a platform pose (the inverse of [`Self::pose_of`]).
    fn axes_of(&self, pose: &Pose) -> [f64; 6] {
        let pivot = Vector3::from(self.pivot_mm);
        let shift = pivot - pose.rotation * pivot;
        pose_to_axes(&(Translation3::from(-shift) * pose))
    }
}

fn axis_index(name: &str) -> Option<usize> {
    AXES.iter().position(|a| a.eq_ignore_ascii_case(name))
}
