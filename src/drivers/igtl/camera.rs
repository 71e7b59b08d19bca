//! The measuring camera over OpenIGTLink: its messages become [`CameraFrame`]s for camera
//! ingestion, the same fit, fusion and supervisor as the twin's camera.
//!
//! Two kinds of camera are read. One sends a POINT message per capture with the coded points
//! it decoded: each point's group names its fixture (`C1` or `C2`) and its name the point's
//! label in the fixture's layout (`CellFrames::c1_labels`); positions are in the camera frame
//! {W}, mm. The other, a tracker that fits the fixtures itself, sends a TRANSFORM message per
//! fixture (device name `C1` or `C2`, the fixture's frame in {W}, mm) with one timestamp per
//! capture; the frame is then the fixture's coded points at their layout, marked
//! [`FrameKind::Fitted`] so that its residuals, zero by construction, teach nothing of the
//! camera's noise.
//!
//! A streaming camera's messages queue while the cell is idle ([`inbox`], bounded); a capture
//! takes everything queued and keeps the newest frame.
//!
//! Each capture's timestamp orders it: a newer one gets the next sequence number, the same
//! one again (a repeated frame) its own number, an older one a number below the last, so
//! ingestion's watch refuses it as out of order and counts repeats as a frozen camera. A frame
//! older than the staleness limit by this machine's clock is refused here.

use super::codec::{Content, HEADER_BYTES, Header, IgtlError, Message, Timestamp};
use crate::camera::{CameraFrame, CodedPoint, Fixture, FrameKind};
use crate::geometry::{CellFrames, Pose};
use inbox::{Inbox, Waited};
use nalgebra::{Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

pub mod inbox;

/// Why no frame came from the camera.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FrameError {
    #[error("cannot connect to the camera at {address}: {reason}")]
    Connect { address: String, reason: String },
    #[error("no frame from the camera within {waited_ms} ms")]
    Timeout { waited_ms: u64 },
    #[error("the camera connection dropped ({reason})")]
    Dropped { reason: String },
    /// A message header that is not one: the stream cannot be followed past it, so the
    /// connection is closed.
    #[error("the camera sent a garbage header: {0}")]
    BadHeader(IgtlError),
    /// A message whose body is damaged or not its type's; it is skipped.
    #[error("the camera sent a garbage message: {0}")]
    Garbage(#[from] IgtlError),
    #[error("a frame {age_ms:.1} ms old (at most {max_ms} ms accepted)")]
    Stale { age_ms: f64, max_ms: u64 },
    #[error(
        "point `{name}` of group `{group}` names no coded point (group C1 or C2, name an index)"
    )]
    UnknownPoint { group: String, name: String },
    #[error("a TRANSFORM from device `{device}`, not C1 or C2, or not a rigid transform")]
    BadTransform { device: String },
}

impl FrameError {
    /// Whether the connection is gone: the next capture must connect again.
    pub fn ends_connection(&self) -> bool {
        matches!(
            self,
            FrameError::Connect { .. } | FrameError::Dropped { .. } | FrameError::BadHeader(_)
        )
    }

    /// A short stable name for telemetry and hold reasons.
    pub fn code(&self) -> &'static str {
        match self {
            FrameError::Connect { .. } => "camera_unreachable",
            FrameError::Timeout { .. } => "camera_silent",
            FrameError::Dropped { .. } => "camera_dropped",
            FrameError::BadHeader(_) | FrameError::Garbage(_) => "camera_garbage",
            FrameError::Stale { .. } => "camera_stale",
            FrameError::UnknownPoint { .. } | FrameError::BadTransform { .. } => "camera_garbage",
        }
    }
}

/// Turns messages into frames, pure: the sequence numbering by timestamp, the staleness
/// limit, the pairing of a tracker's fixture transforms.
#[derive(Debug, Clone)]
pub struct FrameAssembler {
    c1_points_mm: Vec<Point3<f64>>,
    c2_points_mm: Vec<Point3<f64>>,
    /// The labels a camera names each fixture's points by, in layout order.
    c1_labels: Vec<u16>,
    c2_labels: Vec<u16>,
    /// Oldest frame accepted, ms (by the receiving machine's clock).
    max_age_ms: u64,
    last: Option<(Timestamp, u64)>,
    /// The age of the last frame completed, by the receiving machine's clock, ms.
    last_age_ms: Option<f64>,
    /// A tracker's fixture transform waiting for the other fixture's of the same capture.
    pending: Option<(Timestamp, Fixture, Pose)>,
}

impl FrameAssembler {
    pub fn new(frames: &CellFrames, max_age_ms: u64) -> Self {
        FrameAssembler {
            c1_points_mm: frames.c1_points_mm.clone(),
            c2_points_mm: frames.c2_points_mm.clone(),
            c1_labels: frames.c1_labels.clone(),
            c2_labels: frames.c2_labels.clone(),
            max_age_ms,
            last: None,
            last_age_ms: None,
            pending: None,
        }
    }

    /// The age of the last frame completed when it was (its timestamp to the receiving
    /// machine's clock), ms.
    pub fn last_age_ms(&self) -> Option<f64> {
        self.last_age_ms
    }

    /// A new episode: sequence numbers start again.
    pub fn restart(&mut self) {
        self.last = None;
        self.pending = None;
    }

    /// The frame a message completes, if any (`now`: the receiving machine's clock).
    pub fn take(
        &mut self,
        message: &Message,
        now: Timestamp,
    ) -> Result<Option<CameraFrame>, FrameError> {
        let (points, kind) = match &message.content {
            Content::Point(elements) => {
                let mut points = Vec::with_capacity(elements.len());
                for element in elements {
                    let fixture = fixture_named(&element.group);
                    let label = element.name.trim().parse::<u16>().ok();
                    let (Some(fixture), Some(label)) = (fixture, label) else {
                        return Err(FrameError::UnknownPoint {
                            group: element.group.clone(),
                            name: element.name.clone(),
                        });
                    };
                    points.push(CodedPoint {
                        fixture,
                        id: self.index_of(fixture, label),
                        position_mm: Point3::from(element.position.map(f64::from)),
                    });
                }
                (points, FrameKind::Measured)
            }
            Content::Transform(matrix) => {
                let bad = || FrameError::BadTransform {
                    device: message.device.clone(),
                };
                let fixture = fixture_named(&message.device).ok_or_else(bad)?;
                let pose = rigid(matrix).ok_or_else(bad)?;
                match self.pending.take() {
                    Some((stamp, other, other_pose))
                        if stamp == message.timestamp && other != fixture =>
                    {
                        let (c1, c2) = match fixture {
                            Fixture::C1 => (pose, other_pose),
                            Fixture::C2 => (other_pose, pose),
                        };
                        // The tracker's fit at the data sheet's noise of its points.
                        let kind = FrameKind::Fitted {
                            variance_factor: 1.0,
                        };
                        (self.layout(&c1, &c2), kind)
                    }
                    _ => {
                        self.pending = Some((message.timestamp, fixture, pose));
                        return Ok(None);
                    }
                }
            }
            _ => return Ok(None),
        };
        let age_ms = (now.as_secs_f64() - message.timestamp.as_secs_f64()) * 1000.0;
        self.last_age_ms = Some(age_ms);
        if age_ms > self.max_age_ms as f64 {
            return Err(FrameError::Stale {
                age_ms,
                max_ms: self.max_age_ms,
            });
        }
        let sequence = match self.last {
            None => 1,
            Some((stamp, sequence)) if message.timestamp == stamp => sequence,
            Some((stamp, sequence)) if message.timestamp < stamp => sequence.saturating_sub(1),
            Some((_, sequence)) => sequence + 1,
        };
        if self
            .last
            .is_none_or(|(stamp, _)| message.timestamp >= stamp)
        {
            self.last = Some((message.timestamp, sequence));
        }
        Ok(Some(CameraFrame {
            points,
            sequence,
            kind,
        }))
    }

    /// The index in `fixture`'s layout of the point labelled `label`; a label the layout does
    /// not have gets an index no layout has, and the fit leaves the point out.
    fn index_of(&self, fixture: Fixture, label: u16) -> u16 {
        let labels = match fixture {
            Fixture::C1 => &self.c1_labels,
            Fixture::C2 => &self.c2_labels,
        };
        labels
            .iter()
            .position(|&l| l == label)
            .and_then(|k| u16::try_from(k).ok())
            .unwrap_or(u16::MAX)
    }

    /// The coded points of both fixtures at their nominal layout.
    fn layout(&self, c1: &Pose, c2: &Pose) -> Vec<CodedPoint> {
        let place = |fixture, pose: &Pose, layout: &[Point3<f64>]| {
            layout
                .iter()
                .enumerate()
                .map(|(k, local)| CodedPoint {
                    fixture,
                    id: u16::try_from(k).unwrap_or(u16::MAX),
                    position_mm: pose * local,
                })
                .collect::<Vec<_>>()
        };
        let mut points = place(Fixture::C1, c1, &self.c1_points_mm);
        points.extend(place(Fixture::C2, c2, &self.c2_points_mm));
        points
    }
}

fn fixture_named(name: &str) -> Option<Fixture> {
    match name.trim() {
        "C1" => Some(Fixture::C1),
        "C2" => Some(Fixture::C2),
        _ => None,
    }
}

/// The pose of a TRANSFORM's matrix; `None` unless its rotation part is a rotation (to f32's
/// precision) and every number is finite.
fn rigid(m: &[f32; 12]) -> Option<Pose> {
    let m = m.map(f64::from);
    if m.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let rotation = Matrix3::new(m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]);
    let orthogonality = (rotation.transpose() * rotation - Matrix3::identity()).amax();
    if orthogonality > 1e-4 || rotation.determinant() < 0.0 {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation));
    Some(Pose::from_parts(
        Translation3::from(Vector3::new(m[9], m[10], m[11])),
        rotation,
    ))
}

/// The camera driver's timing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CameraSettings {
    /// Longest wait for the TCP connection, ms.
    pub connect_timeout_ms: u64,
    /// Longest wait for a capture's frame, ms.
    pub frame_timeout_ms: u64,
    /// Oldest frame accepted, ms.
    pub max_age_ms: u64,
    /// Ask for each capture with `GET_POINT` (a camera that captures on request, as
    /// `celld twin-server`'s does); otherwise take the newest frame the camera streams.
    pub triggered: bool,
}

impl Default for CameraSettings {
    fn default() -> Self {
        CameraSettings {
            connect_timeout_ms: 1000,
            frame_timeout_ms: 25,
            max_age_ms: 500,
            triggered: true,
        }
    }
}

/// A camera connection: a reader thread decodes messages into a bounded [`Inbox`];
/// [`IgtlCamera::capture`] turns them into frames on the caller's thread.
pub struct IgtlCamera {
    stream: TcpStream,
    inbox: Arc<Inbox>,
    assembler: FrameAssembler,
    settings: CameraSettings,
    /// A message id for the queries sent.
    queries: u32,
    /// The age of the frame the last capture gave, ms.
    frame_age_ms: Option<f64>,
}

impl IgtlCamera {
    /// Connects to the camera (or the tracker's OpenIGTLink server) at `address`.
    pub fn connect(
        address: &str,
        settings: CameraSettings,
        frames: &CellFrames,
    ) -> Result<IgtlCamera, FrameError> {
        let failed = |reason: String| FrameError::Connect {
            address: address.to_string(),
            reason,
        };
        let stream =
            crate::drivers::connect_tcp(address, settings.connect_timeout_ms).map_err(failed)?;
        let reader = stream.try_clone().map_err(|e| failed(e.to_string()))?;
        let inbox = Arc::new(Inbox::default());
        let filled = inbox.clone();
        std::thread::Builder::new()
            .name("celld-igtl".into())
            .spawn(move || read_messages(reader, &filled))
            .map_err(|e| failed(e.to_string()))?;
        Ok(IgtlCamera {
            stream,
            inbox,
            assembler: FrameAssembler::new(frames, settings.max_age_ms),
            settings,
            queries: 0,
            frame_age_ms: None,
        })
    }

    /// The age of the frame the last capture gave when it was taken in, ms.
    pub fn frame_age_ms(&self) -> Option<f64> {
        self.frame_age_ms
    }

    /// A new episode: the frames' numbering starts again.
    pub fn restart(&mut self) {
        self.assembler.restart();
    }

    /// The next capture: with a triggered camera, asks for it; otherwise the newest frame
    /// streamed since the last call, waiting for one if none came.
    pub fn capture(&mut self) -> Result<CameraFrame, FrameError> {
        if self.settings.triggered {
            self.triggered()
        } else {
            self.newest_streamed()
        }
    }

    /// Asks for a capture with `GET_POINT` and waits for the frame it gives.
    fn triggered(&mut self) -> Result<CameraFrame, FrameError> {
        // Whatever arrived unasked for is not this capture's.
        self.inbox.drain();
        self.queries = self.queries.wrapping_add(1);
        let query = Message {
            version: 2,
            device: "celld".into(),
            timestamp: Timestamp::now(),
            message_id: self.queries,
            content: Content::Query("GET_POINT".into()),
        };
        self.stream
            .write_all(&query.encode())
            .map_err(|e| FrameError::Dropped {
                reason: e.to_string(),
            })?;
        let deadline = self.deadline();
        loop {
            let message = self.next_message(deadline)??;
            if let Some(frame) = self.assembler.take(&message, Timestamp::now())? {
                self.frame_age_ms = self.assembler.last_age_ms();
                return Ok(frame);
            }
        }
    }

    /// The newest frame of a streaming camera: everything queued is taken in, in order, and
    /// the newest complete frame kept; a frame refused (stale, damaged) is passed over when a
    /// newer one is there. With none queued, the first frame to come within the frame timeout;
    /// past it, why the last one was refused, or the timeout.
    fn newest_streamed(&mut self) -> Result<CameraFrame, FrameError> {
        let deadline = self.deadline();
        let mut refused = None;
        let mut newest: Option<CameraFrame> = None;
        let (queued, closed) = self.inbox.drain();
        for message in queued {
            self.offer(message, &mut newest, &mut refused)?;
        }
        if let Some(frame) = newest {
            return Ok(frame);
        }
        if closed {
            return Err(refused.unwrap_or_else(reader_stopped));
        }
        loop {
            match self.next_message(deadline) {
                Ok(message) => self.offer(message, &mut newest, &mut refused)?,
                Err(FrameError::Timeout { waited_ms }) => {
                    return Err(refused.unwrap_or(FrameError::Timeout { waited_ms }));
                }
                Err(error) => return Err(error),
            }
            if let Some(frame) = newest {
                return Ok(frame);
            }
        }
    }

    /// Takes one streamed message in: a frame it completes becomes `newest` unless that is
    /// newer; a message or frame refused is remembered in `refused`; an error that ends the
    /// connection is returned.
    fn offer(
        &mut self,
        message: Result<Message, FrameError>,
        newest: &mut Option<CameraFrame>,
        refused: &mut Option<FrameError>,
    ) -> Result<(), FrameError> {
        let taken = message.and_then(|message| self.assembler.take(&message, Timestamp::now()));
        match taken {
            Ok(Some(frame)) => {
                if newest
                    .as_ref()
                    .is_none_or(|kept| frame.sequence >= kept.sequence)
                {
                    *newest = Some(frame);
                    self.frame_age_ms = self.assembler.last_age_ms();
                }
            }
            Ok(None) => {}
            Err(error) if error.ends_connection() => return Err(error),
            Err(error) => *refused = Some(error),
        }
        Ok(())
    }

    /// The frame timeout from now.
    fn deadline(&self) -> Instant {
        Instant::now() + Duration::from_millis(self.settings.frame_timeout_ms)
    }

    /// The next message the reader decoded, waiting until `deadline`: the outer error is the
    /// wait's (a timeout, the reader stopped), the inner one the message's.
    fn next_message(&self, deadline: Instant) -> Result<Result<Message, FrameError>, FrameError> {
        match self.inbox.wait(deadline) {
            Waited::Message(message) => Ok(message),
            Waited::TimedOut => Err(FrameError::Timeout {
                waited_ms: self.settings.frame_timeout_ms,
            }),
            Waited::Closed => Err(reader_stopped()),
        }
    }
}

fn reader_stopped() -> FrameError {
    FrameError::Dropped {
        reason: "the reader stopped".into(),
    }
}

impl Drop for IgtlCamera {
    fn drop(&mut self) {
        let _ = self.stream.shutdown(std::net::Shutdown::Both);
    }
}

/// Reads one message from `reader` (`body`: a buffer to reuse). A garbage header is an error
/// after which the stream cannot be followed ([`FrameError::BadHeader`]); a body with a bad
/// CRC or content is read whole, so the next message can be ([`FrameError::Garbage`]).
pub fn read_message<R: Read>(reader: &mut R, body: &mut Vec<u8>) -> Result<Message, FrameError> {
    let dropped = |e: std::io::Error| FrameError::Dropped {
        reason: e.to_string(),
    };
    let mut header = [0u8; HEADER_BYTES];
    reader.read_exact(&mut header).map_err(dropped)?;
    let parsed = Header::decode(&header).map_err(FrameError::BadHeader)?;
    body.resize(parsed.body_size as usize, 0);
    reader.read_exact(body).map_err(dropped)?;
    Ok(Message::decode(&parsed, body)?)
}

/// Reads messages into `inbox` until the connection ends or a header is garbage; a body with
/// a bad CRC or content is reported and skipped.
fn read_messages(mut stream: TcpStream, inbox: &Inbox) {
    let mut body = Vec::new();
    loop {
        let message = read_message(&mut stream, &mut body);
        let fatal = message.as_ref().is_err_and(FrameError::ends_connection);
        inbox.push(message);
        if fatal {
            let _ = stream.shutdown(std::net::Shutdown::Both);
            inbox.close();
            return;
        }
    }
}

#[cfg(test)]
mod tests;
