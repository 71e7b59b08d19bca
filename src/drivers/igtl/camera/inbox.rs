//! The messages the reader thread decoded, waiting for a capture: at most [`INBOX_MESSAGES`],
//! the oldest let go first, so a streaming camera left running while the cell is idle fills
//! no more memory than that, and what is kept is always the newest.

use super::FrameError;
use crate::drivers::igtl::codec::Message;
use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, PoisonError};
use std::time::Instant;

/// Messages kept: a second of a 100 Hz tracker's two TRANSFORMs a capture, and more.
pub const INBOX_MESSAGES: usize = 256;

/// One decoded message, or why none could be.
pub type Received = Result<Message, FrameError>;

/// What [`Inbox::wait`] found.
#[derive(Debug)]
pub enum Waited {
    Message(Received),
    TimedOut,
    /// The reader has stopped and everything it sent was taken.
    Closed,
}

#[derive(Debug, Default)]
struct Queue {
    messages: VecDeque<Received>,
    closed: bool,
    /// Messages pushed since the connection opened, those let go included.
    received: u64,
}

/// A bounded queue shared by the reader thread (which pushes) and the capture (which takes).
#[derive(Debug, Default)]
pub struct Inbox {
    queue: Mutex<Queue>,
    arrived: Condvar,
}

impl Inbox {
    fn queue(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Adds a message, letting the oldest go when full.
    pub fn push(&self, message: Received) {
        let mut queue = self.queue();
        if queue.messages.len() == INBOX_MESSAGES {
            queue.messages.pop_front();
        }
        queue.messages.push_back(message);
        queue.received += 1;
        drop(queue);
        self.arrived.notify_all();
    }

    /// The reader has stopped: no more messages will come.
    pub fn close(&self) {
        self.queue().closed = true;
        self.arrived.notify_all();
    }

    /// Messages pushed since the connection opened, those let go included.
    pub fn received(&self) -> u64 {
        self.queue().received
    }

    /// Messages queued now (at most [`INBOX_MESSAGES`]).
    pub fn len(&self) -> usize {
        self.queue().messages.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Everything queued now, oldest first, and whether the reader has stopped.
    pub fn drain(&self) -> (Vec<Received>, bool) {
        let mut queue = self.queue();
        (queue.messages.drain(..).collect(), queue.closed)
    }

    /// The oldest message queued, waiting for one until `deadline`.
    pub fn wait(&self, deadline: Instant) -> Waited {
        let mut queue = self.queue();
        loop {
            if let Some(message) = queue.messages.pop_front() {
                return Waited::Message(message);
            }
            if queue.closed {
                return Waited::Closed;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Waited::TimedOut;
            }
            queue = self
                .arrived
                .wait_timeout(queue, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }
}
