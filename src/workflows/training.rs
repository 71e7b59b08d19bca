//! Training runs: they wait their turn in the work queue beside evaluations (`queue`) and
//! compute on one of its threads at low priority, so a running job keeps its timing; the
//! demonstrations named are read and checked before the run is queued, or the demonstrator is
//! recorded in the twin; the result is registered as a `candidate` policy linked to the run,
//! and the run to the demonstrations it learned from.

use super::queue::{Cancelled, NoTurn, Ticket, WorkId, WorkKind};
use super::{Context, Error, Result, off_the_runtime};
use crate::learning::demos::{self, DemoEpisode};
use crate::learning::run::{self, CurvePoint, RunError, TrainingPart, TrainingSettings};
use crate::sim::EnvOptions;
use crate::storage::demonstrations::{self, NewDemonstration};
use crate::storage::{Db, audit, training};
use serde_json::{Value, json};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const DEFAULT_RECORDED_EPISODES: usize = 400;
const MAX_RECORDED_EPISODES: usize = 100_000;
/// Stored demonstrations one run may name.
pub const MAX_NAMED_DEMONSTRATIONS: usize = 1000;

/// What an admin asks of a training run: settings (what is left out keeps its default), with
/// the common ones also on their own.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TrainingRequest {
    pub settings: Option<TrainingSettings>,
    pub part: Option<TrainingPart>,
    pub seed: Option<u64>,
    /// TD3 episodes.
    pub episodes: Option<usize>,
    /// Stored demonstrations to learn from; none: record `record` episodes of the demonstrator.
    pub demonstrations: Vec<i64>,
    pub record: Option<usize>,
}

/// Checks a run, stores it and queues it (it starts at once when a place is free); answers with
/// the run as it is stored, `queued` with its position or `running`. A full queue refuses it
/// ([`Error::Busy`]) before anything is stored.
pub async fn start(
    context: &Context,
    request: TrainingRequest,
    by: &str,
) -> Result<training::TrainingRun> {
    // The settings as given are checked too: an override below must not hide a bad value.
    if let Some(given) = &request.settings {
        given.check().map_err(Error::unprocessable)?;
    }
    let mut settings = request.settings.unwrap_or_default();
    if let Some(part) = request.part {
        settings.part = part;
    }
    if let Some(seed) = request.seed {
        settings.seed = seed;
    }
    if let Some(episodes) = request.episodes {
        settings.td3_episodes = episodes;
    }
    settings.check().map_err(Error::unprocessable)?;
    let record = request.record.unwrap_or(DEFAULT_RECORDED_EPISODES);
    if !(10..=MAX_RECORDED_EPISODES).contains(&record) {
        return Err(Error::unprocessable(format!(
            "record = {record} is outside 10..={MAX_RECORDED_EPISODES}"
        )));
    }
    // The demonstrations named, read and checked before the run starts.
    let ids = request.demonstrations;
    if ids.len() > MAX_NAMED_DEMONSTRATIONS {
        return Err(Error::unprocessable(format!(
            "{} demonstrations named; at most {MAX_NAMED_DEMONSTRATIONS}",
            ids.len()
        )));
    }
    let mut seen = std::collections::HashSet::new();
    if let Some(id) = ids.iter().find(|&&id| !seen.insert(id)) {
        return Err(Error::unprocessable(format!(
            "demonstration {id} is named twice"
        )));
    }
    let mut episodes: Vec<DemoEpisode> = Vec::new();
    let inputs = settings.inputs().name();
    for &id in &ids {
        let stored = demonstrations::get(&context.db, id)
            .await?
            .ok_or_else(|| Error::not_found(format!("no demonstration with id {id}")))?;
        if stored.inputs != inputs {
            return Err(Error::unprocessable(format!(
                "demonstration {id} holds {} inputs and this run learns from {inputs} ones \
                 (for_any_cell = {}); name demonstrations of its kind, or none to record them",
                stored.inputs, settings.for_any_cell
            )));
        }
        let text = demonstrations::body(&context.db, id)
            .await?
            .ok_or_else(|| Error::not_found(format!("no demonstration with id {id}")))?;
        let read = off_the_runtime(move || {
            demos::read_jsonl(text.as_bytes())
                .map_err(|e| Error::unprocessable(format!("demonstration {id}: {e}")))
        })
        .await?;
        episodes.extend(read);
    }
    if !ids.is_empty() {
        run::check_demonstrations(&episodes)
            .map_err(|e| Error::unprocessable(format!("the demonstrations named hold {e}")))?;
    }

    let admitting = context.work.admissions().await;
    let ticket = context.work.reserve()?;
    let run = training::start(
        &context.db,
        !ticket.is_running(),
        &json!(settings),
        &ids,
        by,
    )
    .await?;
    ticket.assign(WorkId::training(run.id));
    drop(admitting);
    let job = RunJob {
        id: run.id,
        settings,
        episodes,
        record: ids.is_empty().then_some(record),
        cancel: ticket.cancel_flag(),
        by: by.to_string(),
    };
    tokio::spawn(drive(context.clone(), ticket, job));
    // After the spawn: the place is freed by the run's end whatever happens here.
    audit::record(
        &context.db,
        by,
        "training.start",
        json!({"training_run_id": run.id, "settings": run.settings, "demonstrations": ids}),
    )
    .await?;
    Ok(placed(context, run))
}

/// `run` with its place in the work queue while it waits.
fn placed(context: &Context, mut run: training::TrainingRun) -> training::TrainingRun {
    run.queue_position = context.work.position(WorkId::training(run.id));
    run
}

/// One run, with its place in the work queue while it waits.
pub async fn get(context: &Context, id: i64) -> Result<training::TrainingRun> {
    let run = training::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no training run with id {id}")))?;
    Ok(placed(context, run))
}

/// Every run, newest first, without their curves, with their places in the work queue.
pub async fn list(context: &Context) -> Result<Vec<training::TrainingRun>> {
    let mut runs = training::list(&context.db).await?;
    let positions = context.work.positions(WorkKind::Training);
    for run in &mut runs {
        run.queue_position = positions.get(&run.id).copied();
    }
    Ok(runs)
}

/// Cancels a run: a queued one leaves the queue and is `cancelled` before this returns; a
/// running one is asked to stop at its next check. Says which.
pub async fn cancel(context: &Context, id: i64, by: &str) -> Result<Cancelled> {
    let run = training::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no training run with id {id}")))?;
    let cancelled = context.work.cancel(WorkId::training(id));
    match cancelled {
        Cancelled::Dequeued => {
            let why = Some("cancelled before it started");
            training::finish(&context.db, id, "cancelled", None, None, why).await?;
        }
        Cancelled::Stopping => {}
        Cancelled::NotHere => {
            return Err(Error::conflict(format!(
                "training run {id} is {} and can no longer be cancelled",
                run.status
            )));
        }
    }
    audit::record(
        &context.db,
        by,
        "training.cancel",
        json!({"training_run_id": id}),
    )
    .await?;
    Ok(cancelled)
}

struct RunJob {
    id: i64,
    settings: TrainingSettings,
    episodes: Vec<DemoEpisode>,
    /// Expert episodes to record first, when no demonstrations were named.
    record: Option<usize>,
    cancel: Arc<AtomicBool>,
    by: String,
}

/// Live progress, shared between the training thread and the task that stores it.
#[derive(Default)]
struct Live {
    stage: String,
    progress: f64,
    curve: Vec<CurvePoint>,
}

/// Waits for the run's turn, runs it to its end and stores what came of it; its place in the
/// queue is freed (the ticket dropped) once that is stored, under the queue's admissions lock.
async fn drive(context: Context, ticket: Ticket, job: RunJob) {
    let db = &context.db;
    let outcome = match ticket.turn().await {
        Err(NoTurn::Removed) => Err(RunError::Cancelled),
        Err(NoTurn::Closed) => Err(RunError::Training(
            "the service stopped before the run started".into(),
        )),
        Ok(()) => {
            if let Err(error) = training::run(db, job.id).await {
                tracing::warn!(%error, run = job.id, "could not store a training run's start");
            }
            train(&context, &job).await
        }
    };
    let ending = context.work.admissions().await;
    if context.work.is_closed() {
        // Stopping: `app` marks what waited or ran, and storage may be closing.
        return;
    }
    let stored = match outcome {
        Ok((policy_id, figures)) => {
            training::finish(
                db,
                job.id,
                "succeeded",
                Some(policy_id),
                Some(&figures),
                None,
            )
            .await
        }
        Err(RunError::Cancelled) => {
            training::finish(db, job.id, "cancelled", None, None, Some("cancelled")).await
        }
        Err(error) => {
            training::finish(db, job.id, "failed", None, None, Some(&error.to_string())).await
        }
    };
    if let Err(error) = stored {
        tracing::error!(%error, run = job.id, "could not store a training run's end");
    }
    drop(ticket);
    drop(ending);
}

async fn train(context: &Context, job: &RunJob) -> std::result::Result<(i64, Value), RunError> {
    let failed = |e: String| RunError::Training(e);
    let cell = context.cell_config.clone();
    let mut episodes = job.episodes.clone();
    if let Some(count) = job.record {
        let (recorded, seed) = (cell.clone(), job.settings.seed);
        let demonstrator = job.settings.demonstrator.clone();
        let recording = job.settings.recording();
        episodes = context
            .work
            .compute(move || {
                demos::record_with(
                    &recorded,
                    EnvOptions::from_cell(&recorded),
                    &demonstrator,
                    count,
                    seed,
                    recording,
                )
            })
            .await
            .map_err(failed)?;
        let new = NewDemonstration {
            name: &format!(
                "training run {} (recorded {}{})",
                job.id,
                job.settings.demonstrator,
                if job.settings.for_any_cell {
                    " on randomised cells"
                } else {
                    ""
                }
            ),
            source: "scripted",
            cell_hash: &cell.config_hash(),
            job_id: None,
            inputs: job.settings.inputs().name(),
            created_by: &job.by,
        };
        let id = demonstrations::insert(&context.db.writer, &new, &episodes)
            .await
            .map_err(|e| failed(e.to_string()))?;
        training::set_demonstrations(&context.db, job.id, &[id])
            .await
            .map_err(|e| failed(e.to_string()))?;
    }
    if job.cancel.load(Ordering::SeqCst) {
        return Err(RunError::Cancelled);
    }

    let live = Arc::new(Mutex::new(Live::default()));
    let keeper = tokio::spawn(keep_progress(context.db.clone(), job.id, live.clone()));
    let (settings, cancel, shared) = (job.settings.clone(), job.cancel.clone(), live.clone());
    let result = context
        .work
        .compute(move || {
            run::run(
                &cell,
                episodes,
                &settings,
                &mut |point, progress| {
                    let mut live = shared.lock().expect("live lock");
                    live.stage = point.stage.to_string();
                    live.progress = progress;
                    live.curve.push(point);
                },
                &|| cancel.load(Ordering::SeqCst),
            )
        })
        .await
        .map_err(failed)
        .and_then(|r| r);
    keeper.abort();
    store_progress(&context.db, job.id, &live).await;
    let (file, figures) = result?;
    let (policy, _) = super::policies::register(
        &context.db,
        &format!("training-{}", job.id),
        file.to_bytes(),
        &job.by,
    )
    .await
    .map_err(|e| failed(e.to_string()))?;
    Ok((policy.id, figures))
}

/// Stores the live progress every half second while the run lasts, when it has moved.
async fn keep_progress(db: Db, id: i64, live: Arc<Mutex<Live>>) {
    let mut stored = (0, f64::NAN);
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let now = {
            let live = live.lock().expect("live lock");
            (live.curve.len(), live.progress)
        };
        if now != stored {
            store_progress(&db, id, &live).await;
            stored = now;
        }
    }
}

async fn store_progress(db: &Db, id: i64, live: &Mutex<Live>) {
    // Copied under the lock and serialised outside it: the training thread takes the lock
    // at each report.
    let (stage, progress, curve) = {
        let live = live.lock().expect("live lock");
        (live.stage.clone(), live.progress, live.curve.clone())
    };
    if stage.is_empty() {
        return;
    }
    let curve = json!(curve);
    if let Err(error) = training::update(db, id, &stage, progress, &curve).await {
        tracing::warn!(%error, run = id, "could not store training progress");
    }
}
