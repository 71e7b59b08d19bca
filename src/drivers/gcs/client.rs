//! A GCS controller over TCP: one command at a time, each answer read to its end within a
//! timeout, every error the controller reports read back with `ERR?`.

use super::errors::GcsError;
use super::protocol::answer_complete;
use crate::drivers::{DriverObserver, Unobserved};
use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The driver's timing, all in milliseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GcsSettings {
    /// Longest wait for the TCP connection, ms.
    pub connect_timeout_ms: u64,
    /// Longest wait for the whole answer to a query, ms.
    pub answer_timeout_ms: u64,
    /// Longest wait for every axis to report on target beyond the move's allowed time (see
    /// `move_time_factor`); then the driver stops the platform, ms.
    pub on_target_deadline_ms: u64,
    /// A move is allowed this many times its time at the platform's speeds (the straight
    /// path at constant speed; a real hexapod also ramps up and down).
    pub move_time_factor: f64,
    /// Pause between two `ONT?` polls, ms (0: poll back to back).
    pub poll_interval_ms: u64,
    /// The platform's velocity set with `VLS` at connection and reset, mm/s (none: the
    /// controller's own).
    pub velocity_mm_s: Option<f64>,
    /// Largest difference, per axis, between where the controller says the platform is and
    /// where the cell last put it before the driver latches (`position_mismatch`): mm for X Y Z.
    pub position_tolerance_mm: f64,
    /// The same for U V W, deg.
    pub orientation_tolerance_deg: f64,
}

impl Default for GcsSettings {
    fn default() -> Self {
        GcsSettings {
            connect_timeout_ms: 1000,
            answer_timeout_ms: 100,
            on_target_deadline_ms: 20,
            move_time_factor: 1.5,
            poll_interval_ms: 0,
            velocity_mm_s: None,
            position_tolerance_mm: 0.005,
            orientation_tolerance_deg: 0.005,
        }
    }
}

/// A connection to one controller.
pub struct GcsClient {
    address: String,
    stream: TcpStream,
    buffer: Vec<u8>,
    settings: GcsSettings,
    observer: Arc<dyn DriverObserver>,
}

/// A second handle on a client's connection that writes `STP` at once, from any thread, even
/// while the client waits for an answer.
pub struct Stopper {
    stream: TcpStream,
}

impl Stopper {
    /// Writes `STP` (stop all axes) on the wire.
    pub fn stop(&self) -> std::io::Result<()> {
        (&self.stream).write_all(b"STP\n")
    }
}

impl GcsClient {
    /// Connects to the controller at `address` (`host:port`).
    pub fn connect(address: &str, settings: GcsSettings) -> Result<GcsClient, GcsError> {
        let failed = |reason: String| GcsError::Connect {
            address: address.to_string(),
            reason,
        };
        let stream =
            crate::drivers::connect_tcp(address, settings.connect_timeout_ms).map_err(failed)?;
        // A controller that stops reading must not hold the control thread in a write.
        stream
            .set_write_timeout(Some(Duration::from_millis(
                settings.answer_timeout_ms.max(1),
            )))
            .map_err(|e| failed(e.to_string()))?;
        Ok(GcsClient {
            address: address.to_string(),
            stream,
            buffer: Vec::with_capacity(256),
            settings,
            observer: Arc::new(Unobserved),
        })
    }

    /// Reports each query's round trip to `observer`.
    pub fn observe_with(&mut self, observer: Arc<dyn DriverObserver>) {
        self.observer = observer;
    }

    pub fn address(&self) -> &str {
        &self.address
    }

    pub fn settings(&self) -> &GcsSettings {
        &self.settings
    }

    /// A handle that can stop the platform from another thread.
    pub fn stopper(&self) -> Result<Stopper, GcsError> {
        self.stream
            .try_clone()
            .map(|stream| Stopper { stream })
            .map_err(|e| dropped("STP", &e))
    }

    /// Gives the connection up: writes `STP` on it, so that a command sent before and not yet
    /// carried out (a controller that stalled, a relay that holds bytes) is stopped by the
    /// controller in the order it reads them, then closes it. Best effort: the connection
    /// may be gone already.
    pub fn give_up(mut self) {
        let _ = self.send("STP");
    }

    /// A connection the controller closed or reset while nothing was asked, seen without
    /// sending anything (a peek that does not wait); none while it is open.
    pub fn closed_by_peer(&self) -> Option<GcsError> {
        use std::os::fd::AsRawFd;
        let mut byte = [0u8; 1];
        // SAFETY: a one-byte buffer we own, on the stream's open descriptor.
        let read = unsafe {
            libc::recv(
                self.stream.as_raw_fd(),
                byte.as_mut_ptr().cast(),
                1,
                libc::MSG_PEEK | libc::MSG_DONTWAIT,
            )
        };
        match read {
            0 => Some(GcsError::Dropped {
                command: "(between commands)".into(),
                reason: "closed by the controller".into(),
            }),
            n if n > 0 => None,
            _ => {
                let error = std::io::Error::last_os_error();
                match error.kind() {
                    ErrorKind::WouldBlock | ErrorKind::Interrupted => None,
                    _ => Some(dropped("(between commands)", &error)),
                }
            }
        }
    }

    /// Writes one command line (LF added when missing); reads nothing.
    pub fn send(&mut self, command: &str) -> Result<(), GcsError> {
        let result = if command.ends_with('\n') {
            self.stream.write_all(command.as_bytes())
        } else {
            self.stream.write_all(format!("{command}\n").as_bytes())
        };
        result.map_err(|e| dropped(command, &e))
    }

    /// Sends a command and checks `ERR?` after it: `Err(Controller)` with the code it reports.
    pub fn command(&mut self, command: &str) -> Result<(), GcsError> {
        self.send(command)?;
        match self.error_code()? {
            0 => Ok(()),
            code => Err(GcsError::controller(code, command)),
        }
    }

    /// `ERR?`: the controller's last error code, which reading clears.
    pub fn error_code(&mut self) -> Result<i32, GcsError> {
        let answer = self.query("ERR?")?;
        answer.trim().parse().map_err(|_| GcsError::Answer {
            command: "ERR?".into(),
            problem: super::protocol::AnswerError::NotANumber {
                text: answer.trim().into(),
            },
            answer,
        })
    }

    /// Sends a query and reads its whole answer within the answer timeout.
    pub fn query(&mut self, command: &str) -> Result<String, GcsError> {
        let sent = Instant::now();
        self.send(command)?;
        let answer = self.read_answer(command)?;
        self.observer
            .controller_round_trip(sent.elapsed().as_secs_f64());
        Ok(answer)
    }

    fn read_answer(&mut self, command: &str) -> Result<String, GcsError> {
        let timeout_ms = self.settings.answer_timeout_ms;
        let deadline = Instant::now() + Duration::from_millis(timeout_ms);
        self.buffer.clear();
        let mut chunk = [0u8; 512];
        while !answer_complete(&self.buffer) {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(GcsError::Timeout {
                    command: command.trim().into(),
                    timeout_ms,
                });
            }
            self.stream
                .set_read_timeout(Some(left))
                .map_err(|e| dropped(command, &e))?;
            match self.stream.read(&mut chunk) {
                Ok(0) => {
                    return Err(GcsError::Dropped {
                        command: command.trim().into(),
                        reason: "closed by the controller".into(),
                    });
                }
                Ok(n) => self.buffer.extend_from_slice(&chunk[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(dropped(command, &e)),
            }
        }
        Ok(String::from_utf8_lossy(&self.buffer).into_owned())
    }
}

fn dropped(command: &str, error: &std::io::Error) -> GcsError {
    GcsError::Dropped {
        command: command.trim().into(),
        reason: error.to_string(),
    }
}
