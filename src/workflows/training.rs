//! Training runs: one at a time, on a thread of its own at low priority so a running job keeps
//! its timing; the demonstrations named are read and checked before the run starts, or the
//! demonstrator is recorded in the twin; the result is registered as a `candidate` policy
//! linked to the run, and the run to the demonstrations it learned from.

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

/// The run in progress, if any.
#[derive(Clone)]
pub struct ActiveRun {
    pub id: i64,
    pub cancel: Arc<AtomicBool>,
}

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

/// Checks a run, stores it and starts it in the background; answers with the run as it starts.
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

    let cancel = Arc::new(AtomicBool::new(false));
    reserve(context, &cancel)?;
    let run = match training::start(&context.db, &json!(settings), &ids, by).await {
        Ok(run) => run,
        Err(error) => {
            *context.training.lock().expect("training lock") = None;
            return Err(error.into());
        }
    };
    if let Some(active) = context.training.lock().expect("training lock").as_mut() {
        active.id = run.id;
    }
    let job = RunJob {
        id: run.id,
        settings,
        episodes,
        record: ids.is_empty().then_some(record),
        cancel,
        by: by.to_string(),
    };
    tokio::spawn(drive(context.clone(), job));
    // After the spawn: the slot is freed by the run's end whatever happens here.
    audit::record(
        &context.db,
        by,
        "training.start",
        json!({"training_run_id": run.id, "settings": run.settings, "demonstrations": ids}),
    )
    .await?;
    Ok(run)
}

/// Asks the running training run to stop at its next check.
pub async fn cancel(context: &Context, id: i64, by: &str) -> Result<()> {
    let run = training::get(&context.db, id)
        .await?
        .ok_or_else(|| Error::not_found(format!("no training run with id {id}")))?;
    let active = context.training.lock().expect("training lock").clone();
    match active {
        Some(active) if active.id == id => active.cancel.store(true, Ordering::SeqCst),
        _ => {
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
    Ok(())
}

/// Takes the one training slot, or says which run holds it.
fn reserve(context: &Context, cancel: &Arc<AtomicBool>) -> Result<()> {
    let mut active = context.training.lock().expect("training lock");
    if let Some(running) = active.as_ref() {
        return Err(Error::conflict(format!(
            "training run {} is running; one at a time",
            running.id
        )));
    }
    // Held from here, so two requests cannot both start; the id follows once stored.
    *active = Some(ActiveRun {
        id: 0,
        cancel: cancel.clone(),
    });
    Ok(())
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

/// Runs a training job to its end and stores what came of it.
async fn drive(context: Context, job: RunJob) {
    let outcome = train(&context, &job).await;
    let db = &context.db;
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
    *context.training.lock().expect("training lock") = None;
}

async fn train(context: &Context, job: &RunJob) -> std::result::Result<(i64, Value), RunError> {
    let failed = |e: String| RunError::Training(e);
    let cell = context.cell_config.clone();
    let mut episodes = job.episodes.clone();
    if let Some(count) = job.record {
        let (recorded, seed) = (cell.clone(), job.settings.seed);
        let demonstrator = job.settings.demonstrator.clone();
        let recording = job.settings.recording();
        episodes = on_training_thread(move || {
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
    let result = on_training_thread(move || {
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

/// Runs `work` on a thread of its own at low priority with a one-thread rayon pool, so
/// training never takes the cores a running job needs.
async fn on_training_thread<T: Send + 'static>(
    work: impl FnOnce() -> T + Send + 'static,
) -> std::result::Result<T, String> {
    let (reply, answer) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("celld-training".into())
        .spawn(move || {
            crate::cell::task::lower_priority();
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .start_handler(|_| crate::cell::task::lower_priority())
                .build();
            let result = match pool {
                Ok(pool) => {
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| pool.install(work)))
                        .map_err(|panic| {
                            format!("the training thread panicked: {}", panic_text(&*panic))
                        })
                }
                Err(error) => Err(error.to_string()),
            };
            let _ = reply.send(result);
        })
        .map_err(|e| e.to_string())?;
    answer
        .await
        .map_err(|_| "the training thread stopped".to_string())?
}

/// A panic's message (a `&str` or a `String` payload; anything else is unnamed).
fn panic_text(panic: &(dyn std::any::Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
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

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_panic_on_the_training_thread_is_reported_with_its_message() {
        let answer = on_training_thread(|| -> u8 { panic!("the loss is {}", f64::NAN) }).await;
        assert_eq!(
            answer,
            Err("the training thread panicked: the loss is NaN".to_string())
        );
        let answer = on_training_thread(|| -> u8 { std::panic::panic_any(7_u8) }).await;
        assert_eq!(
            answer,
            Err("the training thread panicked: (no message)".to_string())
        );
        assert_eq!(on_training_thread(|| 3_u8).await, Ok(3));
    }
}
