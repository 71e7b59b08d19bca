//! The twin controller's command lines, one function per command family. A query answers
//! unless its arguments are wrong; then, as a PI controller, it answers nothing and keeps the
//! error for `ERR?`. A command not in `HLP?` leaves error 2.

use super::catalogue::{self, Parameter};
use super::{
    EPISODE, IDENTITY, SERIAL_NUMBER, STAGE_TYPE, TwinController, ZERO_SYSTEM, axis_index,
};
use crate::drivers::gcs::errors;
use crate::drivers::gcs::protocol::{AXES, PIVOT_AXES, Request, answer_lines};
use crate::sim::rig::TwinRig;

/// PI's password for command level 1.
const LEVEL_1_PASSWORD: &str = "advanced";

pub(super) fn dispatch(
    c: &mut TwinController,
    request: &Request,
    rig: &mut TwinRig,
    now_s: f64,
) -> Option<String> {
    if request.mnemonic.ends_with('?') {
        query(c, request, rig, now_s)
    } else {
        command(c, request, rig, now_s);
        None
    }
}

/// A query's answer (none after an error).
fn query(c: &mut TwinController, request: &Request, rig: &TwinRig, now_s: f64) -> Option<String> {
    match request.mnemonic.as_str() {
        "*IDN?" => Some(format!("{IDENTITY}\n")),
        "CSV?" => Some("2.0\n".into()),
        "HLP?" => Some(catalogue::help()),
        "HPA?" => Some(catalogue::parameter_help()),
        "VER?" => Some(answer_lines(&[
            format!("celld: {}", env!("CARGO_PKG_VERSION")),
            format!("twin controller: GCS 2.0, cell {}", rig.cell().name.trim()),
        ])),
        "SSN?" => Some(format!("{SERIAL_NUMBER}\n")),
        "SAI?" => Some(answer_lines(&AXES)),
        "CCL?" => Some(format!("{}\n", c.command_level)),
        "ERR?" => Some(format!(
            "{}\n",
            std::mem::replace(&mut c.error, errors::NO_ERROR)
        )),
        "SVO?" => c.per_axis(request, |c, _| u8::from(c.servo).to_string()),
        "FRF?" => c.per_axis(request, |c, _| u8::from(c.referenced).to_string()),
        "RON?" => c.per_axis(request, |_, _| "1".into()),
        "CST?" => c.per_axis(request, |_, _| STAGE_TYPE.into()),
        "ONT?" => {
            let mask = c.moving_mask(now_s);
            c.per_axis(request, |_, k| u8::from(mask & 1 << k == 0).to_string())
        }
        "POS?" => {
            let position = c.position(rig, now_s);
            c.per_axis(request, |_, k| position[k].to_string())
        }
        "MOV?" => c.per_axis(request, |c, k| c.target[k].to_string()),
        "TMN?" => c.per_axis(request, |c, k| c.limits.min[k].to_string()),
        "TMX?" => c.per_axis(request, |c, k| c.limits.max[k].to_string()),
        "SPI?" => {
            let lines: Vec<String> = PIVOT_AXES
                .iter()
                .zip(c.pivot_mm)
                .map(|(axis, value)| format!("{axis}={value}"))
                .collect();
            Some(answer_lines(&lines))
        }
        "VLS?" => Some(format!("{}\n", c.velocity_mm_s)),
        "SPA?" => c.parameters(request),
        "VMO?" => c.virtual_move(request, rig),
        "KEN?" => c.coordinate_systems(request),
        _ => {
            c.fail(errors::UNKNOWN_COMMAND);
            None
        }
    }
}

/// A command that answers nothing.
fn command(c: &mut TwinController, request: &Request, rig: &mut TwinRig, now_s: f64) {
    match request.mnemonic.as_str() {
        "SVO" => c.set_servo(request, rig, now_s),
        "FRF" => c.reference(request, rig, now_s),
        "MOV" | "MVR" => c.motion(request, rig, now_s),
        "STP" | "HLT" => c.stop(rig, now_s),
        "VLS" => c.set_velocity(request),
        "SPI" => c.set_pivot(request, now_s),
        "CCL" => c.set_command_level(request),
        "RON" => c.set_reference_mode(request),
        "SPA" => c.set_parameters(request),
        "KEN" => c.enable_coordinate_system(request),
        "KSD" => c.define_coordinate_system(request, now_s),
        EPISODE => c.episode(request, rig),
        _ => c.fail(errors::UNKNOWN_COMMAND),
    }
}

impl TwinController {
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

    /// `AXIS=VALUE` for each queried axis.
    fn per_axis(
        &mut self,
        request: &Request,
        value: impl Fn(&Self, usize) -> String,
    ) -> Option<String> {
        let axes = self.queried(request)?;
        let lines: Vec<String> = axes
            .iter()
            .map(|&k| format!("{}={}", AXES[k], value(self, k)))
            .collect();
        Some(answer_lines(&lines))
    }

    /// `SVO`: a hexapod switches its six servos together, so every value must agree; off
    /// mid-move halts the platform where it is.
    fn set_servo(&mut self, request: &Request, rig: &mut TwinRig, now_s: f64) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        let mut states = Vec::with_capacity(pairs.len());
        for (axis, value) in pairs {
            if axis_index(axis).is_none() {
                return self.fail(errors::INVALID_AXIS);
            }
            match value {
                "0" => states.push(false),
                "1" => states.push(true),
                _ => return self.fail(errors::PARAMETER_SYNTAX),
            }
        }
        if states.iter().any(|on| *on != states[0]) {
            return self.fail(errors::NOT_FOR_STAGE);
        }
        if !states[0] && self.is_moving(now_s) {
            self.halt(rig, now_s);
        }
        self.servo = states[0];
    }

    /// `FRF`: a hexapod references all its axes together, standing still, with its servos on.
    fn reference(&mut self, request: &Request, rig: &TwinRig, now_s: f64) {
        if request.args.iter().any(|a| axis_index(a).is_none()) {
            return self.fail(errors::INVALID_AXIS);
        }
        if self.is_moving(now_s) {
            return self.fail(errors::NOT_WHILE_MOVING);
        }
        if !self.servo {
            return self.fail(errors::MOVE_WITHOUT_REFERENCE_OR_SERVO);
        }
        self.referenced = true;
        self.target = self.axes_of(&rig.setpoint());
    }

    /// `MOV`, `MVR` (relative to the last target). During a move the platform turns to the
    /// new target from where it is.
    fn motion(&mut self, request: &Request, rig: &mut TwinRig, now_s: f64) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        let relative = request.mnemonic == "MVR";
        let mut target = self.target;
        for (axis, value) in pairs {
            let Some(k) = axis_index(axis) else {
                return self.fail(errors::INVALID_AXIS);
            };
            let Some(value) = finite(value) else {
                return self.fail(errors::INVALID_NUMBER);
            };
            if !(self.referenced && self.servo) {
                return self.fail(errors::MOVE_WITHOUT_REFERENCE_OR_SERVO);
            }
            target[k] = if relative { target[k] + value } else { value };
        }
        if !rig.reaches(&self.pose_of(&target)) {
            return self.fail(errors::POSITION_OUT_OF_LIMITS);
        }
        self.start_move(target, rig, now_s);
    }

    /// `VMO?`: 1 when the target (the last one with these axes set) is reachable, else 0.
    fn virtual_move(&mut self, request: &Request, rig: &TwinRig) -> Option<String> {
        let Some(pairs) = request.pairs() else {
            self.fail(errors::PARAMETER_SYNTAX);
            return None;
        };
        let mut target = self.target;
        for (axis, value) in pairs {
            let Some(k) = axis_index(axis) else {
                self.fail(errors::INVALID_AXIS);
                return None;
            };
            let Some(value) = finite(value) else {
                self.fail(errors::INVALID_NUMBER);
                return None;
            };
            target[k] = value;
        }
        Some(format!(
            "{}\n",
            u8::from(rig.reaches(&self.pose_of(&target)))
        ))
    }

    fn set_velocity(&mut self, request: &Request) {
        match request.args.as_slice() {
            [value] => match value.parse::<f64>() {
                Ok(v) if v > 0.0 && v <= self.max_velocity_mm_s => self.velocity_mm_s = v,
                Ok(_) => self.fail(errors::VELOCITY_OUT_OF_LIMITS),
                Err(_) => self.fail(errors::INVALID_NUMBER),
            },
            _ => self.fail(errors::WRONG_PARAMETER_COUNT),
        }
    }

    fn set_pivot(&mut self, request: &Request, now_s: f64) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        if self.is_moving(now_s) {
            return self.fail(errors::NOT_WHILE_MOVING);
        }
        if self.target[3..].iter().any(|angle| *angle != 0.0) {
            return self.fail(errors::PIVOT_WHILE_ROTATED);
        }
        let mut pivot = self.pivot_mm;
        for (axis, value) in pairs {
            let Some(k) = PIVOT_AXES.iter().position(|a| a.eq_ignore_ascii_case(axis)) else {
                return self.fail(errors::INVALID_AXIS);
            };
            let Some(value) = finite(value) else {
                return self.fail(errors::INVALID_NUMBER);
            };
            pivot[k] = value;
        }
        self.pivot_mm = pivot;
    }

    /// `CCL 0`, or `CCL 1 advanced` (PI's password for level 1).
    fn set_command_level(&mut self, request: &Request) {
        match request.args.as_slice() {
            ["0"] => self.command_level = 0,
            ["1", password] if password.eq_ignore_ascii_case(LEVEL_1_PASSWORD) => {
                self.command_level = 1
            }
            [level, ..] if level.parse::<u8>().is_ok() => self.fail(errors::INVALID_PASSWORD),
            [_, ..] => self.fail(errors::PARAMETER_SYNTAX),
            [] => self.fail(errors::WRONG_PARAMETER_COUNT),
        }
    }

    /// `RON`: a hexapod's axes are always referenced by `FRF`; PI refuses the command for
    /// them (error 34).
    fn set_reference_mode(&mut self, request: &Request) {
        let Some(pairs) = request.pairs() else {
            return self.fail(errors::PARAMETER_SYNTAX);
        };
        if pairs.iter().any(|(axis, _)| axis_index(axis).is_none()) {
            return self.fail(errors::INVALID_AXIS);
        }
        self.fail(errors::NOT_FOR_STAGE);
    }

    /// `SPA?` [{AXIS PARAM}]: `AXIS 0xID=VALUE` lines; all parameters of all axes when none.
    fn parameters(&mut self, request: &Request) -> Option<String> {
        let asked: Vec<(usize, Parameter)> = if request.args.is_empty() {
            (0..6)
                .flat_map(|k| Parameter::ALL.map(|p| (k, p)))
                .collect()
        } else {
            let Some(pairs) = request.pairs() else {
                self.fail(errors::PARAMETER_SYNTAX);
                return None;
            };
            let mut asked = Vec::with_capacity(pairs.len());
            for (axis, id) in pairs {
                let Some(k) = axis_index(axis) else {
                    self.fail(errors::INVALID_AXIS);
                    return None;
                };
                let Some(parameter) = Parameter::parse(id) else {
                    self.fail(errors::UNKNOWN_PARAMETER);
                    return None;
                };
                asked.push((k, parameter));
            }
            asked
        };
        let lines: Vec<String> = asked
            .iter()
            .map(|&(k, p)| {
                let value = match p {
                    Parameter::MaxTravelPositive => self.limits.max[k].to_string(),
                    Parameter::MaxTravelNegative => self.limits.min[k].to_string(),
                    Parameter::StageName => STAGE_TYPE.to_string(),
                };
                format!("{} 0x{:X}={value}", AXES[k], p.id())
            })
            .collect();
        Some(answer_lines(&lines))
    }

    /// `SPA`: the twin's parameters follow from its cell file; below command level 1 they are
    /// protected (error 60), at level 1 the twin refuses them (error 34).
    fn set_parameters(&mut self, request: &Request) {
        if request.args.is_empty() || !request.args.len().is_multiple_of(3) {
            return self.fail(errors::PARAMETER_SYNTAX);
        }
        for triple in request.args.chunks(3) {
            if axis_index(triple[0]).is_none() {
                return self.fail(errors::INVALID_AXIS);
            }
            if Parameter::parse(triple[1]).is_none() {
                return self.fail(errors::UNKNOWN_PARAMETER);
            }
        }
        self.fail(if self.command_level < 1 {
            errors::PARAMETER_PROTECTED
        } else {
            errors::NOT_FOR_STAGE
        });
    }

    /// `KEN?` [{NAME}]: `NAME=TYPE` of the enabled coordinate system, `ZERO`.
    fn coordinate_systems(&mut self, request: &Request) -> Option<String> {
        if request.args.iter().any(|name| *name != ZERO_SYSTEM) {
            self.fail(errors::COORDINATE_SYSTEM_MISSING);
            return None;
        }
        Some(format!("{ZERO_SYSTEM}={ZERO_SYSTEM}\n"))
    }

    /// `KEN NAME`: only `ZERO` (or `0`), the twin's one coordinate system, exists.
    fn enable_coordinate_system(&mut self, request: &Request) {
        match request.args.as_slice() {
            [name] if *name == ZERO_SYSTEM || *name == "0" => {}
            [_] => self.fail(errors::COORDINATE_SYSTEM_MISSING),
            _ => self.fail(errors::WRONG_PARAMETER_COUNT),
        }
    }

    /// `KSD NAME {AXIS VALUE}`: checked as a C-887 checks it, then refused (error 34): the
    /// twin moves its platform in `ZERO` only.
    fn define_coordinate_system(&mut self, request: &Request, now_s: f64) {
        let [name, rest @ ..] = request.args.as_slice() else {
            return self.fail(errors::WRONG_PARAMETER_COUNT);
        };
        if rest.is_empty() || !rest.len().is_multiple_of(2) {
            return self.fail(errors::PARAMETER_SYNTAX);
        }
        for pair in rest.chunks(2) {
            if axis_index(pair[0]).is_none() {
                return self.fail(errors::INVALID_AXIS);
            }
            if finite(pair[1]).is_none() {
                return self.fail(errors::INVALID_NUMBER);
            }
        }
        if *name == ZERO_SYSTEM || *name == "0" {
            return self.fail(errors::COORDINATE_SYSTEM_WRITE_PROTECTED);
        }
        if self.is_moving(now_s) {
            return self.fail(errors::COORDINATE_SYSTEM_WHILE_MOVING);
        }
        self.fail(errors::NOT_FOR_STAGE);
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
}

fn finite(text: &str) -> Option<f64> {
    text.parse::<f64>().ok().filter(|v| v.is_finite())
}
