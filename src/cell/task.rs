//! The control thread: owns the robot, runs queued jobs one at a time at the control period,
//! and answers cancel, e-stop, reset and shutdown between steps.
//!
//! It is a plain OS thread, so policy inference and the supervisor never run on the async
//! runtime's workers. Commands come in on a channel; every event (job started, step, job ended,
//! e-stop) goes to one sink, in order; the cell's status is published on a watch channel.

use super::backend::{CellBackend, DriverLatch, EmergencyStop};
/// Kept at this path for the HTTP handlers that run background work behind the control thread.
pub use super::cpu::lower_priority;
use super::job::{JobEnd, JobRun, JobSpec, JobStatus, SafetyLimits, StepRecord, StepUncertainty};
use super::packml::{
    Command, Counters, Machine, MachineInput, MachineStatus, NotNow, StopReason, Transition,
};
use crate::config::cell::CellConfig;
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::mpsc;
use std::time::{Duration, Instant};
use tokio::sync::{oneshot, watch};

/// Requests to the control thread.
pub enum CellCommand {
    Enqueue(JobSpec),
    /// Cancels a queued or running job; answers whether the job was queued or running.
    Cancel {
        job_id: i64,
        reply: oneshot::Sender<bool>,
    },
    /// Latches the e-stop (pressed by `by`): stops motion, fails the running job and cancels
    /// the queue.
    EStop {
        by: String,
        reply: oneshot::Sender<()>,
    },
    /// Clears the latches (the e-stop's, the driver's); starts nothing. Answers why not when
    /// the backend's hardware is not ready again: both latches then stay.
    Reset {
        reply: oneshot::Sender<Result<(), String>>,
    },
    /// The first half of a reset whose latch must be stored before it is cleared: resets the
    /// backend (clearing the driver's latch when the hardware is ready) and keeps the e-stop
    /// latched; answers the count of e-stop presses so far, for [`CellCommand::ClearEStop`],
    /// or why the hardware is not ready (both latches then stay).
    ResetHardware {
        reply: oneshot::Sender<Result<u64, String>>,
    },
    /// The second half: clears the e-stop latch unless it was pressed again after the
    /// [`CellCommand::ResetHardware`] that answered `presses`; answers whether it cleared.
    /// The machine state clears (Aborted → Stopped) and, with `and_reset`, resets (to Idle).
    ClearEStop {
        presses: u64,
        and_reset: bool,
        by: String,
        reply: oneshot::Sender<bool>,
    },
    /// A PackML command other than clear: stop (the robot holds, the running and queued jobs
    /// are cancelled `stopped`), hold (the running job pauses after its current move),
    /// unhold, reset. Refused, changing nothing, in a state that does not take it.
    Machine {
        command: Command,
        by: String,
        reply: oneshot::Sender<Result<(), NotNow>>,
    },
    /// The storage writer cannot store job `job_id`'s steps: if it is running, the robot holds
    /// and the job fails with `storage_failed`; queued jobs are cancelled with that reason.
    StorageFailed {
        job_id: i64,
    },
    /// Holds the robot, closes the running and queued jobs as interrupted, and ends the thread.
    Shutdown {
        reply: oneshot::Sender<()>,
    },
}

/// What happened, in the order it happened.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum CellEvent {
    JobStarted {
        job_id: i64,
    },
    Step(Box<StepRecord>),
    JobEnded {
        job_id: i64,
        end: JobEnd,
    },
    /// The e-stop was pressed or reset, or the driver latched: both latches as they are now.
    Latches {
        estop_latched: bool,
        driver_latch: Option<DriverLatch>,
    },
    /// The machine state changed, or its counters did.
    Machine(Box<MachineUpdate>),
}

/// The PackML transitions one input made, and the machine after them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MachineUpdate {
    pub transitions: Vec<Transition>,
    pub machine: MachineStatus,
}

/// The running job as a plant watches it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct JobProgress {
    pub id: i64,
    pub controller: String,
    /// Steps taken.
    pub step: u32,
    /// Distance of the shaft's estimated position from the bore's axis point, mm (|P|).
    pub pose_error_mm: f64,
    /// σ of the estimate's sideways position, its worst direction, mm.
    pub sigma_mm: f64,
}

/// The relative pose the cell last estimated: P (mm) and O (deg) of docs/design.md §5.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, utoipa::ToSchema)]
pub struct LastPose {
    pub position_mm: [f64; 3],
    pub orientation_deg: [f64; 3],
}

/// The cell as `GET /api/cell` shows it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CellStatus {
    pub backend: String,
    pub estop_latched: bool,
    /// Why the hardware driver moves nothing until an operator reset (none: it is ready).
    pub driver_latch: Option<DriverLatch>,
    pub current_job: Option<i64>,
    pub queue: Vec<i64>,
    pub last_pose: Option<LastPose>,
    /// The running job's progress.
    pub job: Option<JobProgress>,
    /// The PackML state, stop reason and production counters.
    pub machine: MachineStatus,
}

/// The sending side of the control thread, cheap to clone.
#[derive(Clone)]
pub struct CellHandle {
    commands: mpsc::Sender<CellCommand>,
    status: watch::Receiver<CellStatus>,
    stop_now: Option<EmergencyStop>,
}

#[derive(Debug, thiserror::Error)]
#[error("the control thread has stopped")]
pub struct CellStopped;

impl CellHandle {
    pub fn status(&self) -> CellStatus {
        self.status.borrow().clone()
    }

    /// The status and each change of it.
    pub fn watch(&self) -> watch::Receiver<CellStatus> {
        self.status.clone()
    }

    /// Whether the control thread is still there (it owns the status sender, which a panic
    /// drops).
    pub fn is_running(&self) -> bool {
        self.status.has_changed().is_ok()
    }

    /// Stops motion at once from the calling thread, when the backend can (a driver that
    /// writes `STP` on its own connection); the e-stop does this before it asks the control
    /// thread to hold and latch.
    pub fn stop_now(&self) {
        if let Some(stop) = &self.stop_now {
            stop();
        }
    }

    pub fn send(&self, command: CellCommand) -> Result<(), CellStopped> {
        self.commands.send(command).map_err(|_| CellStopped)
    }

    /// Sends a command built around a reply channel and waits for the answer.
    pub async fn ask<T>(
        &self,
        command: impl FnOnce(oneshot::Sender<T>) -> CellCommand,
    ) -> Result<T, CellStopped> {
        let (reply, answer) = oneshot::channel();
        self.send(command(reply))?;
        answer.await.map_err(|_| CellStopped)
    }
}

/// How the thread runs.
pub struct LoopSettings {
    /// Control period; none runs steps back to back.
    pub period: Option<Duration>,
    pub limits: SafetyLimits,
    /// Whether the e-stop was latched when the service last stopped.
    pub estop_latched: bool,
    /// The production counters as last stored.
    pub counters: Counters,
    /// The CPU the thread keeps to itself (`cell::cpu`); none: wherever the kernel puts it.
    pub cpu: Option<usize>,
}

/// Starts the control thread. `sink` receives every event in order.
pub fn spawn(
    cell: CellConfig,
    backend: Box<dyn CellBackend>,
    settings: LoopSettings,
    sink: Box<dyn FnMut(CellEvent) + Send>,
) -> (CellHandle, std::thread::JoinHandle<()>) {
    let (commands, inbox) = mpsc::channel();
    let stop_now = backend.emergency_stop();
    let driver_latch = backend.latch();
    let latched = if settings.estop_latched {
        Some(StopReason::estop(
            "the e-stop was latched when the service last stopped".into(),
        ))
    } else {
        driver_latch
            .as_ref()
            .map(|latch| StopReason::driver_latch(&latch.code, &latch.reason))
    };
    let machine = Machine::new(latched, settings.counters.clone());
    let status = CellStatus {
        backend: backend.name().to_string(),
        estop_latched: settings.estop_latched,
        driver_latch,
        current_job: None,
        queue: Vec::new(),
        last_pose: None,
        job: None,
        machine: machine.status(),
    };
    let (status_tx, status_rx) = watch::channel(status);
    let mut control = ControlLoop {
        cell,
        backend,
        settings,
        sink,
        status: status_tx,
        queue: VecDeque::new(),
        running: None,
        epoch: Instant::now(),
        estop_presses: 0,
        machine,
        job_started_s: 0.0,
    };
    let thread = std::thread::Builder::new()
        .name("celld-control".into())
        .spawn(move || {
            super::cpu::raise_priority();
            if let Some(cpu) = control.settings.cpu
                && let Err(error) = super::cpu::pin_current_thread(&[cpu])
            {
                tracing::warn!(%error, cpu, "the control thread could not move to its CPU");
            }
            control.run(inbox)
        })
        .expect("spawn the control thread");
    (
        CellHandle {
            commands,
            status: status_rx,
            stop_now,
        },
        thread,
    )
}

/// How often an idle control thread lets the backend watch its hardware.
const IDLE_WATCH: Duration = Duration::from_millis(50);

struct ControlLoop {
    cell: CellConfig,
    backend: Box<dyn CellBackend>,
    settings: LoopSettings,
    sink: Box<dyn FnMut(CellEvent) + Send>,
    status: watch::Sender<CellStatus>,
    queue: VecDeque<JobSpec>,
    running: Option<JobRun>,
    epoch: Instant,
    /// E-stops pressed since the thread started (see [`CellCommand::ClearEStop`]).
    estop_presses: u64,
    /// The PackML state and counters.
    machine: Machine,
    /// When the running job started, on [`ControlLoop::now_s`]'s clock.
    job_started_s: f64,
}

impl ControlLoop {
    fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// [`ControlLoop::now_s`] as a clock a job reads around its work, free of `self`.
    fn clock(&self) -> impl Fn() -> f64 + use<> {
        let epoch = self.epoch;
        move || epoch.elapsed().as_secs_f64()
    }

    fn run(&mut self, inbox: mpsc::Receiver<CellCommand>) {
        let mut next_step = Instant::now();
        loop {
            // Wait for a command: forever when idle, until the next step when there is work.
            let has_work = self.stepping() || (self.running.is_none() && self.may_start());
            let command = if has_work {
                let wait = next_step.saturating_duration_since(Instant::now());
                match inbox.recv_timeout(wait) {
                    Ok(command) => Some(command),
                    Err(mpsc::RecvTimeoutError::Timeout) => None,
                    Err(mpsc::RecvTimeoutError::Disconnected) => return self.shutdown(None),
                }
            } else {
                match inbox.recv_timeout(IDLE_WATCH) {
                    Ok(command) => Some(command),
                    Err(mpsc::RecvTimeoutError::Timeout) => {
                        self.backend.watch();
                        None
                    }
                    Err(mpsc::RecvTimeoutError::Disconnected) => return self.shutdown(None),
                }
            };
            if let Some(command) = command {
                if let CellCommand::Shutdown { reply } = command {
                    return self.shutdown(Some(reply));
                }
                self.handle(command);
                // Drain whatever else arrived before stepping.
                while let Ok(command) = inbox.try_recv() {
                    if let CellCommand::Shutdown { reply } = command {
                        return self.shutdown(Some(reply));
                    }
                    self.handle(command);
                }
            }
            if self.running.is_none() && self.may_start() {
                self.start_next();
                next_step = Instant::now();
            }
            if self.stepping() && Instant::now() >= next_step {
                self.step();
                if let Some(period) = self.settings.period {
                    next_step += period;
                    // A step that overran its period does not make the next ones hurry.
                    next_step = next_step.max(Instant::now());
                }
            }
            self.publish();
        }
    }

    /// Whether a running job takes steps: not while the cell holds.
    fn stepping(&self) -> bool {
        use super::packml::PackMlState::{Held, Holding};
        self.running.is_some() && !matches!(self.machine.state(), Held | Holding)
    }

    /// Whether a queued job may start: something waits, nothing is latched, the cell is not
    /// holding.
    fn may_start(&self) -> bool {
        use super::packml::PackMlState::Held;
        !self.queue.is_empty()
            && !self.status.borrow().estop_latched
            && self.machine.state() != Held
    }

    fn handle(&mut self, command: CellCommand) {
        match command {
            CellCommand::Enqueue(spec) => {
                let state = self.machine.state();
                if self.status.borrow().estop_latched {
                    self.end_unstarted(spec.id, JobStatus::Cancelled, "estop");
                } else if !state.accepts_jobs() {
                    // The workflow checks the state before queueing; this is the race where a
                    // stop came between.
                    self.end_unstarted(spec.id, JobStatus::Cancelled, "stopped");
                } else {
                    self.queue.push_back(spec);
                    self.feed(MachineInput::JobQueued);
                }
            }
            CellCommand::Cancel { job_id, reply } => {
                let found = if self.running.as_ref().is_some_and(|r| r.id == job_id) {
                    self.backend.hold();
                    self.finish(JobStatus::Cancelled, Some("cancelled"));
                    true
                } else if let Some(index) = self.queue.iter().position(|s| s.id == job_id) {
                    self.queue.remove(index);
                    self.end_unstarted(job_id, JobStatus::Cancelled, "cancelled");
                    true
                } else {
                    false
                };
                let _ = reply.send(found);
            }
            CellCommand::EStop { by, reply } => {
                self.backend.hold();
                self.estop_presses += 1;
                self.status.send_modify(|s| s.estop_latched = true);
                self.send_latches();
                self.feed(MachineInput::EStop { by: &by });
                self.close_jobs(JobStatus::Failed, JobStatus::Cancelled, "estop");
                self.feed(MachineInput::Done);
                let _ = reply.send(());
            }
            CellCommand::Reset { reply } => {
                let result = self.backend.reset().map_err(|error| error.to_string());
                match &result {
                    Ok(()) => self.status.send_modify(|s| s.estop_latched = false),
                    Err(error) => tracing::warn!(%error, "reset: the hardware is not ready"),
                }
                // The reset may have cleared the driver's latch, or found it graver.
                self.take_driver_latch();
                self.send_latches();
                if result.is_ok() {
                    self.clear_machine(true, "celld");
                }
                let _ = reply.send(result);
            }
            CellCommand::ResetHardware { reply } => {
                let result = self.backend.reset().map_err(|error| error.to_string());
                if let Err(error) = &result {
                    tracing::warn!(%error, "reset: the hardware is not ready");
                }
                if self.take_driver_latch() {
                    self.send_latches();
                }
                let _ = reply.send(result.map(|()| self.estop_presses));
            }
            CellCommand::ClearEStop {
                presses,
                and_reset,
                by,
                reply,
            } => {
                let clear = presses == self.estop_presses;
                if clear {
                    self.status.send_modify(|s| s.estop_latched = false);
                    self.send_latches();
                    self.clear_machine(and_reset, &by);
                }
                let _ = reply.send(clear);
            }
            CellCommand::Machine { command, by, reply } => {
                let _ = reply.send(self.command(command, &by));
            }
            CellCommand::StorageFailed { job_id } => {
                if self.running.as_ref().is_some_and(|r| r.id == job_id) {
                    self.backend.hold();
                    self.finish(JobStatus::Failed, Some("storage_failed"));
                }
                for spec in std::mem::take(&mut self.queue) {
                    self.end_unstarted(spec.id, JobStatus::Cancelled, "storage_failed");
                }
            }
            CellCommand::Shutdown { .. } => unreachable!("handled by the loop"),
        }
    }

    /// A PackML command: the machine's transition, then what the cell does for it.
    fn command(&mut self, command: Command, by: &str) -> Result<(), NotNow> {
        if command == Command::Clear && self.status.borrow().estop_latched {
            // Clearing is the reset's first half and second half; a bare Clear here would
            // leave the e-stop latched under a Stopped state.
            return Err(self.machine.check(command).err().unwrap_or(NotNow {
                command,
                state: self.machine.state(),
                valid: "Aborted, once the e-stop latch is cleared (a reset)".into(),
            }));
        }
        self.machine.check(command)?;
        self.feed(MachineInput::Command { command, by });
        match command {
            Command::Stop => {
                self.backend.hold();
                self.close_jobs(JobStatus::Cancelled, JobStatus::Cancelled, "stopped");
                self.feed(MachineInput::Done);
            }
            Command::Hold => {
                // The move sent last is settled, so the robot stands at a step's end.
                self.settle_running();
                self.feed(MachineInput::Done);
            }
            Command::Unhold => self.feed(MachineInput::Done),
            Command::Clear | Command::Reset => {}
        }
        Ok(())
    }

    /// After the latches cleared: Aborted → Clearing → Stopped, then with `and_reset` (or
    /// from Stopped or Complete) → Resetting → Idle.
    fn clear_machine(&mut self, and_reset: bool, by: &str) {
        use super::packml::PackMlState::Aborted;
        if self.machine.state() == Aborted {
            self.feed(MachineInput::Command {
                command: Command::Clear,
                by,
            });
        }
        if and_reset && self.machine.check(Command::Reset).is_ok() {
            self.feed(MachineInput::Command {
                command: Command::Reset,
                by,
            });
        }
    }

    /// Ends the running job as `running` and the queued ones as `queued`, both with `reason`.
    fn close_jobs(&mut self, running: JobStatus, queued: JobStatus, reason: &str) {
        if self.running.is_some() {
            self.finish(running, Some(reason));
        }
        for spec in std::mem::take(&mut self.queue) {
            self.end_unstarted(spec.id, queued, reason);
        }
    }

    /// Passes an input to the machine; reports its transitions and new counters.
    fn feed(&mut self, input: MachineInput) {
        // Every change of the counters changes one of these two.
        let tally = |m: &Machine| (m.counters().processed, m.counters().estops);
        let counted_before = tally(&self.machine);
        let transitions = match self.machine.step(input) {
            Ok(transitions) => transitions,
            Err(not_now) => {
                tracing::warn!(%not_now, "a machine command came in a state that does not take it");
                return;
            }
        };
        if transitions.is_empty() && tally(&self.machine) == counted_before {
            return;
        }
        let machine = self.machine.status();
        for transition in &transitions {
            tracing::info!(from = transition.from.name(), to = transition.to.name(), cause = %transition.cause, "machine state");
        }
        self.status.send_modify(|s| s.machine = machine.clone());
        (self.sink)(CellEvent::Machine(Box::new(MachineUpdate {
            transitions,
            machine,
        })));
    }

    fn start_next(&mut self) {
        while let Some(spec) = self.queue.pop_front() {
            (self.sink)(CellEvent::JobStarted { job_id: spec.id });
            let now = self.now_s();
            self.job_started_s = now;
            self.feed(MachineInput::JobStarted);
            match JobRun::start(
                &spec,
                &self.cell,
                self.backend.as_mut(),
                self.settings.limits,
                now,
            ) {
                Ok(run) => {
                    self.running = Some(run);
                    return;
                }
                Err(end) => self.job_ended(spec.id, end),
            }
        }
    }

    fn step(&mut self) {
        let clock = self.clock();
        let Some(run) = self.running.as_mut() else {
            return;
        };
        let report = run.step(self.backend.as_mut(), &clock);
        let fresh = run.observation().measurement_fresh;
        if let Some(record) = report.record {
            (self.sink)(CellEvent::Step(Box::new(record)));
        }
        if let Some(end) = report.end {
            let job_id = run.id;
            self.running = None;
            self.job_ended(job_id, end);
        } else {
            self.feed(MachineInput::CameraFresh(fresh));
        }
    }

    /// Settles the running job's last move (storing its step); ends the job if that step did.
    fn settle_running(&mut self) {
        let clock = self.clock();
        let Some(run) = self.running.as_mut() else {
            return;
        };
        let (record, end) = run.settle(self.backend.as_mut(), &clock);
        if let Some(record) = record {
            (self.sink)(CellEvent::Step(Box::new(record)));
        }
        if let Some(end) = end {
            self.backend.hold();
            let job_id = run.id;
            self.running = None;
            self.job_ended(job_id, end);
        }
    }

    /// Ends the running job with `status`. The move it sent last is settled first, so every
    /// move the robot made is stored; `status` stands whatever that move's result.
    fn finish(&mut self, status: JobStatus, reason: Option<&str>) {
        if let Some(mut run) = self.running.take() {
            let clock = self.clock();
            let (record, _) = run.settle(self.backend.as_mut(), &clock);
            if let Some(record) = record {
                (self.sink)(CellEvent::Step(Box::new(record)));
            }
            let end = run.end(status, reason);
            self.job_ended(run.id, end);
        }
    }

    fn end_unstarted(&mut self, job_id: i64, status: JobStatus, reason: &str) {
        self.job_ended(job_id, JobEnd::unstarted(status, reason));
    }

    /// Reports a job's end and counts it.
    fn job_ended(&mut self, job_id: i64, end: JobEnd) {
        let cycle_time_s = self.now_s() - self.job_started_s;
        let more_queued = !self.queue.is_empty();
        // Counted first, so that whoever reads the status on the end's event finds it counted.
        self.feed(MachineInput::JobEnded {
            end: &end,
            cycle_time_s,
            more_queued,
        });
        (self.sink)(CellEvent::JobEnded { job_id, end });
    }

    fn shutdown(&mut self, reply: Option<oneshot::Sender<()>>) {
        self.backend.hold();
        self.close_jobs(JobStatus::Interrupted, JobStatus::Interrupted, "shutdown");
        self.publish();
        if let Some(reply) = reply {
            let _ = reply.send(());
        }
    }

    fn send_latches(&mut self) {
        let status = self.status.borrow();
        let event = CellEvent::Latches {
            estop_latched: status.estop_latched,
            driver_latch: status.driver_latch.clone(),
        };
        drop(status);
        (self.sink)(event);
    }

    /// Takes the backend's latch into the status; whether it changed. A new latch aborts the
    /// machine (the driver holds the robot itself).
    fn take_driver_latch(&mut self) -> bool {
        let driver_latch = self.backend.latch();
        if driver_latch == self.status.borrow().driver_latch {
            return false;
        }
        if let Some(latch) = &driver_latch {
            tracing::warn!(
                code = latch.code,
                reason = latch.reason,
                "the driver latched"
            );
            self.feed(MachineInput::DriverLatched {
                code: &latch.code,
                reason: &latch.reason,
            });
            self.feed(MachineInput::Done);
        }
        self.status
            .send_modify(|status| status.driver_latch = driver_latch);
        true
    }

    fn publish(&mut self) {
        if self.take_driver_latch() {
            self.send_latches();
        }
        let current_job = self.running.as_ref().map(|r| r.id);
        let queue: Vec<i64> = self.queue.iter().map(|s| s.id).collect();
        let last_pose = self.running.as_ref().map(|r| {
            let s = r.observation().state;
            LastPose {
                position_mm: [s[6], s[7], s[8]],
                orientation_deg: [s[9], s[10], s[11]],
            }
        });
        let job = self.running.as_ref().map(|r| {
            let observation = r.observation();
            let s = observation.state;
            JobProgress {
                id: r.id,
                controller: r.controller_name().to_string(),
                step: r.steps(),
                pose_error_mm: (s[6] * s[6] + s[7] * s[7] + s[8] * s[8]).sqrt(),
                sigma_mm: StepUncertainty::of(&observation.estimate).sd_lateral_mm,
            }
        });
        self.status.send_if_modified(|status| {
            let changed = status.current_job != current_job
                || status.queue != queue
                || status.job != job
                || (last_pose.is_some() && status.last_pose != last_pose);
            status.current_job = current_job;
            status.queue = queue;
            status.job = job;
            if last_pose.is_some() {
                status.last_pose = last_pose;
            }
            changed
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::backend::TwinBackend;

    fn start(sink: Box<dyn FnMut(CellEvent) + Send>) -> (CellHandle, std::thread::JoinHandle<()>) {
        let cell = CellConfig::reference();
        let settings = LoopSettings {
            period: None,
            limits: SafetyLimits {
                deadline_s: 1.0,
                max_stale_steps: 4,
            },
            estop_latched: false,
            counters: Counters::default(),
            cpu: None,
        };
        spawn(
            cell.clone(),
            Box::new(TwinBackend::new(&cell, None)),
            settings,
            sink,
        )
    }

    fn estop() -> CellCommand {
        CellCommand::EStop {
            by: "test".into(),
            reply: oneshot::channel().0,
        }
    }

    /// The storage writer's report ends the running job at once, with the steps it took, and
    /// cancels the queue; the robot takes no step after it.
    #[test]
    fn a_job_whose_steps_cannot_be_stored_fails_storage_failed() {
        use super::super::job::ControllerSource;
        use crate::sim::InitialConditions;
        let cell = CellConfig::reference();
        let settings = LoopSettings {
            period: Some(Duration::from_millis(20)),
            limits: SafetyLimits {
                deadline_s: 5.0,
                max_stale_steps: 4,
            },
            estop_latched: false,
            counters: Counters::default(),
            cpu: None,
        };
        let (events, inbox) = mpsc::channel();
        let (handle, thread) = spawn(
            cell.clone(),
            Box::new(TwinBackend::new(&cell, None)),
            settings,
            Box::new(move |event| {
                let _ = events.send(event);
            }),
        );
        for id in [1, 2] {
            let spec = JobSpec {
                id,
                controller: ControllerSource::Builtin("expert".into()),
                seed: 7,
                initial: InitialConditions::from_cell(&cell),
                demonstration: false,
            };
            handle.send(CellCommand::Enqueue(spec)).unwrap();
        }
        let mut steps = 0;
        while steps < 3 {
            if let CellEvent::Step(record) = inbox.recv().unwrap() {
                assert_eq!(record.job_id, 1);
                steps += 1;
            }
        }
        handle
            .send(CellCommand::StorageFailed { job_id: 1 })
            .unwrap();
        let mut ends = Vec::new();
        while ends.len() < 2 {
            match inbox.recv().unwrap() {
                CellEvent::Step(record) => {
                    assert_eq!(record.job_id, 1);
                    steps += 1;
                }
                CellEvent::JobEnded { job_id, end } => ends.push((job_id, end)),
                CellEvent::Machine(_) => {}
                other => panic!("unexpected {other:?}"),
            }
        }
        assert_eq!(ends[0].0, 1);
        assert_eq!(ends[0].1.status, JobStatus::Failed);
        assert_eq!(ends[0].1.failure_reason.as_deref(), Some("storage_failed"));
        assert_eq!(
            ends[0].1.steps, steps,
            "the end counts every step sent before it"
        );
        assert_eq!(ends[1].0, 2);
        assert_eq!(ends[1].1.status, JobStatus::Cancelled);
        assert_eq!(ends[1].1.failure_reason.as_deref(), Some("storage_failed"));
        let (reply, _answer) = oneshot::channel();
        handle.send(CellCommand::Shutdown { reply }).unwrap();
        thread.join().unwrap();
        assert!(inbox.try_iter().all(|e| !matches!(e, CellEvent::Step(_))));
    }

    /// A reset in two halves clears the e-stop only when no press came between them.
    #[test]
    fn an_estop_during_a_reset_keeps_the_latch() {
        let (handle, thread) = start(Box::new(|_| {}));
        let ask = |command: fn(oneshot::Sender<Result<u64, String>>) -> CellCommand| {
            let (reply, answer) = oneshot::channel();
            handle.send(command(reply)).unwrap();
            answer.blocking_recv().unwrap()
        };
        let clear = |presses| {
            let (reply, answer) = oneshot::channel();
            handle
                .send(CellCommand::ClearEStop {
                    presses,
                    and_reset: true,
                    by: "test".into(),
                    reply,
                })
                .unwrap();
            answer.blocking_recv().unwrap()
        };
        handle.send(estop()).unwrap();
        let presses = ask(|reply| CellCommand::ResetHardware { reply }).unwrap();
        assert!(
            handle.status().estop_latched,
            "the first half keeps the latch"
        );
        handle.send(estop()).unwrap();
        assert!(!clear(presses), "pressed since: stays latched");
        let presses = ask(|reply| CellCommand::ResetHardware { reply }).unwrap();
        assert!(clear(presses));
        // Its answer comes after the status changed.
        assert!(!handle.status().estop_latched);
        let (reply, _answer) = oneshot::channel();
        handle.send(CellCommand::Shutdown { reply }).unwrap();
        thread.join().unwrap();
    }

    #[test]
    fn a_handle_knows_when_its_thread_has_ended() {
        let (handle, thread) = start(Box::new(|_| {}));
        assert!(handle.is_running());
        let (reply, _answer) = oneshot::channel();
        handle.send(CellCommand::Shutdown { reply }).unwrap();
        thread.join().unwrap();
        assert!(!handle.is_running());
        assert!(handle.send(estop()).is_err());
    }

    #[test]
    fn a_handle_knows_when_its_thread_has_panicked() {
        let (handle, thread) = start(Box::new(|event| panic!("a sink that fails on {event:?}")));
        handle.send(estop()).unwrap();
        assert!(thread.join().is_err(), "the sink's panic ends the thread");
        assert!(!handle.is_running());
        assert!(handle.send(estop()).is_err());
    }
}
