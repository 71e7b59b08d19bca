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
