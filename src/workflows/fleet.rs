//! A cell in a fleet: the background task that replicates its record, tells the fleet how it
//! is, pulls the registry's policies, answers activation requests, and keeps the fleet's
//! tokens at hand. It never holds up the control loop or a request: everything it does waits
//! on the network in its own task, and an outage only lengthens the outbox.

use super::{Context, Error, Result};
use crate::fleet::registry::{self, FleetToken};
use crate::fleet::replicate::{self, TableSchema};
use crate::fleet::{Fleet, FleetError, outbox};
use crate::sim::Mismatch;
use crate::storage::tokens::FoundToken;
use crate::storage::{DbError, audit, policies};
use serde_json::json;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

/// How often the cell looks for new rows to send: well inside the 2 s a row may wait, and
/// few enough transactions that eight cells on two cores hardly feel them.
const POLL: Duration = Duration::from_millis(500);
/// How often it beats, pulls policies, answers requests and rereads the tokens.
const SYNC: Duration = Duration::from_secs(1);
/// The longest wait between tries while the fleet is unreachable.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// The cell's link to its fleet, shared with the HTTP side.
pub struct FleetLink {
    pub fleet: Fleet,
    /// Whether the last exchange with the fleet's database succeeded.
    reachable: AtomicBool,
    /// Every cell's tokens by hash, as last read from the fleet.
    tokens: RwLock<HashMap<String, FleetToken>>,
    /// The registry's policies this cell refused (too large, unreadable): not fetched again.
    refused: Mutex<Vec<String>>,
}

impl FleetLink {
    pub fn new(fleet: Fleet) -> Arc<FleetLink> {
        Arc::new(FleetLink {
            fleet,
            reachable: AtomicBool::new(false),
            tokens: RwLock::default(),
            refused: Mutex::default(),
        })
    }

    /// A token another cell of the fleet made, as last read from the fleet.
    pub fn token(&self, hash: &str) -> Option<FoundToken> {
        let tokens = self.tokens.read().ok()?;
        let token = tokens.get(hash)?;
        let caller = crate::storage::tokens::Caller {
            // No row on this cell: nothing here revokes it by id.
            token_id: 0,
            name: format!("{}@{}", token.name, token.cell_id),
            role: crate::storage::tokens::Role::parse(&token.role)?,
        };
        Some(FoundToken {
            caller,
            expires_at: token.expires_at.clone(),
            expires_unix_ms: token.expires_unix_ms,
            revoked_at: token.revoked_at.clone(),
        })
    }
}

/// The fleet's database unreachable (503), or refusing what the cell asked (500), as a
/// request's error.
pub fn unavailable(error: FleetError) -> Error {
    match error {
        FleetError::Unreachable(_) => Error::FleetUnavailable(error.to_string()),
        _ => Error::Internal(error.to_string()),
    }
}

/// Refuses a `cell` filter that cannot name a cell.
pub fn check_cell(cell: Option<&str>) -> Result<()> {
    if let Some(cell) = cell {
        crate::config::service::check_cell_id(cell)
            .map_err(|why| Error::bad_request(format!("cell `{cell}` is not a cell id: {why}")))?;
    }
    Ok(())
}

/// The link, or the error that says this cell is in no fleet.
pub fn link(context: &Context) -> Result<&Arc<FleetLink>> {
    context.fleet.as_ref().ok_or_else(|| {
        Error::NoFleet(
            "this cell is in no fleet: start it with --fleet postgres://… \
                        (fleet.url, CELLD_FLEET_URL)"
                .to_string(),
        )
    })
}

/// Asks every cell to activate the registry's policy `sha256` where it passed (audited).
pub async fn request_activation(
    context: &Context,
    sha256: &str,
    by: &str,
) -> Result<registry::Activation> {
    let link = link(context)?;
    let known = crate::fleet::reads::policies(&link.fleet)
        .await
        .map_err(unavailable)?
        .iter()
        .any(|p| p.sha256 == sha256);
    if !known {
        return Err(Error::not_found(format!(
            "the fleet's registry holds no policy with sha256 `{sha256}`"
        )));
    }
    let request = registry::request_activation(&link.fleet, sha256, by)
        .await
        .map_err(unavailable)?;
    audit::record(
        &context.db,
        by,
        "fleet.activate",
        json!({"activation_id": request.id, "sha256": sha256}),
    )
    .await?;
    Ok(request)
}

/// Runs until shutdown: sends the outbox, and about every second beats, pulls policies,
/// answers activation requests and rereads the tokens.
pub async fn run(context: Context, link: Arc<FleetLink>) {
    let mut shutdown = context.shutdown.clone();
    let tables = match replicate::schema(&context.db).await {
        Ok(tables) => tables,
        Err(error) => {
            tracing::error!(%error, "cannot read the cell's schema: nothing is replicated");
            return;
        }
    };
    let mut migrated = false;
    let mut backoff = POLL;
    let mut last_sync: Option<Instant> = None;
    let mut last_lag_s = None;
    loop {
        if *shutdown.borrow() {
            return;
        }
        let round = async {
            if !migrated {
                link.fleet.migrate().await?;
                migrated = true;
            }
            last_lag_s = send_all(&context, &link, &tables).await?.or(last_lag_s);
            if last_sync.is_none_or(|at| at.elapsed() >= SYNC) {
                sync(&context, &link, last_lag_s).await?;
                last_sync = Some(Instant::now());
            }
            Ok::<(), SyncError>(())
        };
        match round.await {
            Ok(()) => {
                if !link.reachable.swap(true, Ordering::SeqCst) {
                    tracing::info!(cell = %link.fleet.cell_id, "the fleet's database is reachable");
                }
                backoff = POLL;
            }
            Err(SyncError::Fleet(error)) => {
                if link.reachable.swap(false, Ordering::SeqCst) || backoff == POLL {
                    let backlog = outbox::backlog(&context.db).await.unwrap_or(-1);
                    tracing::warn!(%error, backlog,
                        "replication to the fleet stopped: rows wait on the cell");
                }
                backoff = (backoff * 2).min(MAX_BACKOFF);
            }
            Err(error) => {
                tracing::warn!(%error, "the fleet's work on the cell failed; trying again");
                backoff = (backoff * 2).min(MAX_BACKOFF);
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = shutdown.changed() => {}
        }
    }
}

#[derive(Debug, thiserror::Error)]
enum SyncError {
    #[error(transparent)]
    Fleet(#[from] FleetError),
    #[error(transparent)]
    Cell(#[from] DbError),
    /// A workflow it ran on the cell (registering, evaluating, activating) failed.
    #[error(transparent)]
    Workflow(#[from] Error),
}

impl From<replicate::ReplicationError> for SyncError {
    fn from(error: replicate::ReplicationError) -> Self {
        match error {
            replicate::ReplicationError::Cell(e) => SyncError::Cell(e),
            replicate::ReplicationError::Fleet(e) => SyncError::Fleet(e),
        }
    }
}

/// Sends batches until the outbox is empty; answers the last batch's oldest wait, s.
async fn send_all(
    context: &Context,
    link: &FleetLink,
    tables: &[TableSchema],
) -> std::result::Result<Option<f64>, SyncError> {
    let mut oldest = None;
    while let Some(sent) = replicate::send_batch(&context.db, &link.fleet, tables).await? {
        for lag in &sent.lags_s {
            context.metrics.fleet_lag_seconds.observe(*lag);
        }
        context
            .metrics
            .fleet_rows
            .inc_by((sent.upserted + sent.deleted) as u64);
        oldest = sent.lags_s.iter().copied().reduce(f64::max);
        if (sent.entries as i64) < replicate::BATCH_ENTRIES {
            break;
        }
    }
    Ok(oldest)
}

async fn sync(
    context: &Context,
    link: &FleetLink,
    lag_s: Option<f64>,
) -> std::result::Result<(), SyncError> {
    beat(context, link, lag_s).await?;
    pull_policies(context, link).await?;
    answer_activations(context, link).await?;
    let tokens = registry::tokens(&link.fleet).await?;
    if let Ok(mut known) = link.tokens.write() {
        known.clear();
        for token in tokens {
            // A hash made on two cells counts as revoked when either revoked it.
            let revoked = known
                .get(&token.token_hash)
                .and_then(|t| t.revoked_at.clone());
            let hash = token.token_hash.clone();
            let mut token = token;
            token.revoked_at = token.revoked_at.or(revoked);
            known.insert(hash, token);
        }
    }
    Ok(())
}

async fn beat(
    context: &Context,
    link: &FleetLink,
    lag_s: Option<f64>,
) -> std::result::Result<(), SyncError> {
    let status = context.cell.status();
    let backlog = outbox::backlog(&context.db).await?;
    context.metrics.fleet_backlog.set(backlog);
    let active = policies::list(&context.db)
        .await?
        .into_iter()
        .find(|p| p.status == "active")
        .map(|p| json!({"id": p.id, "name": p.name, "sha256": p.sha256}).to_string());
    let beat = registry::Heartbeat {
        state: status.machine.state.name().to_string(),
        stop_reason: status.machine.stop_reason.map(|r| r.code),
        estop_latched: status.estop_latched,
        active_policy: active,
        counters: serde_json::to_string(&status.machine.counters).unwrap_or_default(),
        config_hash: context.cell_config.config_hash(),
        backlog,
        lag_s,
    };
    registry::beat(&link.fleet, &beat).await?;
    Ok(())
}

/// Registers the registry's policies this cell lacks, and queues each one's evaluation on
/// this cell (the gate reads only evaluations on the cell's own configuration).
async fn pull_policies(context: &Context, link: &FleetLink) -> std::result::Result<(), SyncError> {
    let mut skipped = registry::held(&context.db).await?;
    skipped.extend(link.refused.lock().map(|r| r.clone()).unwrap_or_default());
    for file in registry::missing(&link.fleet, &skipped).await? {
        let by = format!(
            "fleet ({})",
            file.uploaded_by.as_deref().unwrap_or("unknown")
        );
        let max = context.settings.policies.max_parameters;
        let checked = crate::policy::file::check_parameter_count(&file.file, max)
            .map_err(|e| Error::unprocessable(e.to_string()));
        let registered = match checked {
            Ok(()) => super::policies::register(&context.db, &file.name, file.file, &by).await,
            Err(refused) => Err(refused),
        };
        let policy = match registered {
            Ok((policy, _)) => policy,
            Err(error) if matches!(error, Error::Invalid { .. }) => {
                tracing::warn!(%error, sha256 = %file.sha256, name = %file.name,
                    "a policy of the fleet's registry is refused on this cell");
                if let Ok(mut refused) = link.refused.lock() {
                    refused.push(file.sha256.clone());
                }
                continue;
            }
            Err(error) => return Err(error.into()),
        };
        audit::record(
            &context.db,
            "fleet",
            "policy.pull",
            json!({"policy_id": policy.id, "name": file.name, "sha256": file.sha256,
                   "first_cell": file.first_cell}),
        )
        .await?;
        let evaluated = super::policies::evaluate(
            context,
            policy.id,
            None,
            None,
            policies::EvaluatedOn::Cell(Mismatch::default()),
            Default::default(),
            "fleet",
        )
        .await;
        if let Err(error) = evaluated {
            tracing::warn!(%error, policy = policy.id, "a pulled policy's evaluation is not queued");
        }
    }
    Ok(())
}

/// Answers each activation request this cell has not: activates the policy when its
/// evaluation on this cell passes the gate, and waits while that evaluation is still to come.
async fn answer_activations(
    context: &Context,
    link: &FleetLink,
) -> std::result::Result<(), SyncError> {
    for (id, sha256, by) in registry::unanswered(&link.fleet).await? {
        let Some(policy) = policies::list(&context.db)
            .await?
            .into_iter()
            .find(|p| p.sha256 == sha256)
        else {
            let detail = format!("this cell holds no policy with sha256 {sha256}");
            registry::answer(&link.fleet, id, "missing", &detail).await?;
            continue;
        };
        if policy.status == "active" {
            registry::answer(&link.fleet, id, "already_active", "").await?;
            continue;
        }
        let (_, gate) = super::gate::evaluated(context, policy.id, "activation").await?;
        if let Err(why) = gate {
            let pending = policies::latest_evaluation(&context.db, policy.id)
                .await?
                .is_some_and(|e| e.status == "queued" || e.status == "running");
            if !pending {
                registry::answer(&link.fleet, id, "not_passed", &why).await?;
            }
            continue;
        }
        let by = format!("{by} (fleet activation {id})");
        match super::policies::activate(context, policy.id, false, None, &by).await {
            Ok(done) => {
                let detail = match done.retired {
                    Some(retired) => {
                        format!("policy {} active; policy {retired} retired", policy.id)
                    }
                    None => format!("policy {} active", policy.id),
                };
                registry::answer(&link.fleet, id, "activated", &detail).await?;
            }
            Err(Error::Conflict(why)) => {
                registry::answer(&link.fleet, id, "not_passed", &why).await?;
            }
            Err(error) => return Err(error.into()),
        }
    }
    Ok(())
}
