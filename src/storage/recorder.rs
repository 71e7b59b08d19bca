//! The storage writer: turns the control thread's events into rows while the job runs.
//!
//! Steps are written in batches (a transaction per batch, or every 100 ms, whichever comes
//! first); a job's start and end are written after the steps before them, in the same
//! transaction, so a job never shows more steps than are stored. A failed write is logged and
//! retried with everything after it. The one exception: an event the database refuses outright
//! (it breaks a constraint, as a step with a NaN reward breaks `NOT NULL`) would be refused on
//! every retry and hold back everything after it, so the batch is then written one event at a
//! time and the refused event alone is dropped, logged with its job and step.

use super::demonstrations::{self, NewDemonstration};
use super::{Db, DbError, jobs, steps};
use crate::cell::{CellEvent, StepRecord};
use crate::learning::demos::DemoEpisode;
use crate::policy::inputs::PolicyInputs;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::sync::mpsc::UnboundedReceiver;

/// Runs until the event channel closes, then writes what is left.
/// `cell_hash` names the cell in the demonstrations it records.
pub async fn run(
    db: Db,
    mut events: UnboundedReceiver<CellEvent>,
    batch: usize,
    cell_hash: String,
) {
    let mut pending: VecDeque<CellEvent> = VecDeque::new();
    let mut pending_steps = 0usize;
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            event = events.recv() => {
                let Some(event) = event else { break };
                let urgent = !matches!(event, CellEvent::Step(_));
                pending_steps += usize::from(!urgent);
                pending.push_back(event);
                if urgent || pending_steps >= batch {
                    // Take whatever else is already waiting, so bursts go in one transaction.
                    while let Ok(event) = events.try_recv() {
                        pending_steps += usize::from(matches!(event, CellEvent::Step(_)));
                        pending.push_back(event);
                    }
                    flush(&db, &mut pending, &mut pending_steps, &cell_hash).await;
                }
            }
            _ = tick.tick() => {
                if !pending.is_empty() {
                    flush(&db, &mut pending, &mut pending_steps, &cell_hash).await;
                }
            }
        }
    }
    for attempt in 0..10 {
        if pending.is_empty() {
            return;
        }
        if attempt > 0 {
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        flush(&db, &mut pending, &mut pending_steps, &cell_hash).await;
    }
    tracing::error!(events = pending.len(), "could not store the last events");
}

async fn flush(
    db: &Db,
    pending: &mut VecDeque<CellEvent>,
    pending_steps: &mut usize,
    cell_hash: &str,
) {
    match write(db, pending.iter(), cell_hash).await {
        Ok(()) => {
            pending.clear();
            *pending_steps = 0;
        }
        Err(error) if refused(&error) => {
            while let Some(event) = pending.front() {
                match write(db, [event], cell_hash).await {
                    Ok(()) => {}
                    Err(error) if refused(&error) => {
                        tracing::error!(%error, event = %describe(event), "dropped an event the database refuses");
                    }
                    Err(error) => {
                        tracing::error!(%error, "storing steps failed; will retry");
                        break;
                    }
                }
                pending.pop_front();
            }
            *pending_steps = pending
                .iter()
                .filter(|e| matches!(e, CellEvent::Step(_)))
                .count();
        }
        Err(error) => tracing::error!(%error, "storing steps failed; will retry"),
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
                    // The latch is stored by whoever latched it, before they answer.
                    CellEvent::Latches { .. } => {}
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
        run(db.clone(), inbox, 100, "cell".into()).await;
        assert_eq!(stored(&db, first).await, ("failed".to_string(), vec![1]));
        assert_eq!(
            stored(&db, second).await,
            ("failed".to_string(), vec![1, 2])
        );
    }
}
