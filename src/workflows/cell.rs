//! The e-stop and its latch: motion stops first, then the latch is stored so that it survives
//! a restart, with the press audited in the same transaction.
//!
//! The latch in memory follows what was stored, with one exception, for safety: an e-stop
//! holds the robot and latches at once, and only then stores; if that write fails it answers
//! [`Error::StorageUnavailable`] saying so, the cell stays latched, and the write is retried
//! until the disk takes it. A reset stores the cleared latch first
//! and clears it in memory only once that committed: a reset whose write fails leaves the cell
//! latched and answers [`Error::StorageUnavailable`].

use super::{Context, Error, Result};
use crate::cell::packml::{Command, PackMlState};
use crate::cell::{CellCommand, CellHandle};
use crate::storage::{self, DbError, audit};
use serde_json::{Value, json};
use tokio::sync::mpsc::UnboundedReceiver;

/// Latches the e-stop: motion stops at once, the running job fails with `estop`, queued jobs
/// are cancelled; answers once the running job's end is stored. Stays latched (across
/// restarts too) until [`reset`].
pub async fn estop(context: &Context, by: &str) -> Result<()> {
    let running = context.cell.status().current_job;
    context.cell.stop_now();
    context
        .cell
        .ask(|reply| CellCommand::EStop {
            by: by.to_string(),
            reply,
        })
        .await?;
    let detail = json!({"job": running});
    if let Err(e) = store_latch(context, by, "cell.estop", detail.clone()).await {
        tokio::spawn(keep_storing_latch(context.clone(), by.to_string(), detail));
        return Err(Error::StorageUnavailable(format!(
            "the robot holds and the e-stop is latched, but the latch could not be stored \
             ({e}): it is stored once the database takes writes again, and until then a \
             restart would not know it"
        )));
    }
    if let Some(id) = running {
        super::jobs::wait_until_final(context, id).await?;
    }
    Ok(())
}

/// Clears the e-stop latch and the driver's, and brings the machine state from Aborted or
/// Stopped to Idle (PackML's Clear, then Reset). Starts nothing: the next motion is the next
/// job an operator creates.
pub async fn reset(context: &Context, by: &str) -> Result<()> {
    clear(context, by, true).await
}

/// PackML's Clear: clears the e-stop latch and the driver's (Aborted → Clearing → Stopped),
/// and with `and_reset` goes on to Idle. Hardware that is not ready again (unreachable, not
/// referenced, moved) keeps both latches: [`Error::Unavailable`] with the reason. The cleared
/// latch is stored before it is cleared in memory: if that write fails the cell stays latched
/// ([`Error::StorageUnavailable`]); an e-stop pressed meanwhile wins (the cell stays latched).
pub async fn clear(context: &Context, by: &str, and_reset: bool) -> Result<()> {
    let _one_writer = context.latch_writes.lock().await;
    let presses = context
        .cell
        .ask(|reply| CellCommand::ResetHardware { reply })
        .await?;
    let presses = match presses {
        Ok(presses) => presses,
        Err(reason) => {
            audit::record(&context.db, by, "cell.reset", json!({"refused": reason})).await?;
            return Err(Error::unavailable(format!(
                "the cell stays latched: the hardware is not ready ({reason})"
            )));
        }
    };
    let action = if and_reset {
        "cell.reset"
    } else {
        "cell.clear"
    };
    write_latch(context, false, by, action, json!({"refused": null}))
        .await
        .map_err(|e| {
            Error::StorageUnavailable(format!(
                "the cell stays latched: the reset could not be stored ({e})"
            ))
        })?;
    let cleared = context
        .cell
        .ask(|reply| CellCommand::ClearEStop {
            presses,
            and_reset,
            by: by.to_string(),
            reply,
        })
        .await?;
    if !cleared {
        // Pressed while the reset was stored: that later press wins, as it would had it come
        // just after; its own write (waiting for this one) stores the latch.
        tracing::info!("an e-stop came during the reset: the cell stays latched");
    }
    Ok(())
}

/// A PackML command (stop, hold, unhold, clear, reset), audited. A state that does not take
/// it refuses it ([`Error::Conflict`], naming the states that do).
pub async fn command(context: &Context, by: &str, command: Command) -> Result<()> {
    if command == Command::Clear {
        let state = context.cell.status().machine.state;
        if state != PackMlState::Aborted {
            return Err(Error::conflict(format!(
                "the cell is {}: clear is taken in Aborted",
                state.name()
            )));
        }
        return clear(context, by, false).await;
    }
    context
        .cell
        .ask(|reply| CellCommand::Machine {
            command,
            by: by.to_string(),
            reply,
        })
        .await?
        .map_err(|not_now| Error::conflict(not_now.to_string()))?;
    let action = format!("cell.{}", command.name());
    if let Err(e) = audit::record(&context.db, by, &action, json!({})).await {
        // Done, not recorded: say both, as the e-stop does.
        return Err(Error::StorageUnavailable(format!(
            "the cell took the {} (it is {} now), but its audit entry could not be stored ({e})",
            command.name(),
            context.cell.status().machine.state.name()
        )));
    }
    Ok(())
}

/// Stores the control thread's latch as it is now, with an audit entry, in one transaction.
/// The control thread is asked first, so a stop never waits on storage; the writes are
/// serialised and each stores the latest state, so an e-stop and a reset racing each other
/// cannot leave the stored latch behind the control thread's (which a restart would then
/// believe).
pub async fn store_latch(
    context: &Context,
    by: &str,
    action: &str,
    detail: Value,
) -> std::result::Result<(), DbError> {
    let _one_writer = context.latch_writes.lock().await;
    let latched = context.cell.status().estop_latched;
    write_latch(context, latched, by, action, detail).await
}

/// Retries an e-stop's failed [`store_latch`] every quarter second until it commits (or the
/// service stops). Each try stores the latch as it is then, so a reset meanwhile is not undone.
async fn keep_storing_latch(context: Context, by: String, detail: Value) {
    while !context.shutting_down() {
        tokio::time::sleep(std::time::Duration::from_millis(250)).await;
        if store_latch(&context, &by, "cell.estop", detail.clone())
            .await
            .is_ok()
        {
            return;
        }
    }
}

/// Writes the latch and its audit entry in one transaction (the caller holds `latch_writes`).
async fn write_latch(
    context: &Context,
    latched: bool,
    by: &str,
    action: &str,
    detail: Value,
) -> std::result::Result<(), DbError> {
    let db = &context.db;
    let done = async {
        let mut tx = db.writer.begin().await?;
        storage::set_cell_flag(&mut *tx, "estop", latched).await?;
        audit::record_with(&mut *tx, by, action, &detail).await?;
        tx.commit().await
    }
    .await;
    db.track(done)
}

/// Ends each job the storage writer reports it cannot record (`storage_failed`): the control
/// thread holds the robot at once. Runs until the writer stops.
pub async fn fail_unrecorded_jobs(cell: CellHandle, mut jobs: UnboundedReceiver<i64>) {
    while let Some(job_id) = jobs.recv().await {
        if cell.send(CellCommand::StorageFailed { job_id }).is_err() {
            return;
        }
    }
}
