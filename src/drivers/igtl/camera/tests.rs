use super::*;
use crate::config::cell::CellConfig;
use crate::drivers::igtl::codec::PointElement;

fn assembler() -> FrameAssembler {
    FrameAssembler::new(&CellFrames::from_config(&CellConfig::reference()), 500)
}

fn points(at_s: f64, elements: &[(&str, &str, [f32; 3])]) -> Message {
    Message {
        version: 1,
        device: "camera".into(),
        timestamp: Timestamp::from_secs_f64(at_s),
        message_id: 0,
        content: Content::Point(
            elements
                .iter()
                .map(|(group, name, position)| PointElement {
                    name: name.to_string(),
                    group: group.to_string(),
                    rgba: [255; 4],
                    position: *position,
                    diameter: 0.0,
                    owner: String::new(),
                })
                .collect(),
        ),
    }
}

fn transform(at_s: f64, device: &str, pose: &Pose) -> Message {
    let r = pose.rotation.to_rotation_matrix();
    let t = pose.translation.vector;
    let m = r.matrix();
    let values = [
        m[(0, 0)],
        m[(1, 0)],
        m[(2, 0)],
        m[(0, 1)],
        m[(1, 1)],
        m[(2, 1)],
        m[(0, 2)],
        m[(1, 2)],
        m[(2, 2)],
        t.x,
        t.y,
        t.z,
    ];
    Message {
        version: 2,
        device: device.into(),
        timestamp: Timestamp::from_secs_f64(at_s),
        message_id: 0,
        content: Content::Transform(values.map(|v| v as f32)),
    }
}

#[test]
fn points_become_a_frame_numbered_by_their_timestamp() {
    let mut assembler = assembler();
    let now = Timestamp::from_secs_f64(100.0);
    let first = points(
        99.9,
        &[("C1", "0", [1.0, 2.0, 3.0]), ("C2", "5", [0.0, 0.0, 1.5])],
    );
    let frame = assembler.take(&first, now).unwrap().unwrap();
    assert_eq!(frame.sequence, 1);
    assert_eq!(frame.points.len(), 2);
    assert_eq!(frame.points[1].fixture, Fixture::C2);
    assert_eq!(frame.points[1].id, 5);
    assert_eq!(frame.points[1].position_mm, Point3::new(0.0, 0.0, 1.5));
    let newer = points(99.95, &[("C1", "0", [1.0, 2.0, 3.0])]);
    assert_eq!(assembler.take(&newer, now).unwrap().unwrap().sequence, 2);
    // The same capture again keeps its number; an older one gets a lower one.
    assert_eq!(assembler.take(&newer, now).unwrap().unwrap().sequence, 2);
    assert_eq!(assembler.take(&first, now).unwrap().unwrap().sequence, 1);
    assert_eq!(
        assembler
            .take(&points(99.99, &[]), now)
            .unwrap()
            .unwrap()
            .sequence,
        3
    );
}

#[test]
fn stale_frames_and_unknown_points_are_refused_with_their_numbers() {
    let mut assembler = assembler();
    let now = Timestamp::from_secs_f64(100.0);
    match assembler.take(&points(99.0, &[]), now) {
        Err(FrameError::Stale {
            age_ms,
            max_ms: 500,
        }) => {
            assert!((age_ms - 1000.0).abs() < 1e-3, "{age_ms}")
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        assembler.take(&points(99.9, &[("C3", "1", [0.0; 3])]), now),
        Err(FrameError::UnknownPoint {
            group: "C3".into(),
            name: "1".into()
        })
    );
    assert_eq!(
        assembler.take(&points(99.9, &[("C1", "x", [0.0; 3])]), now),
        Err(FrameError::UnknownPoint {
            group: "C1".into(),
            name: "x".into()
        })
    );
}

#[test]
fn a_trackers_two_fixture_transforms_make_one_frame_of_layout_points() {
    let cell = CellConfig::reference();
    let frames = CellFrames::from_config(&cell);
    let mut assembler = assembler();
    let now = Timestamp::from_secs_f64(50.0);
    let c1 = crate::geometry::pose::pose_from_mm_deg(
        Vector3::new(10.0, -20.0, 900.0),
        Vector3::new(1.0, 2.0, 30.0),
    );
    let c2 = Pose::translation(0.0, 0.0, 1000.0);
    assert_eq!(assembler.take(&transform(49.9, "C1", &c1), now), Ok(None));
    let frame = assembler
        .take(&transform(49.9, "C2", &c2), now)
        .unwrap()
        .unwrap();
    assert_eq!(
        frame.points.len(),
        frames.c1_points_mm.len() + frames.c2_points_mm.len()
    );
    let seen = frame.points[0].position_mm;
    let expected = c1 * frames.c1_points_mm[0];
    // The matrix travels as f32: about 1e-4 mm at a metre.
    assert!((seen - expected).norm() < 1e-3, "{seen} {expected}");
    // A fixture's transform whose partner has another timestamp waits for its own partner.
    assert_eq!(assembler.take(&transform(49.95, "C1", &c1), now), Ok(None));
    assert_eq!(assembler.take(&transform(49.96, "C2", &c2), now), Ok(None));
    let mut skewed = transform(49.97, "C1", &c1);
    if let Content::Transform(m) = &mut skewed.content {
        m[0] = 2.0;
    }
    assert_eq!(
        assembler.take(&skewed, now),
        Err(FrameError::BadTransform {
            device: "C1".into()
        })
    );
    assert_eq!(
        assembler.take(&transform(49.97, "tool", &c1), now),
        Err(FrameError::BadTransform {
            device: "tool".into()
        })
    );
}

#[test]
fn a_damaged_body_is_skipped_and_a_garbage_header_ends_the_stream() {
    let good = points(1.0, &[("C1", "0", [1.0, 2.0, 3.0])]).encode();
    let mut damaged = good.clone();
    let last = damaged.len() - 1;
    damaged[last] ^= 0xFF;
    let mut stream = Vec::new();
    stream.extend_from_slice(&damaged);
    stream.extend_from_slice(&good);
    stream.extend_from_slice(&[0xEE; HEADER_BYTES]);
    let mut reader = std::io::Cursor::new(stream);
    let mut body = Vec::new();
    let first = read_message(&mut reader, &mut body).unwrap_err();
    assert!(
        matches!(first, FrameError::Garbage(IgtlError::Crc { .. })),
        "{first:?}"
    );
    assert!(!first.ends_connection());
    assert_eq!(read_message(&mut reader, &mut body).unwrap().encode(), good);
    let third = read_message(&mut reader, &mut body).unwrap_err();
    assert_eq!(
        third,
        FrameError::BadHeader(IgtlError::Version { version: 0xEEEE })
    );
    assert!(third.ends_connection() && third.code() == "camera_garbage");
    assert!(matches!(
        read_message(&mut reader, &mut body),
        Err(FrameError::Dropped { .. })
    ));
}

/// A POINT frame of the reference layout's points, its first point's x the message's number
/// `k`, so a test can tell which message a frame came from.
fn numbered(k: usize, at_s: f64) -> Message {
    let mut elements = vec![("C1", "0", [k as f32, 0.0, 2000.0])];
    for id in ["1", "2"] {
        elements.push(("C1", id, [0.0, 1.0, 2000.0]));
    }
    points(at_s, &elements)
}

/// The message number of `frame`: its first point's x.
fn number_of(frame: &CameraFrame) -> usize {
    frame.points[0].position_mm.x as usize
}

/// How far the test cameras' clocks run ahead of the driver's, s: a loaded test machine's
/// delays between a backlog's stamping and its capture then cannot make its newest frame
/// stale.
const AHEAD_S: f64 = 1.0;

/// A streaming camera on a free loopback port that, once a client connects, writes
/// `backlog` at once (what queued while the cell was idle), then every `period` one more
/// message numbered from `live`, stamped as it is sent, then stays connected until the client
/// leaves. Its clock runs a second ahead of the driver's ([`AHEAD_S`]).
fn streaming_camera(
    backlog: Vec<Message>,
    live: std::ops::Range<usize>,
    period: Duration,
) -> std::net::SocketAddr {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        let (mut client, _) = listener.accept().unwrap();
        let bytes: Vec<u8> = backlog.iter().flat_map(Message::encode).collect();
        client.write_all(&bytes).unwrap();
        for k in live {
            std::thread::sleep(period);
            let message = numbered(k, Timestamp::now().as_secs_f64() + AHEAD_S);
            if client.write_all(&message.encode()).is_err() {
                return;
            }
        }
        let mut rest = Vec::new();
        let _ = client.read_to_end(&mut rest);
    });
    address
}

/// A streaming camera's driver: frames up to 2 s old accepted (a loaded test machine may take
/// a while between the backlog's writing and its capture).
fn streaming(address: std::net::SocketAddr, frame_timeout_ms: u64) -> IgtlCamera {
    let settings = CameraSettings {
        frame_timeout_ms,
        max_age_ms: 2000,
        triggered: false,
        ..CameraSettings::default()
    };
    let frames = CellFrames::from_config(&CellConfig::reference());
    IgtlCamera::connect(&address.to_string(), settings, &frames).unwrap()
}

/// Waits until the camera's reader has taken in `count` messages.
fn received(camera: &IgtlCamera, count: u64) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while camera.inbox.received() < count {
        assert!(Instant::now() < deadline, "{}", camera.inbox.received());
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn a_streaming_camera_after_an_idle_spell_gives_its_newest_frame() {
    // 30 Hz for ten seconds of idle: 300 frames queued, most of them stale.
    let now = Timestamp::now().as_secs_f64() + AHEAD_S;
    let backlog: Vec<Message> = (0..300)
        .map(|k| numbered(k, now - 10.0 + (k + 1) as f64 / 30.0))
        .collect();
    let mut camera = streaming(
        streaming_camera(backlog, 300..550, Duration::from_millis(33)),
        2000,
    );
    received(&camera, 300);
    let frame = camera.capture().unwrap();
    assert_eq!(number_of(&frame), 299);
    assert!(camera.inbox.is_empty());
    // Then frame after frame as the stream goes on, each newer than the last, none refused.
    let mut last = (299, frame.sequence);
    for _ in 0..5 {
        std::thread::sleep(Duration::from_millis(120));
        let frame = camera.capture().unwrap();
        assert!(number_of(&frame) > last.0 && frame.sequence > last.1);
        last = (number_of(&frame), frame.sequence);
    }
}

#[test]
fn a_backlog_past_the_inbox_keeps_the_newest_and_a_stale_one_alone_is_refused() {
    // 100 Hz for a minute: far more than the inbox keeps; the newest are the ones kept.
    let now = Timestamp::now().as_secs_f64() + AHEAD_S;
    let count = 6000;
    let backlog: Vec<Message> = (0..count)
        .map(|k| numbered(k, now - 60.0 + (k + 1) as f64 / 100.0))
        .collect();
    let mut camera = streaming(streaming_camera(backlog, 0..0, Duration::ZERO), 50);
    received(&camera, count as u64);
    assert_eq!(camera.inbox.len(), inbox::INBOX_MESSAGES);
    assert_eq!(number_of(&camera.capture().unwrap()), count - 1);
    // Nothing newer comes: within the frame timeout, a silent camera.
    assert_eq!(camera.capture(), Err(FrameError::Timeout { waited_ms: 50 }));

    // A camera whose whole backlog is stale and that then falls silent: the capture waits no
    // longer than the frame timeout and says why the frames were refused.
    let backlog: Vec<Message> = (0..40)
        .map(|k| numbered(k, now - 10.0 + k as f64 / 30.0))
        .collect();
    let mut camera = streaming(streaming_camera(backlog, 0..0, Duration::ZERO), 50);
    received(&camera, 40);
    assert!(matches!(
        camera.capture(),
        Err(FrameError::Stale { max_ms: 2000, .. })
    ));
}

#[test]
fn a_streaming_tracker_after_an_idle_spell_gives_its_newest_pair() {
    // Four seconds of pairs at 30 Hz.
    let now = Timestamp::now().as_secs_f64() + AHEAD_S;
    let pose = |k: usize| Pose::translation(k as f64, 0.0, 2000.0);
    let backlog: Vec<Message> = (0..120)
        .flat_map(|k| {
            let at = now - 4.0 + (k + 1) as f64 / 30.0;
            [transform(at, "C1", &pose(k)), transform(at, "C2", &pose(k))]
        })
        .collect();
    let mut camera = streaming(streaming_camera(backlog, 0..0, Duration::ZERO), 2000);
    received(&camera, 240);
    let frame = camera.capture().unwrap();
    assert_eq!(
        frame.kind,
        FrameKind::Fitted {
            variance_factor: 1.0
        }
    );
    let frames = CellFrames::from_config(&CellConfig::reference());
    let expected = pose(119) * frames.c1_points_mm[0];
    assert!((frame.points[0].position_mm - expected).norm() < 1e-3);
}
