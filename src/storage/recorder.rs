//! The storage writer: turns the control thread's events into rows while the job runs.
//!
//! Steps are written in batches (a transaction per batch, or every 100 ms, whichever comes
//! first); a job's start and end are written after the steps before them, in the same
//! transaction, so a job never shows more steps than are stored. A failed write is logged and
//! retried with everything after it; nothing is dropped.

use super::demonstrations::{self, NewDemonstration};
use super::{Db, DbError, jobs, steps};
use crate::cell::{CellEvent, StepRecord};
use crate::learning::demos::DemoEpisode;
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
    match write(db, pending, cell_hash).await {
        Ok(()) => {
            pending.clear();
            *pending_steps = 0;
        }
        Err(error) => tracing::error!(%error, "storing steps failed; will retry"),
    }
}

async fn write(db: &Db, events: &VecDeque<CellEvent>, cell_hash: &str) -> Result<(), DbError> {
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
                                created_by: "celld",
                            };
                            demonstrations::insert(&mut *tx, &new, &[episode]).await?;
                        }
                    }
                    // The latch is stored by whoever latched it, before they answer.
                    CellEvent::EStop { .. } => {}
                    CellEvent::Step(_) => unreachable!(),
                }
            }
        }
    }
    steps::insert_rows(&mut *tx, &run).await?;
    tx.commit().await
}
