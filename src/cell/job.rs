//! One job's run as a pure core: `step(backend, clock) -> StepReport`.
//!
//! Each tick first settles the move sent at the last tick (camera ingestion has had the control
//! period to estimate its capture) and judges it: the episode's own outcome, a missed deadline,
//! or too many steps without a fresh camera frame. Then it asks the controller for the next
//! move, refuses a non-finite one before the robot sees it, and has the backend supervise and
//! execute it. The thread shell in `task` owns the clock and the robot; this file owns the
//! rules.

use super::backend::CellBackend;
use crate::config::cell::CellConfig;
use crate::learning::demos::DemoStep;
use crate::policy::learned::{LearnedPolicy, LearnedPolicyFile};
use crate::policy::shield::RuleSet;
use crate::policy::{self, Actor, Controller, Decision};
use crate::sim::{InitialConditions, Observation, Outcome, PoseErrors, RewardTerms};
use serde::Serialize;

/// Where a job's controller comes from; built on the control thread when the job starts.
#[derive(Debug, Clone)]
pub enum ControllerSource {
    /// A built-in controller or bundled policy by name (`expert`, `hierarchical`, ...).
    Builtin(String),
    /// A registered policy file.
    Policy { id: i64, bytes: Vec<u8> },
}

impl ControllerSource {
    pub fn build(&self, cell: &CellConfig) -> Result<Box<dyn Controller>, String> {
        match self {
            ControllerSource::Builtin(name) => {
                policy::builtin(name, cell).map_err(|e| e.to_string())
            }
            ControllerSource::Policy { id, bytes } => {
                let file = LearnedPolicyFile::from_bytes(bytes)
                    .map_err(|e| format!("policy {id}: {e}"))?;
                let policy = LearnedPolicy::from_file(&file)
                    .map_err(|e| format!("policy {id}: {e}"))?
                    .with_rules(&cell.rules);
                Ok(Box::new(policy.with_name(format!("policy:{id}"))))
            }
        }
    }
}

/// A job as the control thread receives it.
#[derive(Debug, Clone)]
pub struct JobSpec {
    pub id: i64,
    pub controller: ControllerSource,
    pub seed: u64,
    pub initial: InitialConditions,
    /// Record the run as a demonstration (kept when the job succeeds).
    pub demonstration: bool,
}

/// A job's lifecycle state, as stored and served.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
    Interrupted,
}

impl JobStatus {
    pub const ALL: [JobStatus; 6] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Cancelled,
        JobStatus::Interrupted,
    ];

    pub fn as_str(&self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
            JobStatus::Interrupted => "interrupted",
        }
    }

    pub fn parse(text: &str) -> Option<JobStatus> {
        Self::ALL.into_iter().find(|s| s.as_str() == text)
    }

    pub fn is_final(&self) -> bool {
        !matches!(self, JobStatus::Queued | JobStatus::Running)
    }
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobEnd {
    pub status: JobStatus,
    /// `estop`, `cancelled`, `missed_deadline`, `stale_camera`, `nan_action`, an episode
    /// failure code (`contact`, `collision_limit`, ...), `storage_failed` (its steps could not
    /// be stored) or `shutdown`; none on success.
    pub failure_reason: Option<String>,
    pub steps: u32,
    pub reward: f64,
    pub final_errors: Option<PoseErrors>,
    /// What the controller saw and did at each labelled step, for a demonstration job that
    /// succeeded.
    #[serde(skip)]
    pub demonstration: Option<Vec<DemoStep>>,
}

impl JobEnd {
    /// The end of a job that never took a step.
    pub fn unstarted(status: JobStatus, reason: &str) -> JobEnd {
        JobEnd {
            status,
            failure_reason: Some(reason.to_string()),
            steps: 0,
            reward: 0.0,
            final_errors: None,
            demonstration: None,
        }
    }
}

/// The control loop's own stop rules (docs/design.md §8).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SafetyLimits {
    /// Longest a step's decision, supervision and execution may take beyond its move's own
    /// time at the robot's speeds, s.
    pub deadline_s: f64,
    /// Steps in a row without a fresh camera frame before the job stops.
    pub max_stale_steps: u32,
}

/// One control step as stored and streamed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepRecord {
    pub job_id: i64,
    pub step: u32,
    /// Time since the job started, s.
    pub t_s: f64,
    /// The 12-dim state after the step (docs/design.md §5).
    pub state: [f64; 12],
    /// The commanded move `[Δx, Δy, Δz, θx, θy, θz]`, mm and deg.
    pub action: [f64; 6],
    /// The controller's own proposal, in the same units, before the shield's rules shaped it
    /// into `action` (none for a controller without rules: the expert, the baselines).
    pub proposed: Option<[f64; 6]>,
    /// The rules that changed the proposal, in pipeline order (empty where none did).
    pub rules: RuleSet,
    pub actor: Option<Actor>,
    pub scale: Option<f64>,
    pub legs_mm: [f64; 6],
    /// `allowed` or `vetoed` by the supervisor.
    pub verdict: &'static str,
    pub veto_reason: Option<String>,
    pub reward: RewardTerms,
    /// Decision + supervision + execution time of this step, µs. Camera ingestion runs on its
    /// own thread while the control thread waits for the next period, so its time is not here.
    pub compute_us: f64,
    /// How sure the cell was of the state after the step.
    pub uncertainty: StepUncertainty,
    /// A fault the cell noticed at this step (`occlusion`, `out_of_order`, `robot_lag`,
    /// `camera_shift`, `camera_shift_suspected`, `frozen_camera`, `robot_short`).
    pub detected: Option<String>,
}

/// How sure the cell was of its state estimate (docs/estimation.md).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, utoipa::ToSchema)]
pub struct StepUncertainty {
    /// σ of the sideways position of {F} in {M}, its worst direction (mm).
    pub sd_lateral_mm: f64,
    /// σ of the position along the shaft's axis (mm).
    pub sd_axial_mm: f64,
    /// σ of the tilt, its worst direction (deg).
    pub sd_tilt_deg: f64,
    /// The camera's point noise as a multiple of its data sheet, as learned from the fits.
    pub noise_scale: f64,
}

impl StepUncertainty {
    pub fn of(estimate: &crate::camera::StateFilter) -> Self {
        let sd = estimate.sd();
        StepUncertainty {
            sd_lateral_mm: sd.lateral_mm,
            sd_axial_mm: sd.axial_mm,
            sd_tilt_deg: sd.tilt_rad.to_degrees(),
            noise_scale: estimate.noise_scale(),
        }
    }
}

/// What one call of [`JobRun::step`] produced.
#[derive(Debug, Clone, PartialEq)]
pub struct StepReport {
    /// The step settled at this tick (none at a job's first tick).
    pub record: Option<StepRecord>,
    pub end: Option<JobEnd>,
}

/// A move sent to the robot and not yet settled.
struct PendingStep {
    decision: Decision,
    /// Decision + supervision + execution time, s.
    compute_s: f64,
}

/// A running job: its controller, the latest observation and its counters.
pub struct JobRun {
    pub id: i64,
    controller: Box<dyn Controller>,
    limits: SafetyLimits,
    observation: Observation,
    started_s: f64,
    steps: u32,
    stale_steps: u32,
    reward: f64,
    last_errors: Option<PoseErrors>,
    /// The labelled steps so far, when the job records a demonstration.
    demonstration: Option<Vec<DemoStep>>,
    pending: Option<PendingStep>,
}

impl JobRun {
    /// Builds the controller and brings the cell to the episode's start. `now_s` is the
    /// shell's monotonic clock.
    pub fn start(
        spec: &JobSpec,
        cell: &CellConfig,
        backend: &mut dyn CellBackend,
        limits: SafetyLimits,
        now_s: f64,
    ) -> Result<JobRun, JobEnd> {
        let refuse = |reason: String| JobEnd::unstarted(JobStatus::Failed, &reason);
        let mut controller = spec
            .controller
            .build(cell)
            .map_err(|e| refuse(format!("controller: {e}")))?;
        controller.reset(spec.seed ^ 0x5EED_C0DE);
        let observation = backend
            .start(spec.seed, spec.initial)
            .map_err(|e| refuse(format!("start: {e}")))?;
        Ok(JobRun {
            id: spec.id,
            controller,
            limits,
            observation,
            started_s: now_s,
            steps: 0,
            stale_steps: 0,
            reward: 0.0,
            last_errors: None,
            demonstration: spec.demonstration.then(Vec::new),
            pending: None,
        })
    }

    /// The latest observation (the cell's estimate of the relative pose).
    pub fn observation(&self) -> &Observation {
        &self.observation
    }

    /// The controller's name (a built-in's, a bundled policy's or `policy:<id>`).
    pub fn controller_name(&self) -> &str {
        self.controller.name()
    }

    /// Steps settled so far.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// One control tick: settles the last move, then (unless that ended the job) decides and
    /// sends the next. `clock` is the shell's monotonic clock in seconds, read around the work
    /// to time it.
    pub fn step(&mut self, backend: &mut dyn CellBackend, clock: &dyn Fn() -> f64) -> StepReport {
        let (record, end) = self.settle(backend, clock);
        if end.is_some() {
            backend.hold();
            return StepReport { record, end };
        }
        let begin_s = clock();
        let decision = self.controller.act(&self.observation);
        if let (Some(steps), Some(actor), Some(scale)) =
            (self.demonstration.as_mut(), decision.actor, decision.scale)
        {
            steps.push(DemoStep {
                episode: 0,
                step: self.observation.step,
                state: self.observation.state,
                action: decision.action.to_array(),
                actor,
                scale,
            });
        }
        let refusal = if !decision.action.is_finite() {
            Some("nan_action".to_string())
        } else {
            backend
                .act(&decision.action)
                .err()
                .map(|error| format!("backend: {error}"))
        };
        if let Some(reason) = refusal {
            backend.hold();
            let end = self.end(JobStatus::Failed, Some(&reason));
            return StepReport {
                record,
                end: Some(end),
            };
        }
        self.pending = Some(PendingStep {
            decision,
            compute_s: clock() - begin_s,
        });
        StepReport { record, end: None }
    }

    /// Settles the move sent last, if any: its record, and the job's end if the step ends it.
    /// The shell calls this before ending a job from outside, so a move the robot made is
    /// always stored.
    pub fn settle(
        &mut self,
        backend: &mut dyn CellBackend,
        clock: &dyn Fn() -> f64,
    ) -> (Option<StepRecord>, Option<JobEnd>) {
        let Some(pending) = self.pending.take() else {
            return (None, None);
        };
        let result = match backend.settle() {
            Ok(result) => result,
            Err(error) => {
                let end = self.end(JobStatus::Failed, Some(&format!("backend: {error}")));
                return (None, Some(end));
            }
        };
        let compute_s = pending.compute_s;
        self.steps += 1;
        self.reward += result.reward.total;
        self.last_errors = Some(result.true_errors);
        self.stale_steps = if result.observation.measurement_fresh {
            0
        } else {
            self.stale_steps + 1
        };
        let decision = pending.decision;
        let record = StepRecord {
            job_id: self.id,
            step: self.steps,
            t_s: clock() - self.started_s,
            state: result.observation.state,
            action: decision.action.to_array(),
            proposed: decision.shield.map(|trace| trace.proposed.to_array()),
            rules: decision.shield.map(|trace| trace.fired).unwrap_or_default(),
            actor: decision.actor,
            scale: decision.scale,
            legs_mm: result.legs_mm,
            verdict: if result.veto.is_some() {
                "vetoed"
            } else {
                "allowed"
            },
            veto_reason: result.veto.as_ref().map(|v| v.code().to_string()),
            reward: result.reward,
            compute_us: compute_s * 1e6,
            uncertainty: StepUncertainty::of(&result.observation.estimate),
            detected: result.detected.map(str::to_string),
        };
        let state_finite = result.observation.state.iter().all(|v| v.is_finite());
        self.observation = result.observation;
        let end = match result.outcome {
            Some(Outcome::Success) => Some(self.end(JobStatus::Succeeded, None)),
            Some(Outcome::Failure(reason)) => {
                Some(self.end(JobStatus::Failed, Some(reason.code())))
            }
            None if !state_finite => Some(self.end(JobStatus::Failed, Some("nan_state"))),
            None if compute_s > self.limits.deadline_s + result.move_time_s => {
                Some(self.end(JobStatus::Failed, Some("missed_deadline")))
            }
            None if self.stale_steps > self.limits.max_stale_steps => {
                Some(self.end(JobStatus::Failed, Some("stale_camera")))
            }
            None => None,
        };
        (Some(record), end)
    }

    /// Ends the job from outside (cancel, e-stop, shutdown) with what it has done so far.
    pub fn end(&self, status: JobStatus, reason: Option<&str>) -> JobEnd {
        JobEnd {
            status,
            failure_reason: reason.map(str::to_string),
            steps: self.steps,
            reward: self.reward,
            final_errors: self.last_errors,
            demonstration: self
                .demonstration
                .clone()
                .filter(|_| status == JobStatus::Succeeded),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::backend::TwinBackend;
    use crate::policy::Decision;
    use crate::policy::eval::run_episode;
    use crate::sim::AssemblyEnv;
    use std::cell::Cell;

    fn spec(controller: &str, seed: u64) -> JobSpec {
        let cell = CellConfig::reference();
        JobSpec {
            id: 7,
            controller: ControllerSource::Builtin(controller.into()),
            seed,
            initial: InitialConditions::from_cell(&cell),
            demonstration: false,
        }
    }

    const GENEROUS: SafetyLimits = SafetyLimits {
        deadline_s: 10.0,
        max_stale_steps: 4,
    };

    fn run_to_end(run: &mut JobRun, backend: &mut TwinBackend) -> (Vec<StepRecord>, JobEnd) {
        let mut records = Vec::new();
        loop {
            let report = run.step(backend, &|| 0.0);
            records.extend(report.record);
            if let Some(end) = report.end {
                return (records, end);
            }
        }
    }

    #[test]
    fn a_job_is_the_same_episode_as_eval_runs() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let mut run = JobRun::start(&spec("expert", 11), &cell, &mut backend, GENEROUS, 0.0)
            .unwrap_or_else(|e| panic!("{e:?}"));
        let (records, end) = run_to_end(&mut run, &mut backend);

        let mut env = AssemblyEnv::new(&cell, TwinBackend::options(&cell));
        let mut expert = policy::builtin("expert", &cell).unwrap();
        let reference = run_episode(&mut env, expert.as_mut(), 0, 11);
        assert_eq!(end.steps, reference.steps);
        assert_eq!(records.len(), reference.steps as usize);
        assert_eq!(end.status == JobStatus::Succeeded, reference.succeeded());
        assert!((end.reward - reference.reward).abs() < 1e-9);
        assert_eq!(records.last().unwrap().step, end.steps);
    }

    #[test]
    fn a_move_sent_before_the_job_is_ended_from_outside_is_still_recorded() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let mut run = JobRun::start(&spec("expert", 2), &cell, &mut backend, GENEROUS, 0.0)
            .unwrap_or_else(|e| panic!("{e:?}"));
        assert_eq!(
            run.step(&mut backend, &|| 0.0).record,
            None,
            "nothing to settle yet"
        );
        let first = run
            .step(&mut backend, &|| 0.0)
            .record
            .expect("the first move settled");
        // A cancel arrives with the second move sent: the shell settles it, then ends the job.
        let (second, end) = run.settle(&mut backend, &|| 0.0);
        assert_eq!(end, None);
        assert_eq!((first.step, second.map(|r| r.step)), (1, Some(2)));
        assert_eq!(run.end(JobStatus::Cancelled, Some("cancelled")).steps, 2);
        assert_eq!(
            run.settle(&mut backend, &|| 0.0),
            (None, None),
            "nothing left"
        );
    }

    #[test]
    fn the_twin_backend_never_waits_for_an_estimate_it_was_not_sent() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let initial = InitialConditions::from_cell(&cell);
        let error = backend.settle().unwrap_err();
        assert!(
            error.to_string().contains("settle without a move"),
            "{error}"
        );
        // A move left unsettled does not leak its estimate into the next episode.
        backend.start(8, initial).unwrap();
        backend.act(&crate::geometry::Move::default()).unwrap();
        let fresh_start = backend.start(9, initial).unwrap();
        // The twin the same way, but each move settled: its robot and what the cell remembers
        // of it are the same.
        let mut env = AssemblyEnv::new(&cell, TwinBackend::options(&cell));
        env.reset_with(8, initial).unwrap();
        env.step(&crate::geometry::Move::default()).unwrap();
        assert_eq!(fresh_start, env.reset_with(9, initial).unwrap());
    }

    /// A controller that answers NaN after a few moves.
    struct Faulty(u32);
    impl Controller for Faulty {
        fn name(&self) -> &str {
            "faulty"
        }
        fn reset(&mut self, _seed: u64) {}
        fn act(&mut self, _observation: &Observation) -> Decision {
            self.0 += 1;
            let value = if self.0 > 3 { f64::NAN } else { 0.0 };
            Decision::plain(crate::geometry::Move::translation(value, 0.0, 0.0))
        }
    }

    #[test]
    fn a_nan_move_never_reaches_the_robot() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let mut run = JobRun::start(&spec("expert", 1), &cell, &mut backend, GENEROUS, 0.0)
            .unwrap_or_else(|e| panic!("{e:?}"));
        run.controller = Box::new(Faulty(0));
        let (records, end) = run_to_end(&mut run, &mut backend);
        assert_eq!(
            records.len(),
            3,
            "three finite holds, then the NaN is refused"
        );
        assert_eq!(end.failure_reason.as_deref(), Some("nan_action"));
        assert_eq!(end.steps, 3);
    }

    #[test]
    fn a_slow_step_misses_its_deadline() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let limits = SafetyLimits {
            deadline_s: 0.05,
            ..GENEROUS
        };
        let mut run = JobRun::start(&spec("expert", 1), &cell, &mut backend, limits, 0.0)
            .unwrap_or_else(|e| panic!("{e:?}"));
        // A clock that advances 0.1 s per reading: every step takes 0.1 s > 0.05 s.
        let now = Cell::new(0.0);
        let clock = || {
            now.set(now.get() + 0.1);
            now.get()
        };
        // The first tick decides and sends a move in 0.1 s; the second settles it and ends the
        // job.
        assert_eq!(run.step(&mut backend, &clock).end, None);
        let report = run.step(&mut backend, &clock);
        let end = report.end.expect("settling the slow step ends the job");
        assert_eq!(end.failure_reason.as_deref(), Some("missed_deadline"));
        assert_eq!(end.steps, 1);
        assert!((report.record.unwrap().compute_us - 1e5).abs() < 1e-6);
    }

    #[test]
    fn blind_steps_stop_the_job() {
        let mut cell = CellConfig::reference();
        cell.camera.dropout_probability = 1.0;
        let mut backend = TwinBackend::new(&cell, None);
        let limits = SafetyLimits {
            max_stale_steps: 2,
            ..GENEROUS
        };
        let mut run = JobRun::start(&spec("expert", 3), &cell, &mut backend, limits, 0.0)
            .unwrap_or_else(|e| panic!("{e:?}"));
        let (records, end) = run_to_end(&mut run, &mut backend);
        assert_eq!(end.failure_reason.as_deref(), Some("stale_camera"));
        assert_eq!(
            records.len(),
            3,
            "the third blind step in a row is one too many"
        );
    }

    #[test]
    fn an_unknown_policy_file_fails_at_start_with_its_reason() {
        let cell = CellConfig::reference();
        let mut backend = TwinBackend::new(&cell, None);
        let bad = JobSpec {
            controller: ControllerSource::Policy {
                id: 3,
                bytes: b"not safetensors".to_vec(),
            },
            ..spec("expert", 1)
        };
        let end = match JobRun::start(&bad, &cell, &mut backend, GENEROUS, 0.0) {
            Ok(_) => panic!("a broken policy must not start"),
            Err(end) => end,
        };
        assert_eq!(end.status, JobStatus::Failed);
        assert!(end.failure_reason.unwrap().contains("policy 3"));
    }
}
