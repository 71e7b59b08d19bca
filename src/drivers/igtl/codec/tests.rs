use super::*;

/// pyigtl's `PointMessage(positions=[[1.5, -2.25, 1000], [0, 3, -4.5]], names=["3", "7"],
/// groups=["C1", "C2"], timestamp=1700000000.5, device_name="camera").pack()`.
const PYIGTL_POINT_V1: &str = "0001504f494e540000000000000063616d65726100000000000000000000000000006553f100800000000000000000000110bbaab9b64b89aff6330000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000004331000000000000000000000000000000000000000000000000000000000000ffff00ff3fc00000c0100000447a0000000000000000000000000000000000000000000000000000370000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000004332000000000000000000000000000000000000000000000000000000000000ffff00ff0000000040400000c0900000000000000000000000000000000000000000000000000000";

/// pyigtl's `TransformMessage(matrix=[[1,0,0,10],[0,0,-1,20],[0,1,0,-30.5],[0,0,0,1]],
/// timestamp=1700000001.25, device_name="C2")` with `header_version = 2`, `message_id = 42`.
const PYIGTL_TRANSFORM_V2: &str = "00025452414e53464f524d00000043320000000000000000000000000000000000006553f10140000000000000000000003ee028c4f4c93462bb000c0002000000000000002a3f800000000000000000000000000000000000003f80000000000000bf800000000000004120000041a00000c1f400000000";

fn hex(text: &str) -> Vec<u8> {
    (0..text.len())
        .step_by(2)
        .map(|k| u8::from_str_radix(&text[k..k + 2], 16).unwrap())
        .collect()
}

fn decode(bytes: &[u8]) -> Result<Message, IgtlError> {
    let header = Header::decode(bytes[..HEADER_BYTES].try_into().unwrap())?;
    assert_eq!(header.body_size as usize, bytes.len() - HEADER_BYTES);
    Message::decode(&header, &bytes[HEADER_BYTES..])
}

#[test]
fn the_crc_is_ecma_182s() {
    assert_eq!(crc64(b"123456789"), 0x6c40_df5f_0b49_7347);
}

#[test]
fn a_point_message_reads_and_writes_as_pyigtl_does() {
    let bytes = hex(PYIGTL_POINT_V1);
    let message = decode(&bytes).unwrap();
    assert_eq!(message.version, 1);
    assert_eq!(message.device, "camera");
    assert_eq!(message.timestamp.as_secs_f64(), 1_700_000_000.5);
    let Content::Point(points) = &message.content else {
        panic!("{message:?}")
    };
    assert_eq!(points.len(), 2);
    assert_eq!(points[0].name, "3");
    assert_eq!(points[0].group, "C1");
    assert_eq!(points[0].position, [1.5, -2.25, 1000.0]);
    assert_eq!(points[1].group, "C2");
    assert_eq!(points[1].position, [0.0, 3.0, -4.5]);
    assert_eq!(message.encode(), bytes);
}

#[test]
fn a_version_2_transform_reads_and_writes_as_pyigtl_does() {
    let bytes = hex(PYIGTL_TRANSFORM_V2);
    let message = decode(&bytes).unwrap();
    assert_eq!(message.version, 2);
    assert_eq!(message.message_id, 42);
    assert_eq!(message.device, "C2");
    assert_eq!(message.timestamp.as_secs_f64(), 1_700_000_001.25);
    assert_eq!(
        message.content,
        Content::Transform([
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0, 10.0, 20.0, -30.5
        ])
    );
    assert_eq!(message.encode(), bytes);
}

#[test]
fn damaged_messages_are_refused_with_their_numbers() {
    let mut bytes = hex(PYIGTL_POINT_V1);
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    assert!(matches!(decode(&bytes), Err(IgtlError::Crc { .. })));

    let mut header: [u8; HEADER_BYTES] = hex(PYIGTL_POINT_V1)[..HEADER_BYTES].try_into().unwrap();
    header[1] = 9;
    assert_eq!(
        Header::decode(&header),
        Err(IgtlError::Version { version: 9 })
    );
    header[1] = 1;
    header[42..50].copy_from_slice(&u64::MAX.to_be_bytes());
    assert_eq!(
        Header::decode(&header),
        Err(IgtlError::BodyTooLarge {
            size: u64::MAX,
            max: MAX_BODY_BYTES
        })
    );

    let short = Message {
        version: 1,
        device: "C1".into(),
        timestamp: Timestamp::default(),
        message_id: 0,
        content: Content::Other {
            kind: "TRANSFORM".into(),
            bytes: 0,
        },
    };
    let mut bytes = short.encode();
    bytes.extend_from_slice(&[0; 8]);
    bytes[42..50].copy_from_slice(&8u64.to_be_bytes());
    let crc = crc64(&[0; 8]);
    bytes[50..58].copy_from_slice(&crc.to_be_bytes());
    assert_eq!(
        decode(&bytes),
        Err(IgtlError::Content {
            kind: "TRANSFORM".into(),
            size: 8
        })
    );
}

#[test]
fn status_and_queries_round_trip() {
    for content in [
        Content::Status(Status {
            code: 1,
            subcode: -3,
            error_name: "OK".into(),
            message: "camera ready".into(),
        }),
        Content::Query("GET_POINT".into()),
    ] {
        for version in [1, 2] {
            let message = Message {
                version,
                device: "camera".into(),
                timestamp: Timestamp::from_secs_f64(12.75),
                message_id: 7 * u32::from(version - 1),
                content: content.clone(),
            };
            assert_eq!(decode(&message.encode()), Ok(message));
        }
    }
}
