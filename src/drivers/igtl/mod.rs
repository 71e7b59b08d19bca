//! OpenIGTLink, the open protocol of tracked and imaging devices (TCP, port 18944): the
//! message codec ([`codec`]: header versions 1 and 2, CRC-64, POINT, TRANSFORM, STATUS and
//! the GET_ queries; pure) and the camera driver that turns messages into camera frames
//! ([`camera`]).

pub mod camera;
pub mod codec;

pub use codec::{Content, IgtlError, Message, Timestamp};
