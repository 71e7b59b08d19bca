//! The storage writer: turns the control thread's events into rows while the job runs.
//!
//! Steps are written in batches (a transaction per batch, or every 100 ms, whichever comes
//! first); a job's start and end are written after the steps before them, in the same
//! transaction, so a job never shows more steps than are stored. A failed write is logged and
//! retried with everything after it. The one exception: an event the database refuses outright
//! (it breaks a constraint, as a step with a NaN reward breaks `NOT NULL`) would be refused on
//! every retry and hold back everything after it, so the batch is then written one event at a
//! time and the refused event alone is dropped, logged with its job and step.
//!
//! When the storage fails (a full disk) the events wait in memory and are retried every tick,
//! in order, until they commit. A running job is not let run unrecorded: the first failed
//! write that holds its start or steps sends its id to `storage_failed`, and the control
//! thread holds the robot and ends it `storage_failed` (that end is stored, after the steps
//! before it, once the disk takes writes again). While a fault stands and nothing waits, the
//! writer probes every half second ([`health::probe`]) so the fault clears by itself.

use super::demonstrations::{self, NewDemonstration};
use super::{Db, DbError, health, jobs, machine, steps};
use crate::cell::{CellEvent, StepRecord};
use crate::learning::demos::DemoEpisode;
use crate::policy::inputs::PolicyInputs;
use std::collections::{BTreeSet, VecDeque};
use std::time::Duration;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender};

/// Ticks (of 100 ms) between probes while a fault stands and nothing waits.
const PROBE_TICKS: u32 = 5;

/// Runs until the event channel closes, then writes what is left.
/// `cell_hash` names the cell in the demonstrations it records; `storage_failed` takes the id
/// of each running job whose events could not be stored.
pub async fn run(
    db: Db,
    mut events: UnboundedReceiver<CellEvent>,
    batch: usize,
    cell_hash: String,
    storage_failed: UnboundedSender<i64>,
) {
    let mut writer = Writer {
        db,
        pending: VecDeque::new(),
        pending_steps: 0,
        cell_hash,
        storage_failed,
        told: BTreeSet::new(),
    };
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut idle_ticks = 0u32;
    loop {
        tokio::select! {
            event = events.recv() => {
                let Some(event) = event else { break };
                let urgent = !matches!(event, CellEvent::Step(_));
                writer.push(event);
                if urgent || writer.pending_steps >= batch {
                    // Take whatever else is already waiting, so bursts go in one transaction.
                    while let Ok(event) = events.try_recv() {
                        writer.push(event);
                    }
                    writer.flush().await;
                }
            }
            _ = tick.tick() => {
                if !writer.pending.is_empty() {
                    writer.flush().await;
                } else if writer.db.health.fault().is_some() {
                    idle_ticks += 1;
                    if idle_ticks >= PROBE_TICKS {
                        idle_ticks = 0;
                        let _ = health::probe(&writer.db).await;
                    }
                }
            }
        }
    }
    for attempt in 0..10 {
        if writer.pending.is_empty() {
            return;
        }
        if attempt > 0 {
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        writer.flush().await;
    }
    tracing::error!(
        events = writer.pending.len(),
        "could not store the last events"
    );
}

struct Writer {
    db: Db,
    pending: VecDeque<CellEvent>,
    pending_steps: usize,
    cell_hash: String,
    storage_failed: UnboundedSender<i64>,
    /// Jobs reported to `storage_failed` since the last write that stored everything.
    told: BTreeSet<i64>,
}

impl Writer {
    fn push(&mut self, event: CellEvent) {
        self.pending_steps += usize::from(matches!(event, CellEvent::Step(_)));
        self.pending.push_back(event);
    }

    async fn flush(&mut self) {
        // Latches alone write nothing here: an empty commit would say nothing of the disk.
        if self
            .pending
            .iter()
            .all(|e| matches!(e, CellEvent::Latches { .. }))
        {
            self.pending.clear();
            return;
        }
        let db = &self.db;
        let cell_hash = self.cell_hash.as_str();
        let pending = &mut self.pending;
        match db.track(write(db, pending.iter(), cell_hash).await) {
            Ok(()) => {
                pending.clear();
                self.pending_steps = 0;
                self.told.clear();
                return;
            }
            Err(error) if refused(&error) => {
                let mut failed = None;
                while let Some(event) = pending.front() {
                    match db.track(write(db, [event], cell_hash).await) {
                        Ok(()) => {}
                        Err(error) if refused(&error) => {
                            tracing::error!(%error, event = %describe(event), "dropped an event the database refuses");
                        }
                        Err(error) => {
                            failed = Some(error);
                            break;
                        }
                    }
                    pending.pop_front();
                }
                self.pending_steps = pending
                    .iter()
                    .filter(|e| matches!(e, CellEvent::Step(_)))
                    .count();
                if failed.is_none() {
                    return;
                }
            }
            // Logged once when writes begin to fail (`WriteHealth`); retried every tick.
            Err(_) => {}
        }
        self.hold_unrecorded_jobs();
    }

    /// Reports each job that started or stepped in the waiting events and has not ended there:
    /// it runs while its record cannot be kept.
    fn hold_unrecorded_jobs(&mut self) {
        let mut running = BTreeSet::new();
        for event in &self.pending {
            match event {
                CellEvent::JobStarted { job_id } => {
                    running.insert(*job_id);
                }
                CellEvent::Step(record) => {
                    running.insert(record.job_id);
                }
                CellEvent::JobEnded { job_id, .. } => {
                    running.remove(job_id);
                }
                CellEvent::Latches { .. } | CellEvent::Machine(_) => {}
            }
        }
        for job_id in running {
            if self.told.insert(job_id) {
                tracing::error!(
                    job_id,
                    "the job's steps cannot be stored: holding the robot"
                );
                let _ = self.storage_failed.send(job_id);
            }
        }
    }
}

/// Whether the database refused the rows themselves (a constraint), so that retrying the same
/// rows can never succeed; other errors (a busy or full disk) may pass on a retry.
fn refused(error: &DbError) -> bool {
    use sqlx::error::ErrorKind;
    matches!(error, sqlx::Error::Database(e) if matches!(
        e.kind(),
        ErrorKind::UniqueViolation
            | ErrorKind::ForeignKeyViolation
            | ErrorKind::NotNullViolation
            | ErrorKind::CheckViolation
    ))
}

fn describe(event: &CellEvent) -> String {
    match event {
        CellEvent::Step(record) => format!("step {} of job {}", record.step, record.job_id),
        CellEvent::JobStarted { job_id } => format!("start of job {job_id}"),
        CellEvent::JobEnded { job_id, .. } => format!("end of job {job_id}"),
        CellEvent::Latches {
            estop_latched,
            driver_latch,
        } => format!(
            "e-stop latched = {estop_latched}, driver latched = {}",
            driver_latch.is_some()
        ),
        CellEvent::Machine(update) => format!("machine state {}", update.machine.state.name()),
    }
}

async fn write(
    db: &Db,
    events: impl IntoIterator<Item = &CellEvent>,
    cell_hash: &str,
) -> Result<(), DbError> {
    let mut tx = db.writer.begin().await?;
    let mut run: Vec<StepRecord> = Vec::new();
    for event in events {
        match event {
            CellEvent::Step(record) => {
                run.push(StepRecord::clone(record));
                if run.len() == steps::ROWS_PER_STATEMENT {
                    steps::insert_rows(&mut *tx, &run).await?;
                    run.clear();
                }
            }
            other => {
                steps::insert_rows(&mut *tx, &run).await?;
                run.clear();
                match other {
                    CellEvent::JobStarted { job_id } => {
                        jobs::mark_started(&mut *tx, *job_id).await?
                    }
                    CellEvent::JobEnded { job_id, end } => {
                        jobs::mark_ended(&mut *tx, *job_id, end).await?;
                        if let Some(steps) = &end.demonstration {
                            let episode = DemoEpisode {
                                steps: steps.clone(),
                                succeeded: true,
                            };
                            let new = NewDemonstration {
                                name: &format!("job {job_id}"),
                                source: "recorded",
                                cell_hash,
                                job_id: Some(*job_id),
                                inputs: PolicyInputs::Absolute.name(),
                                created_by: "celld",
                            };
                            demonstrations::insert(&mut *tx, &new, &[episode]).await?;
                        }
                    }
                    // The latch is stored by whoever latched it, before they answer
                    // (`workflows::cell`, which also retries an e-stop's failed write).
                    CellEvent::Latches { .. } => {}
                    CellEvent::Machine(update) => machine::record(&mut tx, update).await?,
                    CellEvent::Step(_) => unreachable!(),
                }
            }
        }
    }
    steps::insert_rows(&mut *tx, &run).await?;
    tx.commit().await
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::{JobEnd, JobStatus};
    use crate::sim::reward::RewardTerms;
    use crate::storage::jobs::NewJob;

    fn step(job_id: i64, step: u32, reward: f64) -> CellEvent {
        CellEvent::Step(Box::new(StepRecord {
            job_id,
            step,
            t_s: 0.1 * f64::from(step),
            state: [0.0; 12],
            action: [0.0; 6],
            proposed: None,
            rules: Default::default(),
            actor: None,
            scale: None,
            legs_mm: [0.0; 6],
            verdict: "allowed",
            veto_reason: None,
            reward: RewardTerms {
                total: reward,
                ..RewardTerms::default()
            },
            compute_us: 1.0,
            uncertainty: Default::default(),
            detected: None,
        }))
    }

    fn ended(job_id: i64, reason: &str) -> CellEvent {
        CellEvent::JobEnded {
            job_id,
            end: JobEnd::unstarted(JobStatus::Failed, reason),
        }
    }

    async fn stored(db: &Db, job_id: i64) -> (String, Vec<i64>) {
        let status = sqlx::query_scalar("SELECT status FROM jobs WHERE id = ?")
            .bind(job_id)
            .fetch_one(&db.reader)
            .await
            .unwrap();
        let steps = sqlx::query_scalar("SELECT step FROM steps WHERE job_id = ? ORDER BY step")
            .bind(job_id)
            .fetch_all(&db.reader)
            .await
            .unwrap();
        (status, steps)
    }

    /// A step with a NaN reward breaks `NOT NULL` (SQLite stores NaN as NULL). Before, every
    /// retry of its batch failed and nothing after it was ever stored.
    #[tokio::test]
    async fn an_event_the_database_refuses_is_dropped_alone() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("celld.db")).await.unwrap();
        let job = NewJob {
            controller: "expert".into(),
            policy_id: None,
            seed: 1,
            initial_pos_mm: 1.0,
            initial_ori_deg: 1.0,
            demonstration: false,
            created_by: "test".into(),
        };
        let first = jobs::insert(&db, &job).await.unwrap().id;
        let second = jobs::insert(&db, &job).await.unwrap().id;
        let (events, inbox) = tokio::sync::mpsc::unbounded_channel();
        for event in [
            CellEvent::JobStarted { job_id: first },
            step(first, 1, -1.0),
            step(first, 2, f64::NAN),
            ended(first, "nan_state"),
            CellEvent::JobStarted { job_id: second },
            step(second, 1, -1.0),
            step(second, 2, -2.0),
            ended(second, "contact"),
        ] {
            events.send(event).unwrap();
        }
        drop(events);
        let (failed, _) = tokio::sync::mpsc::unbounded_channel();
        run(db.clone(), inbox, 100, "cell".into(), failed).await;
        assert_eq!(stored(&db, first).await, ("failed".to_string(), vec![1]));
        assert_eq!(
            stored(&db, second).await,
            ("failed".to_string(), vec![1, 2])
        );
    }
}
