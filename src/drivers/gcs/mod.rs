//! PI's GCS 2.0 command set, the language of Physik Instrumente hexapod controllers: the pure
//! protocol ([`protocol`]: commands, answers, the platform pose as X Y Z U V W), the controller
//! error codes ([`errors`]), a TCP client ([`client`]) and the [`Robot`](crate::robot::Robot)
//! it drives ([`robot`]).

pub mod client;
pub mod errors;
pub mod protocol;
pub mod robot;
pub mod twin;

pub use client::{GcsClient, GcsSettings};
pub use errors::GcsError;
pub use robot::GcsRobot;
