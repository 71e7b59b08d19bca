//! Demonstrations imported from JSON Lines (a job with `"demonstration": true` records its own
//! when it succeeds, through the storage writer).

use super::{Context, Error, Result, off_the_runtime};
use crate::learning::demos::{self, DemoError};
use crate::policy::inputs::PolicyInputs;
use crate::storage::audit;
use crate::storage::demonstrations::{self, Demonstration, NewDemonstration};
use serde_json::json;

/// Reads JSON Lines (all of it, or nothing is stored), stores the episodes under `name`.
pub async fn import(
    context: &Context,
    name: &str,
    body: Vec<u8>,
    by: &str,
) -> Result<Demonstration> {
    if name.is_empty() || name.chars().count() > 100 {
        return Err(Error::bad_request("name must be 1 to 100 characters"));
    }
    // Imported steps are the paper's state on this cell: each number within what it can hold.
    let bounds = demos::DemoBounds::for_cell(&context.cell_config);
    let episodes = off_the_runtime(move || {
        demos::read_jsonl(&body[..])
            .and_then(|episodes| demos::check_bounds(&episodes, &bounds).map(|()| episodes))
            .map_err(|e| match e {
                DemoError::Io(_) => Error::bad_request(format!("nothing imported: {e}")),
                _ => Error::unprocessable(format!("nothing imported: {e}")),
            })
    })
    .await?;
    if episodes.is_empty() {
        return Err(Error::unprocessable(
            "nothing imported: the body has no steps",
        ));
    }
    let id = demonstrations::insert(
        &context.db.writer,
        &NewDemonstration {
            name,
            source: "imported",
            cell_hash: &context.cell_config.config_hash(),
            job_id: None,
            inputs: PolicyInputs::Absolute.name(),
            created_by: by,
        },
        &episodes,
    )
    .await?;
    audit::record(
        &context.db,
        by,
        "demonstration.import",
        json!({"demonstration_id": id, "name": name}),
    )
    .await?;
    let stored = demonstrations::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no demonstration with id {id}")))?;
    Ok(stored)
}

/// Deletes a stored demonstration, audited.
pub async fn delete(context: &Context, id: i64, by: &str) -> Result<()> {
    if !demonstrations::delete(&context.db, id).await? {
        return Err(Error::not_found(format!("no demonstration with id {id}")));
    }
    audit::record(
        &context.db,
        by,
        "demonstration.delete",
        json!({"demonstration_id": id}),
    )
    .await?;
    Ok(())
}
