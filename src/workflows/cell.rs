//! The e-stop and its latch: motion stops first, then the latch is stored so that it survives
//! a restart, then the press is audited.

use super::{Context, Error, Result};
use crate::cell::CellCommand;
use crate::storage::{self, audit};
use serde_json::json;

/// Latches the e-stop: motion stops at once, the running job fails with `estop`, queued jobs
/// are cancelled; answers once the running job's end is stored. Stays latched (across
/// restarts too) until [`reset`].
pub async fn estop(context: &Context, by: &str) -> Result<()> {
    let running = context.cell.status().current_job;
    context.cell.stop_now();
    context
        .cell
        .ask(|reply| CellCommand::EStop { reply })
        .await?;
    store_latch(context).await.map_err(|e| {
        Error::Storage(format!(
            "motion is stopped and the e-stop latched, but the latch could not be stored and \
             would not survive a restart: {e}"
        ))
    })?;
    audit::record(&context.db, by, "cell.estop", json!({"job": running})).await?;
    if let Some(id) = running {
        super::jobs::wait_until_final(context, id).await?;
    }
    Ok(())
}

/// Clears the e-stop latch and the driver's. Starts nothing: the next motion is the next job
/// an operator creates. Hardware that is not ready again (unreachable, not referenced, moved)
/// keeps both latches: [`Error::Unavailable`] with the reason.
pub async fn reset(context: &Context, by: &str) -> Result<()> {
    let result = context
        .cell
        .ask(|reply| CellCommand::Reset { reply })
        .await?;
    audit::record(
        &context.db,
        by,
        "cell.reset",
        json!({"refused": result.as_ref().err()}),
    )
    .await?;
    result.map_err(|reason| {
        Error::unavailable(format!(
            "the cell stays latched: the hardware is not ready ({reason})"
        ))
    })?;
    store_latch(context).await?;
    Ok(())
}

/// Stores the control thread's latch as it is now. The control thread is asked first, so a
/// stop never waits on storage; the writes are serialised and each stores the latest state,
/// so an e-stop and a reset racing each other cannot leave the stored latch behind the
/// control thread's (which a restart would then believe).
pub async fn store_latch(context: &Context) -> Result<()> {
    let _one_writer = context.latch_writes.lock().await;
    let latched = context.cell.status().estop_latched;
    storage::set_cell_flag(&context.db.writer, "estop", latched).await?;
    Ok(())
}
