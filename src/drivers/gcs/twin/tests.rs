use super::*;
use crate::config::cell::CellConfig;
use crate::drivers::gcs::protocol::{axis_flags, axis_values};
use crate::sim::InitialConditions;

fn rig() -> TwinRig {
    let cell = CellConfig::reference();
    let mut rig = TwinRig::new(&cell);
    rig.begin_episode(3, InitialConditions::from_cell(&cell))
        .unwrap();
    rig
}

fn started() -> (TwinController, TwinRig) {
    let rig = rig();
    (TwinController::new(&rig, false), rig)
}

fn ready() -> (TwinController, TwinRig) {
    let rig = rig();
    (TwinController::new(&rig, true), rig)
}

/// The command's answer at `t` seconds.
fn ask(c: &mut TwinController, rig: &mut TwinRig, line: &str, t: f64) -> Option<String> {
    c.handle(line, rig, t)
}

fn error(c: &mut TwinController, rig: &mut TwinRig, t: f64) -> i32 {
    ask(c, rig, "ERR?", t).unwrap().trim().parse().unwrap()
}

fn position(c: &mut TwinController, rig: &mut TwinRig, t: f64) -> [f64; 6] {
    axis_values(&ask(c, rig, "POS?", t).unwrap(), &AXES).unwrap()
}

fn char_answer(c: &mut TwinController, rig: &mut TwinRig, byte: u8, t: f64) -> String {
    String::from_utf8(c.handle_char(byte, rig, t).unwrap()).unwrap()
}

#[test]
fn a_move_needs_servo_and_reference_and_lands_where_commanded() {
    let (mut c, mut rig) = started();
    let before = rig.setpoint();
    assert_eq!(ask(&mut c, &mut rig, "MVR Z 1", 0.0), None);
    assert_eq!(error(&mut c, &mut rig, 0.0), 5);
    assert_eq!(error(&mut c, &mut rig, 0.0), 0);
    ask(&mut c, &mut rig, "FRF", 0.0);
    assert_eq!(error(&mut c, &mut rig, 0.0), 5);
    // One servo switches all six, as on a C-887.
    ask(&mut c, &mut rig, "SVO X 1", 0.0);
    assert_eq!(
        ask(&mut c, &mut rig, "SVO?", 0.0).as_deref(),
        Some("X=1 \nY=1 \nZ=1 \nU=1 \nV=1 \nW=1\n")
    );
    ask(&mut c, &mut rig, "FRF X", 0.0);
    assert_eq!(
        ask(&mut c, &mut rig, "FRF? X W", 0.0).as_deref(),
        Some("X=1 \nW=1\n")
    );
    ask(&mut c, &mut rig, "MVR Z 1", 0.0);
    assert_eq!(error(&mut c, &mut rig, 0.0), 0);
    // 1 mm at the cell's 30 mm/s: there after 1/30 s.
    let z = before.translation.vector.z + 1.0;
    assert!((position(&mut c, &mut rig, 1.0)[2] - z).abs() < 1e-9);
    let moved = rig.setpoint().translation.vector - before.translation.vector;
    assert!(
        (moved - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-9,
        "{moved}"
    );
    // Mixed servo states are refused: the six switch together.
    ask(&mut c, &mut rig, "SVO X 1 Y 0", 1.0);
    assert_eq!(error(&mut c, &mut rig, 1.0), errors::NOT_FOR_STAGE);
}

#[test]
fn a_5_mm_move_at_30_mm_s_is_on_target_after_a_sixth_of_a_second_and_not_before() {
    let (mut c, mut rig) = ready();
    let start = position(&mut c, &mut rig, 10.0);
    let z = start[2] + 5.0;
    ask(&mut c, &mut rig, &format!("MOV Z {z}"), 10.0);
    assert_eq!(error(&mut c, &mut rig, 10.0), 0);
    let end = 10.0 + 1.0 / 6.0;
    let just_before = end - 1e-6;
    let ont = axis_flags(&ask(&mut c, &mut rig, "ONT?", just_before).unwrap()).unwrap();
    assert_eq!(ont, [true, true, false, true, true, true]);
    // #5: Z, the third axis, is bit 2.
    assert_eq!(
        char_answer(&mut c, &mut rig, MOTION_STATUS_CHAR, just_before),
        "4\n"
    );
    assert!(c.is_moving(just_before));
    // Half way, POS? answers the straight line's middle; the rig has not moved yet.
    let half = position(&mut c, &mut rig, 10.0 + 1.0 / 12.0);
    assert!((half[2] - (start[2] + 2.5)).abs() < 1e-9, "{half:?}");
    assert!((half[0] - start[0]).abs() < 1e-9 && (half[5] - start[5]).abs() < 1e-9);
    assert!((rig.setpoint().translation.z - start[2]).abs() < 1e-9);
    // A capture mid-move sees the platform where it is.
    c.place(&mut rig, 10.0 + 1.0 / 12.0);
    assert!((rig.setpoint().translation.z - (start[2] + 2.5)).abs() < 1e-9);
    let ont = axis_flags(&ask(&mut c, &mut rig, "ONT?", end).unwrap()).unwrap();
    assert_eq!(ont, [true; 6]);
    assert_eq!(
        char_answer(&mut c, &mut rig, MOTION_STATUS_CHAR, end),
        "0\n"
    );
    assert!((position(&mut c, &mut rig, end)[2] - z).abs() < 1e-9);
    assert!((rig.setpoint().translation.z - z).abs() < 1e-9);
    let log: Vec<_> = c.moves_started().collect();
    assert_eq!(log.len(), 1);
    assert_eq!(log[0].0, 10.0);
    assert_eq!(log[0].1[2], z);
}

#[test]
fn the_system_velocity_sets_the_pace_and_rotations_scale_with_it() {
    let (mut c, mut rig) = ready();
    ask(&mut c, &mut rig, "VLS 15", 0.0);
    assert_eq!(ask(&mut c, &mut rig, "VLS?", 0.0).as_deref(), Some("15\n"));
    let start = position(&mut c, &mut rig, 0.0);
    // 5 mm at 15 mm/s: 1/3 s.
    ask(&mut c, &mut rig, "MVR X 5", 0.0);
    assert!(c.is_moving(1.0 / 3.0 - 1e-6) && !c.is_moving(1.0 / 3.0));
    // 1 deg at the cell's 6 deg/s halved with the velocity: 1/3 s.
    ask(&mut c, &mut rig, "MVR W 1", 1.0);
    assert!(c.is_moving(1.0 + 1.0 / 3.0 - 1e-6) && !c.is_moving(1.0 + 1.0 / 3.0));
    let end = position(&mut c, &mut rig, 2.0);
    assert!((end[0] - start[0] - 5.0).abs() < 1e-9 && (end[5] - start[5] - 1.0).abs() < 1e-9);
}

#[test]
fn a_stop_at_half_time_leaves_the_platform_half_way() {
    for stop in ["STP", "HLT", "#24"] {
        let (mut c, mut rig) = ready();
        let start = position(&mut c, &mut rig, 0.0);
        ask(&mut c, &mut rig, "MVR Z 5", 0.0);
        if stop == "#24" {
            assert_eq!(c.handle_char(STOP_CHAR, &mut rig, 1.0 / 12.0), None);
        } else {
            ask(&mut c, &mut rig, stop, 1.0 / 12.0);
        }
        assert_eq!(error(&mut c, &mut rig, 1.0), errors::STOPPED, "{stop}");
        let here = position(&mut c, &mut rig, 1.0);
        assert!(
            (here[2] - (start[2] + 2.5)).abs() < 1e-9,
            "{stop}: {here:?}"
        );
        let target = axis_values(&ask(&mut c, &mut rig, "MOV? Z", 1.0).unwrap(), &["Z"]);
        assert!((target.unwrap()[0] - here[2]).abs() < 1e-9);
        assert!(!c.is_moving(1.0 / 12.0));
        assert!((rig.setpoint().translation.z - here[2]).abs() < 1e-9);
    }
}

#[test]
fn a_new_target_mid_move_is_approached_from_where_the_platform_is() {
    let (mut c, mut rig) = ready();
    let start = position(&mut c, &mut rig, 0.0);
    ask(&mut c, &mut rig, &format!("MOV Z {}", start[2] + 5.0), 0.0);
    // At 1/12 s the platform is 2.5 mm up; back to the start takes 2.5 mm / 30 mm/s.
    ask(&mut c, &mut rig, &format!("MOV Z {}", start[2]), 1.0 / 12.0);
    assert_eq!(error(&mut c, &mut rig, 1.0 / 12.0), 0);
    let midway = position(&mut c, &mut rig, 1.0 / 12.0 + 1.0 / 24.0);
    assert!((midway[2] - (start[2] + 1.25)).abs() < 1e-9, "{midway:?}");
    assert!(c.is_moving(1.0 / 6.0 - 1e-6) && !c.is_moving(1.0 / 6.0));
    assert_eq!(c.moves_started().count(), 2);
}

#[test]
fn instant_moves_arrive_at_once() {
    let (c, mut rig) = ready();
    let mut c = c.with_instant_moves(true);
    let start = position(&mut c, &mut rig, 0.0);
    ask(&mut c, &mut rig, "MVR Z 5", 0.0);
    assert!(!c.is_moving(0.0));
    assert!((rig.setpoint().translation.z - start[2] - 5.0).abs() < 1e-9);
    assert_eq!(
        char_answer(&mut c, &mut rig, MOTION_STATUS_CHAR, 0.0),
        "0\n"
    );
}

#[test]
fn the_status_register_sets_pis_bits() {
    let (mut c, mut rig) = started();
    // Power-on: on target, servos off.
    assert_eq!(char_answer(&mut c, &mut rig, STATUS_CHAR, 0.0), "0x8000\n");
    let (mut c, mut rig) = ready();
    assert_eq!(char_answer(&mut c, &mut rig, STATUS_CHAR, 0.0), "0x9000\n");
    ask(&mut c, &mut rig, "MVR X 5", 0.0);
    // Moving, servos on.
    assert_eq!(char_answer(&mut c, &mut rig, STATUS_CHAR, 0.1), "0x3000\n");
    ask(&mut c, &mut rig, "FOO", 1.0);
    // Still, servos on, an error pending.
    assert_eq!(char_answer(&mut c, &mut rig, STATUS_CHAR, 1.0), "0x9100\n");
    assert_eq!(error(&mut c, &mut rig, 1.0), errors::UNKNOWN_COMMAND);
}

#[test]
fn an_unknown_command_leaves_error_2_and_the_next_command_is_answered() {
    let (mut c, mut rig) = ready();
    assert_eq!(ask(&mut c, &mut rig, "FOO? X", 0.0), None);
    assert_eq!(c.handle_char(3, &mut rig, 0.0), None);
    assert!(
        ask(&mut c, &mut rig, "POS? X", 0.0)
            .unwrap()
            .starts_with("X=")
    );
    assert_eq!(error(&mut c, &mut rig, 0.0), errors::UNKNOWN_COMMAND);
    assert_eq!(error(&mut c, &mut rig, 0.0), 0);
}

#[test]
fn every_command_in_the_help_is_known() {
    let (mut c, mut rig) = ready();
    let help = ask(&mut c, &mut rig, "HLP?", 0.0).unwrap();
    let lines: Vec<&str> = help.lines().collect();
    let names: Vec<&str> = lines[1..lines.len() - 1]
        .iter()
        .map(|l| l.split_whitespace().next().unwrap())
        .collect();
    assert_eq!(names.len(), COMMANDS.len() + 1);
    for name in names {
        if let Some(code) = name.strip_prefix('#') {
            c.handle_char(code.parse().unwrap(), &mut rig, 0.0);
        } else {
            // Commands with arguments the twin accepts where it can.
            let line = match name {
                "MOV" | "MVR" => "MVR X 0".to_string(),
                "VMO?" => "VMO? X 0".into(),
                "SVO" => "SVO X 1".into(),
                "VLS" => "VLS 10".into(),
                "SPI" => "SPI R 0".into(),
                "CCL" => "CCL 0".into(),
                "KEN" => "KEN ZERO".into(),
                "EPISODE" => "EPISODE 3 50 1".into(),
                other => other.to_string(),
            };
            ask(&mut c, &mut rig, &line, 0.0);
        }
        assert_ne!(
            error(&mut c, &mut rig, 0.0),
            errors::UNKNOWN_COMMAND,
            "{name}"
        );
    }
}

#[test]
fn limits_parameters_and_virtual_moves_agree_with_the_reach() {
    let (mut c, mut rig) = ready();
    let tmx = axis_values(&ask(&mut c, &mut rig, "TMX?", 0.0).unwrap(), &AXES).unwrap();
    let tmn = axis_values(&ask(&mut c, &mut rig, "TMN?", 0.0).unwrap(), &AXES).unwrap();
    let limits = TravelLimits::of(&rig);
    assert_eq!((tmn, tmx), (limits.min, limits.max));
    assert_eq!(
        ask(&mut c, &mut rig, "SPA? Z 0x15 Z 0x30 X 60", 0.0),
        Some(format!(
            "Z 0x15={} \nZ 0x30={} \nX 0x3C={STAGE_TYPE}\n",
            tmx[2], tmn[2]
        ))
    );
    assert_eq!(
        ask(&mut c, &mut rig, "CST? Y", 0.0),
        Some(format!("Y={STAGE_TYPE}\n"))
    );
    assert_eq!(
        ask(&mut c, &mut rig, "RON? U", 0.0).as_deref(),
        Some("U=1\n")
    );
    // VMO? sets the named axes in the last target: the home pose's Z limit is reachable from
    // home, a millimetre beyond is not, and nothing moves.
    let home = rig.cell().robot.home_height_mm;
    let vmo = |c: &mut TwinController, rig: &mut TwinRig, z: f64| {
        ask(c, rig, &format!("VMO? X 0 Y 0 Z {z} U 0 V 0 W 0"), 0.0)
    };
    assert_eq!(vmo(&mut c, &mut rig, tmx[2]).as_deref(), Some("1\n"));
    assert_eq!(vmo(&mut c, &mut rig, tmx[2] + 1.0).as_deref(), Some("0\n"));
    assert!(tmn[2] < home && home < tmx[2]);
    assert_eq!(c.moves_started().count(), 0);
    assert_eq!(error(&mut c, &mut rig, 0.0), 0);
}

#[test]
fn levels_coordinate_systems_and_versions_answer_as_on_a_c887() {
    let (mut c, mut rig) = ready();
    assert_eq!(ask(&mut c, &mut rig, "CCL?", 0.0).as_deref(), Some("0\n"));
    ask(&mut c, &mut rig, "CCL 1 advanced", 0.0);
    assert_eq!(ask(&mut c, &mut rig, "CCL?", 0.0).as_deref(), Some("1\n"));
    ask(&mut c, &mut rig, "SPA X 0x15 100", 0.0);
    assert_eq!(error(&mut c, &mut rig, 0.0), errors::NOT_FOR_STAGE);
    ask(&mut c, &mut rig, "CCL 0", 0.0);
    assert_eq!(
        ask(&mut c, &mut rig, "KEN?", 0.0).as_deref(),
        Some("ZERO=ZERO\n")
    );
    ask(&mut c, &mut rig, "KEN ZERO", 0.0);
    assert_eq!(error(&mut c, &mut rig, 0.0), 0);
    let version = ask(&mut c, &mut rig, "VER?", 0.0).unwrap();
    assert!(
        version.starts_with("celld: ") && version.contains(" \n"),
        "{version}"
    );
    assert_eq!(
        ask(&mut c, &mut rig, "SSN?", 0.0),
        Some(format!("{SERIAL_NUMBER}\n"))
    );
    let parameters = ask(&mut c, &mut rig, "HPA?", 0.0).unwrap();
    assert!(parameters.contains("0x15=\t"), "{parameters}");
}

#[test]
fn bad_commands_leave_their_error_code() {
    let (mut c, mut rig) = started();
    for (line, code) in [
        ("FOO", errors::UNKNOWN_COMMAND),
        ("POS? Q", errors::INVALID_AXIS),
        ("SVO X", errors::PARAMETER_SYNTAX),
        ("VLS 500", errors::VELOCITY_OUT_OF_LIMITS),
        ("STP", errors::STOPPED),
        ("RON X 1", errors::NOT_FOR_STAGE),
        ("SPA X 0x15 100", errors::PARAMETER_PROTECTED),
        ("SPA X 0x99 1", errors::UNKNOWN_PARAMETER),
        ("SPA? X 0x99", errors::UNKNOWN_PARAMETER),
        ("CCL 1 guess", errors::INVALID_PASSWORD),
        ("KEN USER", errors::COORDINATE_SYSTEM_MISSING),
        ("KEN? USER", errors::COORDINATE_SYSTEM_MISSING),
        ("KSD USER X 1", errors::NOT_FOR_STAGE),
        ("KSD ZERO X 1", errors::COORDINATE_SYSTEM_WRITE_PROTECTED),
        ("KSD USER Q 1", errors::INVALID_AXIS),
        ("VMO? X abc", errors::INVALID_NUMBER),
    ] {
        c.handle(line, &mut rig, 0.0);
        assert_eq!(error(&mut c, &mut rig, 0.0), code, "{line}");
    }
    let (mut ready, mut rig) = ready();
    ready.handle("MOV Z 100000", &mut rig, 0.0);
    assert_eq!(
        error(&mut ready, &mut rig, 0.0),
        errors::POSITION_OUT_OF_LIMITS
    );
    ready.handle("MVR X 5", &mut rig, 0.0);
    ready.handle("KSD USER X 1", &mut rig, 0.01);
    assert_eq!(
        error(&mut ready, &mut rig, 0.01),
        errors::COORDINATE_SYSTEM_WHILE_MOVING
    );
}

#[test]
fn the_pivot_point_turns_the_platform_about_itself() {
    let (_, mut rig) = started();
    let mut c = TwinController::new(&rig, true);
    let setpoint = rig.setpoint();
    // Only while U V W are 0.
    let axes = c.axes_of(&setpoint);
    if axes[3..].iter().any(|a| *a != 0.0) {
        c.handle("SPI R 0 S 0 T 10", &mut rig, 0.0);
        assert_eq!(error(&mut c, &mut rig, 0.0), errors::PIVOT_WHILE_ROTATED);
    }
    c.pivot_mm = [0.0, 0.0, 10.0];
    let pose = c.pose_of(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    let back = c.axes_of(&pose);
    for (a, b) in back.iter().zip([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) {
        assert!((a - b).abs() < 1e-9, "{back:?}");
    }
}
