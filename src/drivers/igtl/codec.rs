//! OpenIGTLink messages as bytes, pure. Every number is big-endian.
//!
//! A message is a 58-byte header (version `u16`, type `char[12]`, device name `char[20]`,
//! timestamp u64, body size u64, CRC-64 of the body u64) and its body. In header version 2
//! the body starts with a 12-byte extended header (its own size u16, metadata header size
//! u16, metadata size u32, message id u32) and ends with the metadata. The CRC is ECMA-182's
//! CRC-64 (polynomial 0x42F0E1EBA9EA3693, no reflection, zero initial value and final XOR).
//! The timestamp is seconds (u32) and a binary fraction of a second (u32).

use crc::{CRC_64_ECMA_182, Crc};

/// Bytes in a message header.
pub const HEADER_BYTES: usize = 58;
/// Bytes in header version 2's extended header.
pub const EXTENDED_HEADER_BYTES: usize = 12;
/// Bytes of one POINT element: `name[64]`, `group[32]`, RGBA, x y z, diameter (f32),
/// `owner[20]`.
pub const POINT_ELEMENT_BYTES: usize = 136;
/// Bytes of a TRANSFORM body: a 3×4 matrix of f32, column by column.
pub const TRANSFORM_BYTES: usize = 48;
/// The largest body accepted (a garbage header would otherwise ask for gigabytes), bytes.
pub const MAX_BODY_BYTES: u64 = 1 << 20;

const CRC64: Crc<u64> = Crc::<u64>::new(&CRC_64_ECMA_182);

/// The CRC-64 OpenIGTLink puts in the header, of `bytes`.
pub fn crc64(bytes: &[u8]) -> u64 {
    CRC64.checksum(bytes)
}

/// A message's time of generation: seconds since 1970 and a binary fraction of a second.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default)]
pub struct Timestamp {
    pub seconds: u32,
    /// The fraction of a second, in units of 2⁻³² s.
    pub fraction: u32,
}

impl Timestamp {
    /// The timestamp of `seconds` since 1970 (s, non-negative).
    pub fn from_secs_f64(seconds: f64) -> Timestamp {
        let whole = seconds.floor();
        let fraction = ((seconds - whole) * 4_294_967_296.0).floor();
        Timestamp {
            seconds: whole as u32,
            fraction: fraction.min(u32::MAX as f64) as u32,
        }
    }

    /// Now, by the system clock.
    pub fn now() -> Timestamp {
        let since = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        Timestamp::from_secs_f64(since.as_secs_f64())
    }

    /// Seconds since 1970.
    pub fn as_secs_f64(&self) -> f64 {
        f64::from(self.seconds) + f64::from(self.fraction) / 4_294_967_296.0
    }

    fn to_u64(self) -> u64 {
        (u64::from(self.seconds) << 32) | u64::from(self.fraction)
    }

    fn from_u64(value: u64) -> Timestamp {
        Timestamp {
            seconds: (value >> 32) as u32,
            fraction: value as u32,
        }
    }
}

/// One point of a POINT message.
#[derive(Debug, Clone, PartialEq)]
pub struct PointElement {
    pub name: String,
    pub group: String,
    pub rgba: [u8; 4],
    /// Position, mm.
    pub position: [f32; 3],
    /// Diameter, mm.
    pub diameter: f32,
    pub owner: String,
}

/// A STATUS message's body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Status {
    /// 1: OK; other values name a fault (OpenIGTLink's status codes).
    pub code: u16,
    pub subcode: i64,
    pub error_name: String,
    pub message: String,
}

/// What a message carries.
#[derive(Debug, Clone, PartialEq)]
pub enum Content {
    Point(Vec<PointElement>),
    /// A rigid transform: the rotation's columns then the translation (mm), as the matrix
    /// `[[m0 m3 m6 m9] [m1 m4 m7 m10] [m2 m5 m8 m11]]`.
    Transform([f32; 12]),
    Status(Status),
    /// A query with no body: `GET_POINT`, `GET_TRANS`, `GET_STATUS`, …; the type name.
    Query(String),
    /// A type this codec does not read: its name and body size (bytes).
    Other {
        kind: String,
        bytes: usize,
    },
}

impl Content {
    /// The type name in the header.
    pub fn kind(&self) -> &str {
        match self {
            Content::Point(_) => "POINT",
            Content::Transform(_) => "TRANSFORM",
            Content::Status(_) => "STATUS",
            Content::Query(kind) | Content::Other { kind, .. } => kind,
        }
    }
}

/// A whole message.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// The header version: 1 (OpenIGTLink 1 and 2) or 2 (OpenIGTLink 3, extended header).
    pub version: u16,
    pub device: String,
    pub timestamp: Timestamp,
    /// The extended header's message id (version 2; 0 in version 1).
    pub message_id: u32,
    pub content: Content,
}

/// A message header, read before its body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    pub version: u16,
    pub kind: String,
    pub device: String,
    pub timestamp: Timestamp,
    /// Bytes of the body.
    pub body_size: u64,
    pub crc: u64,
}

/// Why bytes are not a message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IgtlError {
    #[error("header version {version} (1 and 2 are known)")]
    Version { version: u16 },
    #[error("a body of {size} bytes (at most {max} accepted)")]
    BodyTooLarge { size: u64, max: u64 },
    #[error("CRC mismatch: the header says {header:#018x}, the body gives {body:#018x}")]
    Crc { header: u64, body: u64 },
    #[error("{kind}: {size} bytes of content do not make a message of that type")]
    Content { kind: String, size: usize },
    #[error("the extended header is {size} bytes (at least 12) or overruns the body")]
    ExtendedHeader { size: usize },
    #[error("a field that is not text: {field}")]
    Text { field: &'static str },
}

impl Message {
    /// The message as bytes: header, then body, CRC included.
    pub fn encode(&self) -> Vec<u8> {
        let content = encode_content(&self.content);
        let mut body = Vec::with_capacity(content.len() + EXTENDED_HEADER_BYTES + 2);
        if self.version >= 2 {
            body.extend_from_slice(&(EXTENDED_HEADER_BYTES as u16).to_be_bytes());
            // No metadata: the metadata header is its count alone.
            body.extend_from_slice(&2u16.to_be_bytes());
            body.extend_from_slice(&0u32.to_be_bytes());
            body.extend_from_slice(&self.message_id.to_be_bytes());
            body.extend_from_slice(&content);
            body.extend_from_slice(&0u16.to_be_bytes());
        } else {
            body = content;
        }
        let mut bytes = Vec::with_capacity(HEADER_BYTES + body.len());
        bytes.extend_from_slice(&self.version.to_be_bytes());
        put_text(&mut bytes, self.content.kind(), 12);
        put_text(&mut bytes, &self.device, 20);
        bytes.extend_from_slice(&self.timestamp.to_u64().to_be_bytes());
        bytes.extend_from_slice(&(body.len() as u64).to_be_bytes());
        bytes.extend_from_slice(&crc64(&body).to_be_bytes());
        bytes.extend_from_slice(&body);
        bytes
    }

    /// The message of a header and its body; checks the CRC.
    pub fn decode(header: &Header, body: &[u8]) -> Result<Message, IgtlError> {
        let computed = crc64(body);
        if computed != header.crc {
            return Err(IgtlError::Crc {
                header: header.crc,
                body: computed,
            });
        }
        let (content, message_id) = if header.version >= 2 {
            split_extended(body)?
        } else {
            (body, 0)
        };
        Ok(Message {
            version: header.version,
            device: header.device.clone(),
            timestamp: header.timestamp,
            message_id,
            content: decode_content(&header.kind, content)?,
        })
    }
}

impl Header {
    /// Reads a header; refuses unknown versions and oversized bodies before any body is read.
    pub fn decode(bytes: &[u8; HEADER_BYTES]) -> Result<Header, IgtlError> {
        let version = u16::from_be_bytes([bytes[0], bytes[1]]);
        if !(1..=2).contains(&version) {
            return Err(IgtlError::Version { version });
        }
        let body_size = be_u64(&bytes[42..50]);
        if body_size > MAX_BODY_BYTES {
            return Err(IgtlError::BodyTooLarge {
                size: body_size,
                max: MAX_BODY_BYTES,
            });
        }
        Ok(Header {
            version,
            kind: text(&bytes[2..14], "type")?,
            device: text(&bytes[14..34], "device name")?,
            timestamp: Timestamp::from_u64(be_u64(&bytes[34..42])),
            body_size,
            crc: be_u64(&bytes[50..58]),
        })
    }
}

/// The content and message id of a version 2 body (its metadata left out).
fn split_extended(body: &[u8]) -> Result<(&[u8], u32), IgtlError> {
    let bad = |size| IgtlError::ExtendedHeader { size };
    if body.len() < EXTENDED_HEADER_BYTES {
        return Err(bad(body.len()));
    }
    let size = usize::from(u16::from_be_bytes([body[0], body[1]]));
    let metadata_header = usize::from(u16::from_be_bytes([body[2], body[3]]));
    let metadata = be_u32(&body[4..8]) as usize;
    let message_id = be_u32(&body[8..12]);
    let end = body
        .len()
        .checked_sub(metadata_header + metadata)
        .ok_or(bad(size))?;
    if size < EXTENDED_HEADER_BYTES || size > end {
        return Err(bad(size));
    }
    Ok((&body[size..end], message_id))
}

fn encode_content(content: &Content) -> Vec<u8> {
    let mut out = Vec::new();
    match content {
        Content::Point(points) => {
            for point in points {
                put_text(&mut out, &point.name, 64);
                put_text(&mut out, &point.group, 32);
                out.extend_from_slice(&point.rgba);
                for value in point.position {
                    out.extend_from_slice(&value.to_be_bytes());
                }
                out.extend_from_slice(&point.diameter.to_be_bytes());
                put_text(&mut out, &point.owner, 20);
            }
        }
        Content::Transform(matrix) => {
            for value in matrix {
                out.extend_from_slice(&value.to_be_bytes());
            }
        }
        Content::Status(status) => {
            out.extend_from_slice(&status.code.to_be_bytes());
            out.extend_from_slice(&status.subcode.to_be_bytes());
            put_text(&mut out, &status.error_name, 20);
            out.extend_from_slice(status.message.as_bytes());
            out.push(0);
        }
        Content::Query(_) | Content::Other { .. } => {}
    }
    out
}

fn decode_content(kind: &str, bytes: &[u8]) -> Result<Content, IgtlError> {
    let wrong = || IgtlError::Content {
        kind: kind.to_string(),
        size: bytes.len(),
    };
    Ok(match kind {
        "POINT" => {
            if !bytes.len().is_multiple_of(POINT_ELEMENT_BYTES) {
                return Err(wrong());
            }
            let mut points = Vec::with_capacity(bytes.len() / POINT_ELEMENT_BYTES);
            for element in bytes.chunks_exact(POINT_ELEMENT_BYTES) {
                points.push(PointElement {
                    name: text(&element[0..64], "point name")?,
                    group: text(&element[64..96], "point group")?,
                    rgba: [element[96], element[97], element[98], element[99]],
                    position: [
                        be_f32(&element[100..104]),
                        be_f32(&element[104..108]),
                        be_f32(&element[108..112]),
                    ],
                    diameter: be_f32(&element[112..116]),
                    owner: text(&element[116..136], "point owner")?,
                });
            }
            Content::Point(points)
        }
        "TRANSFORM" => {
            if bytes.len() != TRANSFORM_BYTES {
                return Err(wrong());
            }
            Content::Transform(std::array::from_fn(|k| be_f32(&bytes[4 * k..4 * k + 4])))
        }
        "STATUS" => {
            if bytes.len() < 31 || bytes.last() != Some(&0) {
                return Err(wrong());
            }
            Content::Status(Status {
                code: u16::from_be_bytes([bytes[0], bytes[1]]),
                subcode: i64::from_be_bytes(bytes[2..10].try_into().expect("8 bytes")),
                error_name: text(&bytes[10..30], "status error name")?,
                message: text(&bytes[30..], "status message")?,
            })
        }
        query if query.starts_with("GET_") => Content::Query(query.to_string()),
        other => Content::Other {
            kind: other.to_string(),
            bytes: bytes.len(),
        },
    })
}

/// `value` in a field of `width` bytes, zero padded (cut at the width).
fn put_text(out: &mut Vec<u8>, value: &str, width: usize) {
    let bytes = value.as_bytes();
    let used = bytes.len().min(width);
    out.extend_from_slice(&bytes[..used]);
    out.resize(out.len() + (width - used), 0);
}

/// A zero-padded text field.
fn text(bytes: &[u8], field: &'static str) -> Result<String, IgtlError> {
    let end = bytes.iter().position(|b| *b == 0).unwrap_or(bytes.len());
    std::str::from_utf8(&bytes[..end])
        .map(|s| s.trim_end().to_string())
        .map_err(|_| IgtlError::Text { field })
}

fn be_u64(bytes: &[u8]) -> u64 {
    u64::from_be_bytes(bytes.try_into().expect("8 bytes"))
}

fn be_u32(bytes: &[u8]) -> u32 {
    u32::from_be_bytes(bytes.try_into().expect("4 bytes"))
}

fn be_f32(bytes: &[u8]) -> f32 {
    f32::from_be_bytes(bytes.try_into().expect("4 bytes"))
}

#[cfg(test)]
mod tests;
