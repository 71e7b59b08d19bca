//! The GCS robot driver against the twin-server's controller and against a scripted
//! controller that fails the ways real ones do: the connection drops mid-move, an answer comes
//! late, an error code, a platform that never reaches its target. Each ends in a typed error
//! with its numbers; after a lost connection the driver moves nothing until an operator reset.

use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::gcs::protocol::{AXES, pose_to_axes};
use assembly_cell::drivers::gcs::{GcsClient, GcsError, GcsRobot, GcsSettings};
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions};
use assembly_cell::geometry::Move;
use assembly_cell::kinematics::StewartGeometry;
use assembly_cell::robot::{Robot, RobotError, RobotFault};
use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::{Arc, Mutex};
use std::time::Duration;

fn twin_server(ready: bool) -> TwinServer {
    TwinServer::start(&TwinServerOptions {
        ready,
        ..TwinServerOptions::loopback(&CellConfig::reference(), 4)
    })
    .unwrap()
}

fn drive_fault(result: Result<(), RobotError>) -> GcsError {
    match result {
        Err(RobotError::Fault(RobotFault::Drive(error))) => error,
        other => panic!("expected a drive fault, got {other:?}"),
    }
}

#[test]
fn the_driver_moves_the_twin_servers_platform_where_the_step_leads() {
    let server = twin_server(true);
    let cell = CellConfig::reference();
    let settings = GcsSettings::default();
    let mut robot = GcsRobot::connect(&server.gcs.to_string(), settings, &cell).unwrap();
    assert!(
        robot.identity().contains("twin hexapod"),
        "{}",
        robot.identity()
    );
    let start = robot.setpoint();
    let step = Move::translation(1.0, -0.5, -2.0);
    robot.execute(&step).unwrap();
    robot.execute(&step).unwrap();
    let moved = robot.setpoint().translation.vector - start.translation.vector;
    assert!(moved.norm() > 4.0, "{moved}");
    // A second connection reads the same position back.
    let again = GcsRobot::connect(&server.gcs.to_string(), settings, &cell).unwrap();
    let difference = again.setpoint().translation.vector - robot.setpoint().translation.vector;
    assert!(difference.norm() < 1e-9, "{difference}");
    assert_eq!(again.encoders_mm(), robot.encoders_mm());
}

#[test]
fn the_driver_sets_the_velocity_it_is_given_and_names_one_the_controller_refuses() {
    let server = twin_server(true);
    let cell = CellConfig::reference();
    let settings = GcsSettings {
        velocity_mm_s: Some(4.5),
        ..GcsSettings::default()
    };
    GcsRobot::connect(&server.gcs.to_string(), settings, &cell).unwrap();
    let mut client = GcsClient::connect(&server.gcs.to_string(), settings).unwrap();
    assert_eq!(client.query("VLS?").unwrap(), "4.5\n");
    let too_fast = GcsSettings {
        velocity_mm_s: Some(500.0),
        ..settings
    };
    let error = GcsRobot::connect(&server.gcs.to_string(), too_fast, &cell)
        .err()
        .expect("refused");
    assert_eq!(error, GcsError::controller(8, "VLS 500"));
    assert_eq!(
        error.to_string(),
        "controller error 8 after `VLS 500`: velocity out of limits"
    );
}

#[test]
fn an_unreferenced_controller_is_refused_by_name() {
    let server = twin_server(false);
    let error = GcsRobot::connect(
        &server.gcs.to_string(),
        GcsSettings::default(),
        &CellConfig::reference(),
    )
    .err()
    .expect("not ready");
    assert_eq!(
        error,
        GcsError::NotReady {
            axis: "X",
            what: "switched on (SVO?)"
        }
    );
}

/// What the scripted controller does with one command.
#[derive(Clone, Copy)]
enum Reply {
    /// What a ready hexapod does.
    Normal,
    /// Leaves `ERR?` this code.
    Error(i32),
    /// Closes the connection without answering.
    Close,
    /// Answers normally after this many milliseconds.
    Late(u64),
    /// Answers `ONT?` with every axis off target.
    NeverOnTarget,
    /// Answers `SPI?` with a pivot point 10 mm up the platform's axis.
    OffPivot,
}

/// A hexapod controller on a loopback port that does what a ready one does unless `script`
/// (given the command and how many times it came, from 1) says otherwise. Records every
/// command.
struct Scripted {
    address: SocketAddr,
    log: Arc<Mutex<Vec<String>>>,
}

impl Scripted {
    fn start(script: impl Fn(&str, usize) -> Reply + Send + Sync + 'static) -> Scripted {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap();
        let log = Arc::new(Mutex::new(Vec::new()));
        let home = StewartGeometry::from_config(&CellConfig::reference().robot).home_pose();
        let lines: Vec<String> = AXES
            .iter()
            .zip(pose_to_axes(&home))
            .map(|(axis, value)| format!("{axis}={value}"))
            .collect();
        let position = Arc::new(Mutex::new(lines.join(" \n") + "\n"));
        let shared = (Arc::new(script), log.clone(), position);
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let (script, log, position) = shared.clone();
                std::thread::spawn(move || serve(stream.unwrap(), &*script, &log, &position));
            }
        });
        Scripted { address, log }
    }

    fn log(&self) -> Vec<String> {
        self.log.lock().unwrap().clone()
    }
}

fn serve(
    stream: TcpStream,
    script: &(dyn Fn(&str, usize) -> Reply + Send + Sync),
    log: &Mutex<Vec<String>>,
    position: &Mutex<String>,
) {
    let mut writer = stream.try_clone().unwrap();
    let mut error = 0;
    for line in BufReader::new(stream).lines() {
        let Ok(line) = line else { return };
        let count = {
            let mut log = log.lock().unwrap();
            log.push(line.clone());
            log.iter().filter(|l| **l == line).count()
        };
        let mnemonic = line.split_whitespace().next().unwrap_or("").to_string();
        let reply = script(&mnemonic, count);
        match reply {
            Reply::Close => return,
            Reply::Late(ms) => std::thread::sleep(Duration::from_millis(ms)),
            Reply::Error(code) => error = code,
            Reply::Normal | Reply::NeverOnTarget | Reply::OffPivot => {}
        }
        let flags = |on: u8| format!("X={on} \nY={on} \nZ={on} \nU={on} \nV={on} \nW={on}\n");
        let answer = match mnemonic.as_str() {
            "*IDN?" => Some("scripted hexapod\n".to_string()),
            "SVO?" | "FRF?" => Some(flags(1)),
            "ONT?" if matches!(reply, Reply::NeverOnTarget) => Some(flags(0)),
            "ONT?" => Some(flags(1)),
            "SPI?" if matches!(reply, Reply::OffPivot) => Some("R=0 \nS=0 \nT=10\n".into()),
            "SPI?" => Some("R=0 \nS=0 \nT=0\n".into()),
            "VLS?" => Some(format!("{SCRIPTED_VELOCITY_MM_S}\n")),
            "ERR?" => Some(format!("{}\n", std::mem::take(&mut error))),
            "POS?" => Some(position.lock().unwrap().clone()),
            "MOV" if matches!(reply, Reply::Normal) => {
                let words: Vec<&str> = line.split_whitespace().skip(1).collect();
                let lines: Vec<String> = words
                    .chunks(2)
                    .map(|p| format!("{}={}", p[0], p[1]))
                    .collect();
                *position.lock().unwrap() = lines.join(" \n") + "\n";
                None
            }
            "STP" => {
                error = 10;
                None
            }
            _ => None,
        };
        if let Some(answer) = answer
            && writer.write_all(answer.as_bytes()).is_err()
        {
            return;
        }
    }
}

fn quick() -> GcsSettings {
    GcsSettings {
        connect_timeout_ms: 1000,
        // Generous for a loaded test machine; the late answer comes three times as late.
        answer_timeout_ms: 500,
        on_target_deadline_ms: 50,
        poll_interval_ms: 1,
        ..GcsSettings::default()
    }
}

/// The scripted controller's platform velocity (`VLS?`), mm/s.
const SCRIPTED_VELOCITY_MM_S: f64 = 20.0;

/// Half a millimetre down Segment I's axis from home: well inside the workspace.
fn step() -> Move {
    Move::translation(0.0, 0.0, -0.5)
}

fn connect(controller: &Scripted) -> GcsRobot {
    GcsRobot::connect(
        &controller.address.to_string(),
        quick(),
        &CellConfig::reference(),
    )
    .unwrap()
}

#[test]
fn a_connection_dropped_mid_move_latches_until_an_operator_reset() {
    let controller = Scripted::start(|command, count| match (command, count) {
        ("ONT?", 1) => Reply::Close,
        _ => Reply::Normal,
    });
    let mut robot = connect(&controller);
    let error = drive_fault(robot.execute(&step()));
    assert!(
        matches!(&error, GcsError::Dropped { command, .. } if command == "ONT?"),
        "{error:?}"
    );
    assert_eq!(robot.latched().map(|latch| &latch.error), Some(&error));
    // Holding reconnects: STP before anything else, then the position. The scripted
    // controller carried out the MOV before it dropped the connection, so the platform is not
    // where the cell last put it: the latch names that now.
    let before_hold = controller.log().len();
    robot.hold();
    assert_eq!(controller.log()[before_hold..], ["STP", "ERR?", "POS?"]);
    match robot.latched().map(|latch| &latch.error) {
        Some(GcsError::PositionMismatch { distance_mm, .. }) => {
            assert!((distance_mm - 0.5).abs() < 1e-9, "{distance_mm}")
        }
        other => panic!("{other:?}"),
    }
    let refused = drive_fault(robot.execute(&step()));
    assert!(
        matches!(&refused, GcsError::AwaitingReset { cause } if cause.contains("0.5000 mm")),
        "{refused:?}"
    );
    let moves = controller
        .log()
        .iter()
        .filter(|c| c.starts_with("MOV"))
        .count();
    assert_eq!(moves, 1, "no MOV after the drop");
    // The operator's reset, with the latch's reason shown, checks the controller again and
    // takes the platform where it is; then the robot moves.
    robot.reset().unwrap();
    assert_eq!(robot.latched(), None);
    robot.execute(&step()).unwrap();
}

#[test]
fn a_late_answer_is_a_timeout_with_its_limit_and_latches() {
    let controller = Scripted::start(|command, count| match (command, count) {
        ("POS?", 2) => Reply::Late(1500),
        _ => Reply::Normal,
    });
    let mut robot = connect(&controller);
    let error = drive_fault(robot.execute(&step()));
    assert_eq!(
        error,
        GcsError::Timeout {
            command: "POS?".into(),
            timeout_ms: 500
        }
    );
    assert!(robot.latched().is_some());
    assert!(matches!(
        drive_fault(robot.execute(&step())),
        GcsError::AwaitingReset { .. }
    ));
}

#[test]
fn a_controller_error_code_is_typed_and_the_next_move_goes_through() {
    let controller = Scripted::start(|command, count| match (command, count) {
        ("MOV", 1) => Reply::Error(7),
        _ => Reply::Normal,
    });
    let mut robot = connect(&controller);
    let before = robot.setpoint();
    let error = drive_fault(robot.execute(&step()));
    match &error {
        GcsError::Controller {
            code: 7,
            message,
            command,
        } => {
            assert_eq!(*message, "position out of limits");
            assert!(command.starts_with("MOV X "), "{command}");
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        robot.setpoint(),
        before,
        "a refused move leaves the setpoint"
    );
    assert_eq!(robot.latched(), None, "the connection is fine");
    robot.execute(&step()).unwrap();
}

#[test]
fn a_platform_that_never_arrives_is_stopped_at_the_deadline() {
    let controller = Scripted::start(|command, _| match command {
        "ONT?" => Reply::NeverOnTarget,
        _ => Reply::Normal,
    });
    let mut robot = connect(&controller);
    let error = drive_fault(robot.execute(&step()));
    // The margin and the move's own time: 0.5 mm at the controller's velocity, × 1.5.
    let move_ms = (0.5 / SCRIPTED_VELOCITY_MM_S * 1.5 * 1e3).ceil() as u64;
    assert_eq!(
        error,
        GcsError::Deadline {
            deadline_ms: 50 + move_ms
        }
    );
    let log = controller.log();
    // Connecting stops the controller first; the deadline's STP follows the MOV.
    assert_eq!(log.first().map(String::as_str), Some("STP"));
    let moved = log
        .iter()
        .position(|c| c.starts_with("MOV"))
        .expect("MOV sent");
    assert!(log[moved..].iter().any(|c| c == "STP"), "{log:?}");
    assert_eq!(robot.latched(), None);
}

#[test]
fn a_pivot_point_off_the_origin_is_refused_with_its_coordinates() {
    let controller = Scripted::start(|command, _| match command {
        "SPI?" => Reply::OffPivot,
        _ => Reply::Normal,
    });
    let error = GcsRobot::connect(
        &controller.address.to_string(),
        quick(),
        &CellConfig::reference(),
    )
    .err()
    .expect("refused");
    assert_eq!(
        error,
        GcsError::Pivot {
            r_mm: 0.0,
            s_mm: 0.0,
            t_mm: 10.0
        }
    );
}
