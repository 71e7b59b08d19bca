//! `celld serve`: wires the control thread, the storage writer, telemetry and HTTP together,
//! and takes them down in order. The only module that knows all of them.
//!
//! ```text
//!   HTTP handlers ──commands──▶ control thread (robot, controller, supervisor)
//!        ▲                          │ events, in order
//!        │ status (watch)           ├──▶ storage writer (batched SQLite transactions)
//!        └──────────────────────────┼──▶ telemetry broadcast ──▶ SSE subscribers
//!                                   └──▶ metrics
//! ```

use crate::cell::cpu::{self, CpuPlan};
use crate::cell::task::{self, CellEvent, LoopSettings};
use crate::cell::{
    CellBackend, CellCommand, DriverBackend, DriverSettings, JobStatus, SafetyLimits, TwinBackend,
};
use crate::config::cell::CellConfig;
use crate::config::drivers::RobotDriver;
use crate::config::service::ServiceConfig;
use crate::fleet;
use crate::http;
use crate::metrics::Metrics;
use crate::opcua::{self, OpcUaSettings};
use crate::policy;
use crate::storage::tokens::{self, Role};
use crate::storage::{Db, jobs, machine, policies, recorder, training};
use crate::workflows::queue::WorkQueue;
use crate::workflows::{self, Context, TelemetryMessage};
use anyhow::{Context as _, Result, bail};
use serde_json::json;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use tokio::sync::{broadcast, mpsc, watch};

/// Places the threads (`control.cpu`), starts the async runtime and runs the service until
/// SIGINT or SIGTERM.
pub fn run(settings: ServiceConfig) -> Result<()> {
    let available = cpu::available().context("reading this process's CPUs")?;
    let placement = cpu::plan(&available, settings.control.cpu)?;
    if let Some(placement) = &placement {
        // Before any thread starts: the runtime's workers and every thread after them inherit
        // this set; only the control thread leaves it, for its own CPU.
        cpu::pin_current_thread(&placement.others)
            .with_context(|| format!("keeping the service on CPUs {:?}", placement.others))?;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let served = runtime.block_on(serve(settings, placement));
    // Dropping a runtime waits for every blocking task; a stopped service must not (a request's
    // parse, a join that timed out). Work threads hold nothing once `serve` has marked their
    // work: the process ends with them.
    runtime.shutdown_timeout(Duration::from_millis(200));
    served
}

async fn serve(settings: ServiceConfig, placement: Option<CpuPlan>) -> Result<()> {
    settings.validate()?;
    let cell = match &settings.cell {
        Some(path) => CellConfig::load(path)?,
        None => CellConfig::reference(),
    };
    let active = &settings.control.active_controller;
    if !active.starts_with("policy:") {
        policy::check_known(active).context("control.active_controller")?;
    }
    let db = Db::open(&settings.db).await?;
    let interrupted = jobs::interrupt_leftovers(&db).await?;
    if interrupted > 0 {
        tracing::warn!(
            interrupted,
            "jobs left running or queued by the last run are now interrupted"
        );
    }
    let runs = training::fail_leftovers(&db).await?;
    if runs > 0 {
        tracing::warn!(
            runs,
            "training runs left queued or running by the last run are marked failed"
        );
    }
    let evaluations = policies::fail_leftover_evaluations(&db).await?;
    if evaluations > 0 {
        tracing::warn!(
            evaluations,
            "policy evaluations left queued or running by the last run are marked failed"
        );
    }
    let first_token = if tokens::count(&db).await? == 0 {
        Some(first_admin_token(&db, &settings.db).await?)
    } else {
        None
    };
    let fleet = join_or_leave_fleet(&settings, &db).await?;
    let estop_latched = db.cell_flag("estop").await?;
    let counters = machine::counters(&db)
        .await
        .context("reading the production counters")?;

    let metrics = Metrics::default();
    let (telemetry, _) = broadcast::channel(settings.control.telemetry_buffer);
    let (events, events_inbox) = mpsc::unbounded_channel();
    // Jobs whose steps the storage writer cannot store: the control thread holds them.
    let (unrecorded, unrecorded_jobs) = mpsc::unbounded_channel();
    let recorder = tokio::spawn(recorder::run(
        db.clone(),
        events_inbox,
        settings.control.step_batch,
        cell.config_hash(),
        unrecorded,
    ));
    let sink = event_sink(metrics.clone(), telemetry.clone(), events);
    let period = settings
        .step_period_s(cell.camera.rate_hz)
        .map(Duration::from_secs_f64);
    let loop_settings = LoopSettings {
        period,
        limits: SafetyLimits {
            deadline_s: settings.control.deadline_ms / 1000.0,
            max_stale_steps: settings.control.max_stale_steps,
        },
        estop_latched,
        counters,
        cpu: placement.as_ref().map(|p| p.control),
    };
    let cpu = placement.as_ref().map(|p| p.control);
    let backend: Box<dyn CellBackend> = match settings.robot.driver {
        RobotDriver::Twin => Box::new(TwinBackend::new(&cell, cpu)),
        RobotDriver::Gcs => {
            let drivers = DriverSettings {
                robot_address: settings.robot.endpoint(),
                robot: settings.robot.gcs_settings(),
                camera_address: settings.camera.endpoint(),
                camera: settings.camera.camera_settings(),
                rehearsal: settings.robot.rehearsal,
            };
            Box::new(
                DriverBackend::connect(&cell, drivers, cpu)
                    .context("connecting the cell's drivers ([robot] and [camera] settings)")?
                    .observed_by(Arc::new(metrics.clone())),
            )
        }
    };
    let (cell_handle, control_thread) = task::spawn(cell.clone(), backend, loop_settings, sink);
    tokio::spawn(workflows::cell::fail_unrecorded_jobs(
        cell_handle.clone(),
        unrecorded_jobs,
    ));

    let (stop_streams, shutdown) = watch::channel(false);
    let accepting = Arc::new(AtomicBool::new(true));
    let context = Context {
        db: db.clone(),
        cell: cell_handle.clone(),
        cell_config: Arc::new(cell.clone()),
        settings: Arc::new(settings.clone()),
        metrics,
        telemetry,
        accepting: accepting.clone(),
        shutdown: shutdown.clone(),
        known_callers: Default::default(),
        work: WorkQueue::new(settings.work.concurrency, settings.work.queue_length)
            .context("starting the background work threads")?,
        latch_writes: Default::default(),
        fleet: fleet.clone(),
    };
    let listener = tokio::net::TcpListener::bind(settings.listen)
        .await
        .with_context(|| format!("cannot listen on {}", settings.listen))?;
    let address = listener.local_addr()?;
    let work = context.work.clone();
    let server_shutdown = shutdown.clone();
    workflows::policies::register_bundled(&context)
        .await
        .context("registering the bundled policy")?;
    if let Some(why) = workflows::jobs::configured_policy_refused(&context).await? {
        // Jobs asking for `active` are refused for this reason until it passes (or a policy
        // is activated); the service itself runs.
        tracing::warn!(%why, "control.active_controller names a policy the gate refuses");
    }
    if let Some(link) = &fleet {
        tokio::spawn(workflows::fleet::run(context.clone(), link.clone()));
    }
    let plant = opcua::cell::CellPlant::start(context.clone());
    let server = tokio::spawn(http::server::serve(
        listener,
        http::router(context),
        (&settings.http).into(),
        server_shutdown,
    )?);
    let opcua_server = opcua::serve(
        plant,
        &OpcUaSettings::from_config(&settings),
        shutdown.clone(),
    )
    .await
    .context("starting the OPC UA server (opcua.listen)")?;
    println!(
        "celld: cell `{}` on the {} backend{}, database {}",
        cell.name,
        cell_handle.status().backend,
        match period {
            None => " (fast)".to_string(),
            Some(p) => format!(", control period {} ms", p.as_secs_f64() * 1000.0),
        },
        settings.db.display()
    );
    println!("celld: listening on http://{address}");
    if let Some(placement) = &placement {
        println!(
            "celld: the control thread has CPU {} to itself; everything else runs on CPUs {:?}",
            placement.control, placement.others
        );
    }
    match &first_token {
        // The token rides in the fragment, which the browser never sends to a server.
        Some(token) => {
            println!("celld: dashboard (signs in as admin) http://{address}/#token={token}")
        }
        None => println!(
            "celld: dashboard http://{address}/ (sign in with a token, such as the one in {})",
            admin_token_path(&settings.db).display()
        ),
    }
    if let Some(opcua) = &opcua_server {
        println!(
            "celld: OPC UA {} (certificate {}; a client's certificate is trusted once moved from {} to {})",
            opcua.endpoint_url(),
            opcua.certificate_path().display(),
            opcua.rejected_dir().display(),
            opcua.trusted_dir().display()
        );
    }
    if let Some(link) = &fleet {
        println!(
            "celld: in the fleet at {} as cell `{}`; rows replicate in the background",
            link.fleet.target, link.fleet.cell_id
        );
    }
    println!("celld: API http://{address}/api/docs (described at /api/openapi.json)");
    if estop_latched {
        println!("celld: the e-stop is latched from before; POST /api/cell/reset to clear it");
    }
    std::io::stdout().flush().ok();

    wait_for_signal().await;
    tracing::info!("stopping: no new jobs, holding the robot");
    accepting.store(false, Ordering::SeqCst);
    // The control thread holds the robot, closes the running and queued jobs as interrupted,
    // and exits; its event sink closes with it, which lets the storage writer finish.
    // Meanwhile background work stops: the queue takes no more, its running work is asked to
    // stop, and what waited or ran is marked failed now rather than at the next start.
    // Each wait is bounded (2 + 1 + 3 + 2 + 2 s), so the process is gone within 10 s.
    let (stopped, ()) = tokio::join!(
        tokio::time::timeout(
            Duration::from_secs(2),
            cell_handle.ask(|reply| CellCommand::Shutdown { reply }),
        ),
        stop_background_work(&work, &db),
    );
    if !matches!(stopped, Ok(Ok(()))) {
        tracing::error!("the control thread did not confirm the stop in 2 s");
    }
    let _ = stop_streams.send(true);
    let joined = tokio::task::spawn_blocking(move || control_thread.join());
    let _ = tokio::time::timeout(Duration::from_secs(1), joined).await;
    if tokio::time::timeout(Duration::from_secs(3), recorder)
        .await
        .is_err()
    {
        tracing::error!("the storage writer did not finish in 3 s");
    }
    if tokio::time::timeout(Duration::from_secs(2), server)
        .await
        .is_err()
    {
        tracing::warn!("open connections did not close in 2 s");
    }
    if let Some(opcua) = opcua_server
        && tokio::time::timeout(Duration::from_secs(2), opcua.finished())
            .await
            .is_err()
    {
        tracing::warn!("the OPC UA server did not stop in 2 s");
    }
    db.writer.close().await;
    db.reader.close().await;
    println!("celld: stopped");
    Ok(())
}

/// At shutdown: closes the work queue (its running work is asked to stop) and marks every
/// evaluation and training run still queued or running as failed, saying so; bounded by 2 s.
async fn stop_background_work(work: &WorkQueue, db: &Db) {
    let (running, waiting) = work.close();
    if !running.is_empty() || !waiting.is_empty() {
        tracing::warn!(
            running = running.len(),
            waiting = waiting.len(),
            "stopping background work: it is marked failed"
        );
    }
    let why = "the service was stopped (SIGTERM or SIGINT)";
    let marked = tokio::time::timeout(Duration::from_secs(2), async {
        policies::fail_unfinished_evaluations(db, why).await?;
        training::fail_unfinished(db, why).await
    })
    .await;
    match marked {
        Ok(Ok(_)) => {}
        Ok(Err(error)) => tracing::error!(%error, "could not mark the stopped background work"),
        Err(_) => tracing::error!("marking the stopped background work took over 2 s"),
    }
}

/// What the control thread's events turn into: metrics, telemetry, rows.
fn event_sink(
    metrics: Metrics,
    telemetry: broadcast::Sender<TelemetryMessage>,
    storage: mpsc::UnboundedSender<CellEvent>,
) -> Box<dyn FnMut(CellEvent) + Send> {
    Box::new(move |event| {
        let (name, data) = match &event {
            CellEvent::Step(record) => {
                metrics.step_seconds.observe(record.compute_us / 1e6);
                if let Some(reason) = &record.veto_reason {
                    metrics.count_veto(reason);
                }
                ("step", serde_json::to_string(record))
            }
            CellEvent::JobStarted { job_id } => (
                "job",
                serde_json::to_string(&json!({"job_id": job_id, "status": JobStatus::Running})),
            ),
            CellEvent::JobEnded { job_id, end } => {
                metrics.count_job(end.status.as_str(), end.failure_reason.as_deref());
                (
                    "job",
                    serde_json::to_string(&json!({
                        "job_id": job_id,
                        "status": end.status,
                        "failure_reason": end.failure_reason,
                        "steps": end.steps,
                        "reward": end.reward,
                    })),
                )
            }
            CellEvent::Latches {
                estop_latched,
                driver_latch,
            } => {
                metrics
                    .driver_latched
                    .set(i64::from(driver_latch.is_some()));
                (
                    "cell",
                    serde_json::to_string(&json!({
                        "estop_latched": estop_latched,
                        "driver_latch": driver_latch,
                    })),
                )
            }
            CellEvent::Machine(update) => ("machine", serde_json::to_string(update)),
        };
        if telemetry.receiver_count() > 0
            && let Ok(data) = data
        {
            let _ = telemetry.send(TelemetryMessage {
                event: name,
                data: data.into(),
            });
        }
        if storage.send(event).is_err() {
            tracing::error!("the storage writer has stopped; an event was not stored");
        }
    })
}

async fn wait_for_signal() {
    let interrupt = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut terminate =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
                .expect("install the SIGTERM handler");
        tokio::select! {
            _ = interrupt => {}
            _ = terminate.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = interrupt.await;
}

/// The file beside the database that holds the first admin token.
pub fn admin_token_path(db: &Path) -> PathBuf {
    db.with_file_name("admin.token")
}

/// With `fleet.url`: the link to the fleet (connected in the background) and the outbox
/// filling, with the cell's whole record the first time. Without: no outbox kept.
async fn join_or_leave_fleet(
    settings: &ServiceConfig,
    db: &Db,
) -> Result<Option<Arc<workflows::fleet::FleetLink>>> {
    let Some(url) = &settings.fleet.url else {
        if fleet::outbox::leave(db).await? {
            tracing::warn!("started without fleet.url: this cell no longer replicates to a fleet");
        }
        return Ok(None);
    };
    let cell_id = settings.cell_id();
    fleet::check_cell_id(&cell_id).map_err(|reason| {
        anyhow::anyhow!(
            "the cell id `{cell_id}` (service.cell_id, else the cell file's name) {reason}"
        )
    })?;
    let link = fleet::Fleet::connect_lazy(url, &cell_id).context("fleet.url")?;
    let queued = fleet::outbox::join(db, &link.target).await?;
    if queued > 0 {
        tracing::info!(rows = queued, cell = %cell_id, "joining the fleet: the cell's record is queued for it");
    }
    Ok(Some(workflows::fleet::FleetLink::new(link)))
}

/// Makes the first admin token, prints it once and writes it beside the database (mode 0600);
/// returns the secret for the sign-in URL.
async fn first_admin_token(db: &Db, db_path: &Path) -> Result<String> {
    let token = workflows::tokens::create(
        db,
        Role::Admin,
        "admin",
        None,
        "celld serve (first start)",
        "celld",
    )
    .await?;
    let path = admin_token_path(db_path);
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options
        .open(&path)
        .with_context(|| format!("cannot write {}", path.display()))?;
    writeln!(file, "{}", token.token)?;
    println!(
        "celld: first start: admin token (shown once; also in {}):\n{}",
        path.display(),
        token.token
    );
    Ok(token.token)
}

/// `celld token create`: a new token in the database, printed once; `expires_in` is a
/// lifetime such as `3600`, `90m`, `12h` or `30d` (none: never expires).
pub async fn create_token(
    db_path: &Path,
    role: &str,
    name: &str,
    expires_in: Option<&str>,
) -> Result<()> {
    let Some(role) = Role::parse(role) else {
        bail!("role `{role}` is not viewer, operator or admin");
    };
    let expires_in_s = expires_in
        .map(workflows::tokens::parse_lifetime)
        .transpose()
        .map_err(anyhow::Error::msg)
        .context("--expires-in")?;
    let db = Db::open(db_path).await?;
    let token =
        workflows::tokens::create(&db, role, name, expires_in_s, "celld token create", "cli")
            .await
            .context("--name")?;
    println!("{}", token.token);
    if let Some(at) = &token.expires_at {
        eprintln!("celld: token {} expires at {at}", token.id);
    }
    db.writer.close().await;
    db.reader.close().await;
    Ok(())
}

/// `celld token list`: every token, one a line, without secrets.
pub async fn list_tokens(db_path: &Path) -> Result<()> {
    let db = Db::open(db_path).await?;
    let listed = workflows::tokens::list(&db).await?;
    println!(
        "{:>4}  {:<8}  {:<8}  {:<24}  {:<24}  {:<24}  name",
        "id", "role", "state", "created", "expires", "revoked"
    );
    for token in listed {
        println!(
            "{:>4}  {:<8}  {:<8}  {:<24}  {:<24}  {:<24}  {}",
            token.id,
            token.role.as_str(),
            serde_json::to_value(token.state)?.as_str().unwrap_or(""),
            token.created_at,
            token.expires_at.as_deref().unwrap_or("never"),
            token.revoked_at.as_deref().unwrap_or("-"),
            token.name
        );
    }
    db.writer.close().await;
    db.reader.close().await;
    Ok(())
}

/// `celld token revoke ID`: revokes a token (audited as `cli`). A running service reads the
/// revocation within [`workflows::tokens::RECHECK`].
pub async fn revoke_token(db_path: &Path, id: i64) -> Result<()> {
    let db = Db::open(db_path).await?;
    let revoked = workflows::tokens::revoke_stored(&db, id, "cli").await;
    db.writer.close().await;
    db.reader.close().await;
    let token = revoked?;
    println!(
        "celld: token {} (`{}`, {}) revoked at {}",
        token.id,
        token.name,
        token.role.as_str(),
        token.revoked_at.as_deref().unwrap_or("?")
    );
    Ok(())
}
