//! Nothing runs that the cell gave up on. The GCS driver reaches the twin-server's controller
//! (moves taking their time at the cell's speeds) through an in-process relay that stalls
//! (holds every byte both ways, as a controller stopped with SIGSTOP does, then delivers them
//! in order), delays, or holds one connection's command back and delivers it after a newer
//! connection's. After a stall, the platform must be where the cell last put it; where a relay
//! delivers a command after the cell has checked, the driver must say so (`position_mismatch`)
//! at the operator's reset instead of moving on.

use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::gcs::protocol::{AXES, axis_values, pose_to_axes};
use assembly_cell::drivers::gcs::{GcsClient, GcsError, GcsRobot, GcsSettings};
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions};
use assembly_cell::geometry::Move;
use assembly_cell::robot::{Robot, RobotError, RobotFault};
use rand::{Rng, SeedableRng};
use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// What the relay does to the bytes between the driver and the controller.
#[derive(Default)]
struct Faults {
    /// Hold every byte, both ways, until cleared.
    stalled: bool,
    /// Stall as this many more `MOV`s have passed and the next reaches the relay, before
    /// passing it on.
    stall_at_move: Option<u32>,
    /// Added before each chunk is passed on.
    delay: Duration,
    /// Withhold the next `MOV` line from the controller, close that connection, and keep the
    /// line for [`Relay::deliver_withheld`].
    withhold_next_move: bool,
    withheld: Option<(Vec<u8>, SocketAddr)>,
}

/// A TCP relay in front of a controller.
struct Relay {
    address: SocketAddr,
    faults: Arc<Mutex<Faults>>,
}

impl Relay {
    fn start(upstream: SocketAddr) -> Relay {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap();
        let faults = Arc::new(Mutex::new(Faults::default()));
        let shared = faults.clone();
        std::thread::spawn(move || {
            for client in listener.incoming() {
                let Ok(client) = client else { continue };
                let Ok(server) = TcpStream::connect(upstream) else {
                    continue;
                };
                let _ = (client.set_nodelay(true), server.set_nodelay(true));
                let (c2, s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                let (f1, f2) = (shared.clone(), shared.clone());
                std::thread::spawn(move || pump(client, server, &f1, Some(upstream)));
                std::thread::spawn(move || pump(s2, c2, &f2, None));
            }
        });
        Relay { address, faults }
    }

    fn set(&self, change: impl FnOnce(&mut Faults)) {
        change(&mut self.faults.lock().unwrap());
    }

    fn withheld(&self) -> bool {
        self.faults.lock().unwrap().withheld.is_some()
    }

    /// Sends the withheld command to the controller on a connection of its own.
    fn deliver_withheld(&self) {
        let withheld = self.faults.lock().unwrap().withheld.take();
        if let Some((line, upstream)) = withheld {
            let mut late = TcpStream::connect(upstream).unwrap();
            late.write_all(&line).unwrap();
            // Give the controller time to read it before the connection closes.
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Passes bytes from `from` to `to` as the faults allow. `upstream` is set on the driver's
/// side (commands), where a `MOV` may be withheld.
fn pump(
    mut from: TcpStream,
    mut to: TcpStream,
    faults: &Mutex<Faults>,
    upstream: Option<SocketAddr>,
) {
    let mut chunk = [0u8; 4096];
    loop {
        let n = match from.read(&mut chunk) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        let mut bytes = chunk[..n].to_vec();
        let mut closed = false;
        let delay = {
            let mut state = faults.lock().unwrap();
            if upstream.is_some() && find(&bytes, b"MOV ").is_some() {
                match state.stall_at_move {
                    Some(0) => {
                        state.stall_at_move = None;
                        state.stalled = true;
                    }
                    Some(more) => state.stall_at_move = Some(more - 1),
                    None => {}
                }
            }
            // While stalled, what arrives is kept, as a stopped controller's socket keeps it,
            // and passed on in one piece when the stall ends.
            while state.stalled {
                drop(state);
                if !closed {
                    closed = read_on(&mut from, &mut bytes);
                } else {
                    std::thread::sleep(Duration::from_millis(1));
                }
                state = faults.lock().unwrap();
            }
            if let Some(upstream) = upstream
                && state.withhold_next_move
                && let Some(start) = find(&bytes, b"MOV ")
            {
                let end = start + find(&bytes[start..], b"\n").unwrap() + 1;
                state.withhold_next_move = false;
                state.withheld = Some((bytes[start..end].to_vec(), upstream));
                let _ = to.write_all(&bytes[..start]);
                // The connection breaks: nothing after the command reaches the controller.
                let _ = from.shutdown(Shutdown::Both);
                let _ = to.shutdown(Shutdown::Both);
                return;
            }
            state.delay
        };
        if !delay.is_zero() {
            std::thread::sleep(delay);
        }
        if to.write_all(&bytes).is_err() || closed {
            break;
        }
    }
    let _ = to.shutdown(Shutdown::Write);
}

/// Reads what arrives within a millisecond onto `bytes`; whether the sender has closed.
fn read_on(from: &mut TcpStream, bytes: &mut Vec<u8>) -> bool {
    let mut chunk = [0u8; 4096];
    let _ = from.set_read_timeout(Some(Duration::from_millis(1)));
    let closed = match from.read(&mut chunk) {
        Ok(0) => true,
        Ok(n) => {
            bytes.extend_from_slice(&chunk[..n]);
            false
        }
        Err(error) => !matches!(error.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut),
    };
    let _ = from.set_read_timeout(None);
    closed
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

fn timed_twin_server() -> TwinServer {
    TwinServer::start(&TwinServerOptions {
        instant_moves: false,
        ..TwinServerOptions::loopback(&CellConfig::reference(), 4)
    })
    .unwrap()
}

fn settings() -> GcsSettings {
    GcsSettings {
        answer_timeout_ms: 100,
        on_target_deadline_ms: 100,
        poll_interval_ms: 2,
        ..GcsSettings::default()
    }
}

/// The controller's position, X Y Z U V W, asked on a connection of its own.
fn position(server: &TwinServer) -> [f64; 6] {
    let mut client = GcsClient::connect(&server.gcs.to_string(), settings()).unwrap();
    let answer = client.query("POS?").unwrap();
    axis_values(&answer, &AXES).unwrap()
}

/// The largest difference of X Y Z (mm) and of U V W (deg) between two positions.
fn apart(a: &[f64; 6], b: &[f64; 6]) -> (f64, f64) {
    let largest =
        |range: std::ops::Range<usize>| range.map(|k| (a[k] - b[k]).abs()).fold(0.0, f64::max);
    (largest(0..3), largest(3..6))
}

fn drive_fault(result: Result<(), RobotError>) -> Option<GcsError> {
    match result {
        Ok(()) => None,
        Err(RobotError::Fault(RobotFault::Drive(error))) => Some(error),
        Err(other) => panic!("{other:?}"),
    }
}

/// Resets until the driver takes the platform again: once more after it names a mismatch.
fn reset(robot: &mut GcsRobot) -> Option<GcsError> {
    for _ in 0..50 {
        match robot.reset() {
            Ok(()) => return None,
            Err(error @ GcsError::PositionMismatch { .. }) => {
                robot
                    .reset()
                    .expect("a second reset takes the platform where it is");
                return Some(error);
            }
            // The relay may still be passing on what it held.
            Err(_) => std::thread::sleep(Duration::from_millis(20)),
        }
    }
    panic!("the driver never came back")
}

/// A held `MOV` that the `STP` written after it stops runs for the time between the twin's
/// controller taking the one and the other: microseconds, or a millisecond or two when its
/// thread is put aside on a loaded machine (0.03 mm at 30 mm/s). A move of its own is 0.5 to
/// 2 mm, and that is what the driver without its `STP` after giving up lets run.
const RAN: f64 = 0.05;

/// 100 short jobs; each is stalled for a quarter of a second once: half of them as a `MOV`
/// is on its way (the command held until after the driver gave up on it), half at a random
/// moment (while the platform moves, or while the driver polls). The platform
/// must not move after the driver gave up (beyond the microseconds a held `MOV` runs before
/// the `STP` written after it stops it), and after the operator's reset the driver knows
/// where it is.
#[test]
fn a_stalled_controller_carries_out_nothing_the_cell_gave_up_on() {
    let server = timed_twin_server();
    let relay = Relay::start(server.gcs);
    let cell = CellConfig::reference();
    let mut robot = GcsRobot::connect(&relay.address.to_string(), settings(), &cell).unwrap();
    let tolerance = settings().position_tolerance_mm;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let (mut gave_up, mut ran_after, mut largest_mm) = (0, Vec::new(), 0.0_f64);
    for job in 0..100 {
        let stall_after = Duration::from_millis(rng.random_range(0..120));
        let at_move = (job % 2 == 0).then(|| rng.random_range(0..6));
        relay.set(|f| f.stall_at_move = at_move);
        let stall = {
            let faults = relay.faults.clone();
            std::thread::spawn(move || {
                if at_move.is_some() {
                    // Until the relay stalls at its move (the job's moves take under 2 s).
                    let waiting = std::time::Instant::now();
                    while !faults.lock().unwrap().stalled {
                        if waiting.elapsed() > Duration::from_secs(5) {
                            return;
                        }
                        std::thread::sleep(Duration::from_micros(200));
                    }
                } else {
                    std::thread::sleep(stall_after);
                    faults.lock().unwrap().stalled = true;
                }
                std::thread::sleep(Duration::from_millis(250));
                faults.lock().unwrap().stalled = false;
            })
        };
        let mut failed = None;
        for k in 0..6 {
            // Back and forth along Segment I's axis, 0.5 to 2 mm a move.
            let length = rng.random_range(0.5..2.0) * if k % 2 == 0 { -1.0 } else { 1.0 };
            if let Some(error) = drive_fault(robot.execute(&Move::translation(0.0, 0.0, length))) {
                failed = Some(error);
                break;
            }
        }
        // Where the platform is as the driver gives up (read past the relay).
        let at_give_up = position(&server);
        stall.join().unwrap();
        let Some(error) = failed else { continue };
        // A stop the controller read late (one written on a connection given up, after the
        // relay let it through) fails the move it stopped: the platform is held, as it must.
        let stopped = matches!(error, GcsError::Controller { code: 10, .. });
        assert!(error.latches() || stopped, "job {job}: {error}");
        gave_up += 1;
        // Everything the relay held has reached the controller, and a move it held would
        // have run to its end (2 mm at 30 mm/s: 67 ms) before the cell's next connection
        // could stop it.
        std::thread::sleep(Duration::from_millis(200));
        let (mm, deg) = apart(&position(&server), &at_give_up);
        largest_mm = largest_mm.max(mm);
        if mm > RAN || deg > RAN {
            ran_after.push((job, mm, deg));
        }
        robot.hold();
        reset(&mut robot);
        // After the reset the driver knows where the platform is.
        let (mm, deg) = apart(&position(&server), &pose_to_axes(&robot.setpoint()));
        assert!(
            mm <= tolerance && deg <= tolerance,
            "job {job}: {mm} mm {deg} deg"
        );
    }
    eprintln!(
        "{gave_up} of 100 stalls made the driver give up; moves after: {ran_after:?}; \
         the platform moved at most {largest_mm:.6} mm after a give-up"
    );
    assert!(
        gave_up >= 50,
        "only {gave_up} of 100 stalls made the driver give up"
    );
    assert!(
        ran_after.is_empty(),
        "moves ran after the cell gave up on them (job, mm, deg): {ran_after:?}"
    );
}

/// The worst a relay can do: it breaks the connection right after a `MOV`, so the `STP` the
/// driver writes after giving up never follows it, and delivers that `MOV` after the driver's
/// new connection has stopped the controller and checked the position. The platform moves;
/// the operator's reset must find it and refuse once with the distance.
#[test]
fn a_command_delivered_after_the_check_is_found_at_the_reset() {
    let server = timed_twin_server();
    let relay = Relay::start(server.gcs);
    let cell = CellConfig::reference();
    let mut robot = GcsRobot::connect(&relay.address.to_string(), settings(), &cell).unwrap();
    robot
        .execute(&Move::translation(0.0, 0.0, -1.0))
        .expect("a first move");
    let before = pose_to_axes(&robot.setpoint());
    relay.set(|f| f.withhold_next_move = true);
    let error = drive_fault(robot.execute(&Move::translation(0.0, 0.0, -2.0))).expect("dropped");
    assert!(error.is_connection_lost(), "{error}");
    assert!(relay.withheld());
    robot.hold();
    assert!(
        !matches!(
            robot.latched().map(|l| &l.error),
            Some(GcsError::PositionMismatch { .. })
        ),
        "nothing has moved yet"
    );
    relay.deliver_withheld();
    // The withheld move, 2 mm at the cell's 30 mm/s, runs to its end.
    std::thread::sleep(Duration::from_millis(200));
    let (moved_mm, _) = apart(&position(&server), &before);
    assert!((moved_mm - 2.0).abs() < 0.01, "{moved_mm}");
    match robot.reset() {
        Err(GcsError::PositionMismatch { distance_mm, .. }) => {
            assert!((distance_mm - 2.0).abs() < 0.01, "{distance_mm}")
        }
        other => panic!("the reset took a platform that moved unbidden: {other:?}"),
    }
    assert_eq!(
        robot.latched().map(|l| l.error.code()),
        Some("position_mismatch")
    );
    // Seen and acknowledged: the second reset takes the platform where it is.
    robot.reset().unwrap();
    let (mm, _) = apart(&position(&server), &pose_to_axes(&robot.setpoint()));
    assert!(mm < 1e-6, "{mm}");
}

/// Answers that come late, but within the timeout, cost nothing: every move arrives.
#[test]
fn a_slow_relay_within_the_timeout_is_no_fault() {
    let server = timed_twin_server();
    let relay = Relay::start(server.gcs);
    relay.set(|f| f.delay = Duration::from_millis(5));
    let cell = CellConfig::reference();
    let mut robot = GcsRobot::connect(&relay.address.to_string(), settings(), &cell).unwrap();
    for k in 0..4 {
        let length = if k % 2 == 0 { -1.0 } else { 1.0 };
        robot.execute(&Move::translation(0.0, 0.0, length)).unwrap();
    }
    let (mm, _) = apart(&position(&server), &pose_to_axes(&robot.setpoint()));
    assert!(mm < 1e-6, "{mm}");
    assert_eq!(robot.latched(), None);
}
