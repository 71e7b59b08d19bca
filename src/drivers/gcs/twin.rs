//! The twin's platform as a GCS 2.0 hexapod controller: the commands a PI hexapod answers,
//! executed on a [`TwinRig`]. Pure: one command in, its answer (if it has one) out; the TCP
//! server is `celld twin-server`'s.
//!
//! Moves are instantaneous (the twin's legs arrive at once), so `ONT?` answers 1 right after
//! `MOV`. Errors are kept as a controller keeps them: the first since the last `ERR?`.

use super::errors::{self, NO_ERROR};
use super::protocol::{AXES, PIVOT_AXES, Request, answer_lines, pose_to_axes};
use crate::geometry::Pose;
use crate::sim::rig::TwinRig;
use nalgebra::{Translation3, Vector3};

/// `*IDN?`'s answer.
pub const IDENTITY: &str = "celld, twin hexapod (GCS 2.0), 0, celld";

/// A single-character command: stop all axes (like `STP`).
pub const STOP_CHAR: u8 = 24;
/// A single-character query: motion status, as a hex bit mask of moving axes.
pub const MOTION_STATUS_CHAR: u8 = 5;
/// A single-character query: controller ready (answers 0xB1 when ready).
pub const READY_CHAR: u8 = 7;

/// The twin's own command (no PI controller has it): `EPISODE SEED OFFSET_MM ORIENTATION_DEG`
/// draws a new episode, as the in-process twin does at a job's start.
pub const EPISODE: &str = "EPISODE";

/// Velocity limits accepted by `VLS`, mm/s.
const MAX_VELOCITY_MM_S: f64 = 50.0;

/// The controller's state: servos, reference, target, velocity, pivot, the pending error.
#[derive(Debug, Clone)]
pub struct TwinController {
    servo: [bool; 6],
    referenced: bool,
    /// The last commanded target, X Y Z U V W.
    target: [f64; 6],
    velocity_mm_s: f64,
    /// The pivot point R S T, mm, in the platform frame.
    pivot_mm: [f64; 3],
    error: i32,
}

impl TwinController {
    /// A controller as after power-on (`ready`: false), or referenced with its servos on.
    pub fn new(rig: &TwinRig, ready: bool) -> Self {
        TwinController {
            servo: [ready; 6],
            referenced: ready,
            target: pose_to_axes(&rig.setpoint()),
            velocity_mm_s: 10.0,
            pivot_mm: [0.0; 3],
            error: NO_ERROR,
        }
    }

    /// The platform moved outside the controller's knowledge (a new episode): the target
    /// follows it.
    pub fn follow(&mut self, rig: &TwinRig) {
        self.target = self.axes_of(&rig.setpoint());
    }

    /// Answers one single-character command (`#5`, `#7`, `#24`).
    pub fn handle_char(&mut self, byte: u8) -> Option<Vec<u8>> {
        match byte {
            STOP_CHAR => {
                self.fail(errors::STOPPED);
                None
            }
            MOTION_STATUS_CHAR => Some(b"0\n".to_vec()),
            READY_CHAR => Some(vec![0xB1, b'\n']),
            _ => {
                self.fail(errors::UNKNOWN_COMMAND);
                None
            }
        }
    }

    /// Executes one command line (without its LF) on `rig`; the answer of a query.
    pub fn handle(&mut self, line: &str, rig: &mut TwinRig) -> Option<String> {
        let request = Request::parse(line)?;
        match request.mnemonic.as_str() {
            "*IDN?" => Some(format!("{IDENTITY}\n")),
            "CSV?" => Some("2.0\n".into()),
            "SAI?" => Some(answer_lines(&AXES)),
            "ERR?" => Some(format!(
                "{}\n",
                std::mem::replace(&mut self.error, NO_ERROR)
            )),
            "SVO?" => self.flags(&request, |c, k| c.servo[k]),
            "FRF?" => self.flags(&request, |c, _| c.referenced),
            "ONT?" => self.flags(&request, |_, _| true),
            "POS?" => {
                let position = self.axes_of(&rig.setpoint());
                self.values(&request, &position)
            }
            "MOV?" => {
                let target = self.target;
                self.values(&request, &target)
            }
            "SPI?" => {
                let lines: Vec<String> = PIVOT_AXES
                    .iter()
                    .zip(self.pivot_mm)
                    .map(|(axis, value)| format!("{axis}={value}"))
                    .collect();
                Some(answer_lines(&lines))
            }
            "VLS?" => Some(format!("{}\n", self.velocity_mm_s)),
            "SVO" => {
                self.set_servo(&request);
                None
            }
            "FRF" => {
                self.reference(&request, rig);
                None
            }
            "MOV" | "MVR" => {
                self.motion(&request, rig);
                None
            }
            "STP" | "HLT" => {
                self.target = self.axes_of(&rig.setpoint());
                self.fail(errors::STOPPED);
                None
            }
            "VLS" => {
                match request.args.as_slice() {
                    [value] => match value.parse::<f64>() {
                        Ok(v) if v > 0.0 && v <= MAX_VELOCITY_MM_S => self.velocity_mm_s = v,
                        Ok(_) => self.fail(errors::VELOCITY_OUT_OF_LIMITS),
                        Err(_) => self.fail(errors::INVALID_NUMBER),
                    },
                    _ => self.fail(errors::WRONG_PARAMETER_COUNT),
                }
                None
            }
            "SPI" => {
                self.set_pivot(&request);
                None
            }
            EPISODE => {
                self.episode(&request, rig);
                None
            }
            _ => {
                self.fail(errors::UNKNOWN_COMMAND);
                None
            }
        }
    }

    /// Keeps the first error since the last `ERR?`.
    fn fail(&mut self, code: i32) {
        if self.error == NO_ERROR {
            self.error = code;
        }
    }

    /// The axes named by a query (all six when none), or `None` after an invalid one.
    fn queried(&mut self, request: &Request) -> Option<Vec<usize>> {
        if request.args.is_empty() {
            return Some((0..6).collect());
        }
        let found: Option<Vec<usize>> = request.args.iter().map(|a| axis_index(a)).collect();
        if found.is_none() {
            self.fail(errors::INVALID_AXIS);
        }
        found
    }

    fn flags(&mut self, request: &Request, flag: impl Fn(&Self, usize) -> bool) -> Option<String> {
        let axes = self.queried(request)?;
        let lines: Vec<String> = axes
            .iter()
            .map(|&k| format!("{}={}", AXES[k], u8::from(flag(self, k))))
            .collect();
        Some(answer_lines(&lines))
    }

    fn values(&mut self, request: &Request, values: &[f64; 6]) -> Option<String> {
        let axes = self.queried(request)?;
        let lines: Vec<String> = axes
            .iter()
            .map(|&k| format!("{}={}", AXES[k], values[k]))
            .collect();
        Some(answer_lines(&lines))
    }

    fn set_servo(&mut self, request: &Request) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        let mut servo = self.servo;
        for (axis, value) in pairs {
            let (Some(k), Ok(on)) = (axis_index(axis), value.parse::<u8>()) else {
                return self.fail(errors::PARAMETER_SYNTAX);
            };
            servo[k] = on != 0;
        }
        self.servo = servo;
    }

    /// `FRF`: a hexapod references all its axes together, and needs its servos on.
    fn reference(&mut self, request: &Request, rig: &TwinRig) {
        if request.args.iter().any(|a| axis_index(a).is_none()) {
            return self.fail(errors::INVALID_AXIS);
        }
        if !self.servo.iter().all(|on| *on) {
            return self.fail(errors::MOVE_WITHOUT_REFERENCE_OR_SERVO);
        }
        self.referenced = true;
        self.target = self.axes_of(&rig.setpoint());
    }

    fn motion(&mut self, request: &Request, rig: &mut TwinRig) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        let relative = request.mnemonic == "MVR";
        let mut target = self.target;
        for (axis, value) in pairs {
            let Some(k) = axis_index(axis) else {
                return self.fail(errors::INVALID_AXIS);
            };
            let Some(value) = value.parse::<f64>().ok().filter(|v| v.is_finite()) else {
                return self.fail(errors::INVALID_NUMBER);
            };
            if !(self.referenced && self.servo[k]) {
                return self.fail(errors::MOVE_WITHOUT_REFERENCE_OR_SERVO);
            }
            target[k] = if relative { target[k] + value } else { value };
        }
        let pose = self.pose_of(&target);
        if !rig.reaches(&pose) {
            return self.fail(errors::POSITION_OUT_OF_LIMITS);
        }
        match rig.move_to(&pose) {
            Ok(()) => self.target = target,
            Err(_) => self.fail(errors::POSITION_OUT_OF_LIMITS),
        }
    }

    fn episode(&mut self, request: &Request, rig: &mut TwinRig) {
        let [seed, offset, orientation] = request.args.as_slice() else {
            return self.fail(errors::WRONG_PARAMETER_COUNT);
        };
        let (Ok(seed), Ok(offset_mm), Ok(orientation_deg)) = (
            seed.parse(),
            offset.parse::<f64>(),
            orientation.parse::<f64>(),
        ) else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        let initial = crate::sim::InitialConditions {
            offset_mm,
            orientation_deg,
        };
        if !(offset_mm.is_finite() && orientation_deg.is_finite())
            || rig.begin_episode(seed, initial).is_err()
        {
            return self.fail(errors::PARAMETER_OUT_OF_RANGE);
        }
        self.follow(rig);
    }

    fn set_pivot(&mut self, request: &Request) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        if self.target[3..].iter().any(|angle| *angle != 0.0) {
            return self.fail(errors::PIVOT_WHILE_ROTATED);
        }
        let mut pivot = self.pivot_mm;
        for (axis, value) in pairs {
            let Some(k) = PIVOT_AXES.iter().position(|a| a.eq_ignore_ascii_case(axis)) else {
                return self.fail(errors::INVALID_AXIS);
            };
            let Some(value) = value.parse::<f64>().ok().filter(|v| v.is_finite()) else {
                return self.fail(errors::INVALID_NUMBER);
            };
            pivot[k] = value;
        }
        self.pivot_mm = pivot;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::sim::InitialConditions;

    fn started() -> (TwinController, TwinRig) {
        let cell = CellConfig::reference();
        let mut rig = TwinRig::new(&cell);
        rig.begin_episode(3, InitialConditions::from_cell(&cell))
            .unwrap();
        (TwinController::new(&rig, false), rig)
    }

    #[test]
    fn a_move_needs_servo_and_reference_and_lands_where_commanded() {
        let (mut controller, mut rig) = started();
        let before = rig.setpoint();
        assert_eq!(controller.handle("MVR Z 1", &mut rig), None);
        assert_eq!(controller.handle("ERR?", &mut rig).as_deref(), Some("5\n"));
        assert_eq!(controller.handle("ERR?", &mut rig).as_deref(), Some("0\n"));
        controller.handle("FRF", &mut rig);
        assert_eq!(controller.handle("ERR?", &mut rig).as_deref(), Some("5\n"));
        controller.handle("SVO X 1 Y 1 Z 1 U 1 V 1 W 1", &mut rig);
        controller.handle("FRF", &mut rig);
        assert_eq!(
            controller.handle("FRF? X W", &mut rig).as_deref(),
            Some("X=1 \nW=1\n")
        );
        controller.handle("MVR Z 1", &mut rig);
        assert_eq!(controller.handle("ERR?", &mut rig).as_deref(), Some("0\n"));
        let moved = rig.setpoint().translation.vector - before.translation.vector;
        assert!(
            (moved - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-9,
            "{moved}"
        );
        let z = before.translation.vector.z + 1.0;
        let answer = controller.handle("POS? Z", &mut rig).unwrap();
        let read = super::super::protocol::axis_values(&answer, &["Z"]).unwrap()[0];
        assert!((read - z).abs() < 1e-9, "{answer}");
    }

    #[test]
    fn bad_commands_leave_their_error_code() {
        let (mut controller, mut rig) = started();
        for (line, code) in [
            ("FOO", errors::UNKNOWN_COMMAND),
            ("POS? Q", errors::INVALID_AXIS),
            ("SVO X", errors::PARAMETER_SYNTAX),
            ("VLS 500", errors::VELOCITY_OUT_OF_LIMITS),
            ("STP", errors::STOPPED),
        ] {
            controller.handle(line, &mut rig);
            assert_eq!(
                controller.handle("ERR?", &mut rig),
                Some(format!("{code}\n")),
                "{line}"
            );
        }
        let (mut ready, mut rig) = {
            let (_, rig) = started();
            (TwinController::new(&rig, true), rig)
        };
        ready.handle("MOV Z 100000", &mut rig);
        assert_eq!(
            ready.handle("ERR?", &mut rig),
            Some(format!("{}\n", errors::POSITION_OUT_OF_LIMITS))
        );
    }

    #[test]
    fn the_pivot_point_turns_the_platform_about_itself() {
        let (_, mut rig) = started();
        let mut controller = TwinController::new(&rig, true);
        let setpoint = rig.setpoint();
        // Only while U V W are 0.
        let axes = controller.axes_of(&setpoint);
        if axes[3..].iter().any(|a| *a != 0.0) {
            controller.handle("SPI R 0 S 0 T 10", &mut rig);
            assert_eq!(
                controller.handle("ERR?", &mut rig),
                Some(format!("{}\n", errors::PIVOT_WHILE_ROTATED))
            );
        }
        controller.pivot_mm = [0.0, 0.0, 10.0];
        let pose = controller.pose_of(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let back = controller.axes_of(&pose);
        for (a, b) in back.iter().zip([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) {
            assert!((a - b).abs() < 1e-9, "{back:?}");
        }
    }
}
