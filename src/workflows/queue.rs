//! The one queue of background work: policy evaluations and training runs wait here, in the
//! order they were asked for, behind a limit on how many compute at once (`work.concurrency`).
//! Their compute runs on a pool of that many threads at nice 10, made once at start, so a burst
//! of requests can neither start hundreds of threads nor take the cores that a running job, the
//! e-stop and the HTTP workers need. Past `work.queue_length` waiting, a request is refused
//! ([`QueueError::Full`], 429) rather than queued. At shutdown [`WorkQueue::close`] empties the
//! queue and asks every running piece of work to stop.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tokio::sync::Notify;

/// What a piece of background work is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum WorkKind {
    Evaluation,
    Training,
}

/// A piece of work by its stored record: an evaluation's or a training run's id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct WorkId {
    pub kind: WorkKind,
    pub id: i64,
}

impl WorkId {
    pub fn evaluation(id: i64) -> Self {
        WorkId {
            kind: WorkKind::Evaluation,
            id,
        }
    }

    pub fn training(id: i64) -> Self {
        WorkId {
            kind: WorkKind::Training,
            id,
        }
    }
}

/// Why the queue took no more work.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QueueError {
    #[error(
        "the work queue is full: {waiting} waiting (work.queue_length = {queue_length}) behind \
         {running} running (work.concurrency = {concurrency}); try again in about \
         {retry_after_s} s"
    )]
    Full {
        waiting: usize,
        queue_length: usize,
        running: usize,
        concurrency: usize,
        /// A hint: the mean run so far less what the oldest running one has done, ≥ 1 s.
        retry_after_s: u64,
    },
    #[error("the service is stopping: it takes no new background work")]
    Closed,
}

/// Why a wait for a turn ended without one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoTurn {
    /// Taken out of the queue ([`WorkQueue::cancel`]).
    Removed,
    /// The service is stopping ([`WorkQueue::close`]).
    Closed,
}

/// What [`WorkQueue::cancel`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cancelled {
    /// It was waiting and is out of the queue.
    Dequeued,
    /// It is running and was asked to stop at its next check.
    Stopping,
    /// The queue does not hold it (it ended, or never was).
    NotHere,
}

/// Before any run has ended, the retry hint, s.
const FIRST_RETRY_AFTER_S: f64 = 30.0;

struct Entry {
    seq: u64,
    /// Known once its record is stored.
    work: Option<WorkId>,
    cancel: Arc<AtomicBool>,
    /// When it took its place in the queue, then when it started.
    since: Instant,
}

#[derive(Default)]
struct State {
    running: Vec<Entry>,
    waiting: VecDeque<Entry>,
    closed: bool,
    next_seq: u64,
    /// Mean duration of the runs ended so far, s (exponentially weighted).
    mean_run_s: Option<f64>,
}

impl State {
    fn entry(&self, seq: u64) -> Option<&Entry> {
        self.running
            .iter()
            .chain(self.waiting.iter())
            .find(|e| e.seq == seq)
    }

    fn retry_after_s(&self, now: Instant) -> u64 {
        let oldest = self
            .running
            .iter()
            .map(|e| now.duration_since(e.since).as_secs_f64())
            .fold(0.0, f64::max);
        let left = self.mean_run_s.map_or(FIRST_RETRY_AFTER_S, |m| m - oldest);
        left.ceil().clamp(1.0, 3600.0) as u64
    }
}

struct Shared {
    state: Mutex<State>,
    changed: Notify,
    /// See [`WorkQueue::admissions`].
    admissions: tokio::sync::Mutex<()>,
    concurrency: usize,
    queue_length: usize,
    pool: rayon::ThreadPool,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().expect("work queue lock")
    }

    /// Frees `seq`'s place, wherever it is, and starts the next ones in order.
    fn release(&self, seq: u64) {
        let mut state = self.lock();
        let now = Instant::now();
        if let Some(at) = state.running.iter().position(|e| e.seq == seq) {
            let ended = state.running.swap_remove(at);
            let took = now.duration_since(ended.since).as_secs_f64();
            state.mean_run_s = Some(state.mean_run_s.map_or(took, |m| 0.7 * m + 0.3 * took));
        } else {
            state.waiting.retain(|e| e.seq != seq);
        }
        while !state.closed && state.running.len() < self.concurrency {
            let Some(mut next) = state.waiting.pop_front() else {
                break;
            };
            next.since = now;
            state.running.push(next);
        }
        drop(state);
        self.changed.notify_waiters();
    }
}

/// The queue, cheap to clone (one per service, in the `Context`).
#[derive(Clone)]
pub struct WorkQueue {
    shared: Arc<Shared>,
}

impl WorkQueue {
    /// A queue running at most `concurrency` (≥ 1) pieces of work at once, with up to
    /// `queue_length` waiting; starts its `concurrency` compute threads.
    pub fn new(concurrency: usize, queue_length: usize) -> std::io::Result<Self> {
        let concurrency = concurrency.max(1);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(concurrency)
            .thread_name(|i| format!("celld-work-{i}"))
            .start_handler(|_| crate::cell::task::lower_priority())
            .build()
            .map_err(std::io::Error::other)?;
        Ok(WorkQueue {
            shared: Arc::new(Shared {
                state: Mutex::default(),
                changed: Notify::new(),
                admissions: tokio::sync::Mutex::new(()),
                concurrency,
                queue_length,
                pool,
            }),
        })
    }

    /// Takes a place: a running one when one is free and nobody waits, else the last in the
    /// queue; refused when `queue_length` already wait or the service is stopping. The place is
    /// held until the [`Ticket`] is dropped.
    pub fn reserve(&self) -> Result<Ticket, QueueError> {
        let mut state = self.shared.lock();
        if state.closed {
            return Err(QueueError::Closed);
        }
        let entry = Entry {
            seq: state.next_seq,
            work: None,
            cancel: Arc::default(),
            since: Instant::now(),
        };
        let (seq, cancel) = (entry.seq, entry.cancel.clone());
        if state.running.len() < self.shared.concurrency && state.waiting.is_empty() {
            state.running.push(entry);
        } else if state.waiting.len() < self.shared.queue_length {
            state.waiting.push_back(entry);
        } else {
            return Err(QueueError::Full {
                waiting: state.waiting.len(),
                queue_length: self.shared.queue_length,
                running: state.running.len(),
                concurrency: self.shared.concurrency,
                retry_after_s: state.retry_after_s(Instant::now()),
            });
        }
        state.next_seq += 1;
        Ok(Ticket {
            shared: self.shared.clone(),
            seq,
            cancel,
        })
    }

    /// Held while a piece of work is admitted (its place taken and its record stored) and while
    /// one ends (its end stored and its place freed): whoever reads that a piece has ended then
    /// finds its place free, and no more than `concurrency` records read `running` at once.
    pub async fn admissions(&self) -> tokio::sync::MutexGuard<'_, ()> {
        self.shared.admissions.lock().await
    }

    /// `work`'s place in the queue (1 = next to start), while it waits.
    pub fn position(&self, work: WorkId) -> Option<usize> {
        let state = self.shared.lock();
        state
            .waiting
            .iter()
            .position(|e| e.work == Some(work))
            .map(|at| at + 1)
    }

    /// The places of every waiting piece of `kind`, by id.
    pub fn positions(&self, kind: WorkKind) -> HashMap<i64, usize> {
        let state = self.shared.lock();
        state
            .waiting
            .iter()
            .enumerate()
            .filter_map(|(at, e)| e.work.filter(|w| w.kind == kind).map(|w| (w.id, at + 1)))
            .collect()
    }

    /// How many run and how many wait now.
    pub fn counts(&self) -> (usize, usize) {
        let state = self.shared.lock();
        (state.running.len(), state.waiting.len())
    }

    /// Takes `work` out of the queue if it waits, or asks it to stop if it runs.
    pub fn cancel(&self, work: WorkId) -> Cancelled {
        let mut state = self.shared.lock();
        if let Some(at) = state.waiting.iter().position(|e| e.work == Some(work)) {
            state.waiting.remove(at);
            drop(state);
            self.shared.changed.notify_waiters();
            return Cancelled::Dequeued;
        }
        match state.running.iter().find(|e| e.work == Some(work)) {
            Some(entry) => {
                entry.cancel.store(true, Ordering::SeqCst);
                Cancelled::Stopping
            }
            None => Cancelled::NotHere,
        }
    }

    /// At shutdown: takes no more work, empties the queue and asks every running piece to stop.
    /// Returns what was running and what was waiting.
    pub fn close(&self) -> (Vec<WorkId>, Vec<WorkId>) {
        let mut state = self.shared.lock();
        state.closed = true;
        for entry in state.running.iter().chain(state.waiting.iter()) {
            entry.cancel.store(true, Ordering::SeqCst);
        }
        let running = state.running.iter().filter_map(|e| e.work).collect();
        let waiting = state.waiting.drain(..).filter_map(|e| e.work).collect();
        drop(state);
        self.shared.changed.notify_waiters();
        (running, waiting)
    }

    pub fn is_closed(&self) -> bool {
        self.shared.lock().closed
    }

    /// Runs `work` on one of the queue's compute threads (nice 10) and answers its result, or
    /// what a panic in it said. Rayon work inside it stays on those threads. Call it while
    /// holding a running [`Ticket`], so no more than `work.concurrency` compute at once.
    pub async fn compute<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T, String> {
        let (reply, answer) = tokio::sync::oneshot::channel();
        self.shared.pool.spawn(move || {
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work))
                .map_err(|panic| format!("the work thread panicked: {}", panic_text(&*panic)));
            let _ = reply.send(result);
        });
        answer
            .await
            .map_err(|_| "the work thread stopped".to_string())?
    }
}

/// A place in the [`WorkQueue`], held while its work waits and runs; dropping it frees the
/// place and starts the next in line.
pub struct Ticket {
    shared: Arc<Shared>,
    seq: u64,
    cancel: Arc<AtomicBool>,
}

impl Ticket {
    /// Names the work once its record is stored, so its place can be looked up.
    pub fn assign(&self, work: WorkId) {
        let mut guard = self.shared.lock();
        let state = &mut *guard;
        if let Some(entry) = state
            .running
            .iter_mut()
            .chain(state.waiting.iter_mut())
            .find(|e| e.seq == self.seq)
        {
            entry.work = Some(work);
        }
    }

    /// Whether it holds a running place now (else it waits).
    pub fn is_running(&self) -> bool {
        let state = self.shared.lock();
        state.running.iter().any(|e| e.seq == self.seq)
    }

    /// Set when the work is to stop: cancelled while running, or the service stopping.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        self.cancel.clone()
    }

    /// Waits until the work may start, or says why it never will.
    pub async fn turn(&self) -> Result<(), NoTurn> {
        loop {
            let notified = self.shared.changed.notified();
            tokio::pin!(notified);
            // Registered before the state is read, so a change in between is not missed.
            notified.as_mut().enable();
            {
                let state = self.shared.lock();
                if state.closed {
                    return Err(NoTurn::Closed);
                }
                if state.running.iter().any(|e| e.seq == self.seq) {
                    return Ok(());
                }
                if state.entry(self.seq).is_none() {
                    return Err(NoTurn::Removed);
                }
            }
            notified.await;
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.shared.release(self.seq);
    }
}

/// A panic's message (a `&str` or a `String` payload; anything else is unnamed).
fn panic_text(panic: &(dyn std::any::Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[tokio::test]
    async fn work_runs_in_order_behind_the_limit_and_a_full_queue_refuses() {
        let queue = WorkQueue::new(2, 3).unwrap();
        let tickets: Vec<Ticket> = (0..5).map(|_| queue.reserve().unwrap()).collect();
        for (i, ticket) in tickets.iter().enumerate() {
            ticket.assign(WorkId::evaluation(10 + i as i64));
        }
        assert_eq!(queue.counts(), (2, 3));
        let positions: Vec<Option<usize>> = (10..15)
            .map(|id| queue.position(WorkId::evaluation(id)))
            .collect();
        assert_eq!(positions, [None, None, Some(1), Some(2), Some(3)]);
        assert_eq!(
            queue.positions(WorkKind::Evaluation),
            HashMap::from([(12, 1), (13, 2), (14, 3)])
        );
        assert!(queue.positions(WorkKind::Training).is_empty());
        match queue.reserve() {
            Err(QueueError::Full {
                waiting: 3,
                queue_length: 3,
                running: 2,
                concurrency: 2,
                retry_after_s,
            }) => assert!(retry_after_s >= 1),
            Err(other) => panic!("{other}"),
            Ok(_) => panic!("a sixth place past a queue of 3 behind 2"),
        }

        // The first to end lets the first waiting one start; the others move up.
        let mut tickets = tickets.into_iter();
        let first = tickets.next().unwrap();
        let rest: Vec<Ticket> = tickets.collect();
        assert!(!rest[1].is_running());
        drop(first);
        assert!(rest[1].is_running());
        assert_eq!(rest[1].turn().await, Ok(()));
        assert_eq!(queue.position(WorkId::evaluation(13)), Some(1));
        assert_eq!(queue.counts(), (2, 2));
    }

    #[tokio::test]
    async fn a_waiting_turn_comes_when_a_place_frees() {
        let queue = WorkQueue::new(1, 4).unwrap();
        let running = queue.reserve().unwrap();
        let waiting = queue.reserve().unwrap();
        let waited =
            tokio::spawn(async move { waiting.turn().await.map(|()| waiting.is_running()) });
        tokio::task::yield_now().await;
        assert!(!waited.is_finished());
        drop(running);
        assert_eq!(waited.await.unwrap(), Ok(true));
        assert_eq!(queue.counts(), (0, 0), "both tickets dropped");
    }

    #[tokio::test]
    async fn cancelling_takes_a_waiting_one_out_and_flags_a_running_one() {
        let queue = WorkQueue::new(1, 4).unwrap();
        let (running, waiting) = (queue.reserve().unwrap(), queue.reserve().unwrap());
        running.assign(WorkId::training(1));
        waiting.assign(WorkId::training(2));
        assert_eq!(queue.cancel(WorkId::training(2)), Cancelled::Dequeued);
        assert_eq!(waiting.turn().await, Err(NoTurn::Removed));
        assert_eq!(queue.counts(), (1, 0));
        assert_eq!(queue.cancel(WorkId::training(1)), Cancelled::Stopping);
        assert!(running.cancel_flag().load(Ordering::SeqCst));
        assert_eq!(queue.cancel(WorkId::training(3)), Cancelled::NotHere);
        drop(waiting);
        assert_eq!(
            queue.counts(),
            (1, 0),
            "a removed ticket frees nothing twice"
        );
    }

    #[tokio::test]
    async fn closing_refuses_new_work_empties_the_queue_and_flags_the_running() {
        let queue = WorkQueue::new(1, 4).unwrap();
        let (running, waiting) = (queue.reserve().unwrap(), queue.reserve().unwrap());
        running.assign(WorkId::evaluation(1));
        waiting.assign(WorkId::training(2));
        let (was_running, was_waiting) = queue.close();
        assert_eq!(was_running, [WorkId::evaluation(1)]);
        assert_eq!(was_waiting, [WorkId::training(2)]);
        assert!(running.cancel_flag().load(Ordering::SeqCst));
        assert_eq!(waiting.turn().await, Err(NoTurn::Closed));
        assert!(matches!(queue.reserve(), Err(QueueError::Closed)));
        drop(running);
        assert_eq!(queue.counts(), (0, 0), "nothing starts once closed");
    }

    #[tokio::test]
    async fn compute_stays_on_one_low_priority_thread_per_place() {
        let queue = WorkQueue::new(1, 0).unwrap();
        let (threads, names) = queue
            .compute(|| {
                let seen: std::collections::HashSet<String> = (0..64)
                    .into_par_iter()
                    .map(|_| format!("{:?}", std::thread::current().id()))
                    .collect();
                (seen.len(), std::thread::current().name().map(String::from))
            })
            .await
            .unwrap();
        assert_eq!(threads, 1, "a pool of one thread runs every piece of it");
        assert_eq!(names.as_deref(), Some("celld-work-0"));
        #[cfg(target_os = "linux")]
        {
            // SAFETY: getpriority reads its integer arguments only; 0 is the calling thread.
            let nice = queue
                .compute(|| unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) })
                .await
                .unwrap();
            assert!(nice >= 10, "nice {nice}");
        }
    }

    #[tokio::test]
    async fn a_panic_on_a_work_thread_is_reported_with_its_message() {
        let queue = WorkQueue::new(1, 0).unwrap();
        let answer = queue
            .compute(|| -> u8 { panic!("the loss is {}", f64::NAN) })
            .await;
        assert_eq!(
            answer,
            Err("the work thread panicked: the loss is NaN".to_string())
        );
        let answer = queue
            .compute(|| -> u8 { std::panic::panic_any(7_u8) })
            .await;
        assert_eq!(
            answer,
            Err("the work thread panicked: (no message)".to_string())
        );
        assert_eq!(queue.compute(|| 3_u8).await, Ok(3));
    }
}
