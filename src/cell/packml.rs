//! The cell's machine state as a plant knows it: the PackML state model (ISA-TR88.00.02,
//! OPC 30050), its stop reason and its production counters.
//!
//! A pure core: the control thread feeds it what happened (a job queued, started, ended; the
//! camera fresh or stale; an e-stop, a driver latch) and what an operator commanded (stop,
//! hold, unhold, clear, reset), and gets back the transitions it made, which the thread
//! reports and the storage writer records. The cell's own behaviour does not depend on it
//! except where a state refuses work (a new job while Stopped or Aborted): the e-stop holds
//! and latches exactly as before, and the states describe it. Docs: docs/opcua.md.

use super::job::{JobEnd, JobStatus};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The PackML states, numbered as ISA-TR88 numbers them (OPC 30050's `StateCurrent`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub enum PackMlState {
    Clearing = 1,
    Stopped = 2,
    Starting = 3,
    Idle = 4,
    Suspended = 5,
    Execute = 6,
    Stopping = 7,
    Aborting = 8,
    Aborted = 9,
    Holding = 10,
    Held = 11,
    Unholding = 12,
    Suspending = 13,
    Unsuspending = 14,
    Resetting = 15,
    Completing = 16,
    Complete = 17,
}

impl PackMlState {
    pub fn number(self) -> u32 {
        self as u32
    }

    pub fn name(self) -> &'static str {
        use PackMlState::*;
        match self {
            Clearing => "Clearing",
            Stopped => "Stopped",
            Starting => "Starting",
            Idle => "Idle",
            Suspended => "Suspended",
            Execute => "Execute",
            Stopping => "Stopping",
            Aborting => "Aborting",
            Aborted => "Aborted",
            Holding => "Holding",
            Held => "Held",
            Unholding => "Unholding",
            Suspending => "Suspending",
            Unsuspending => "Unsuspending",
            Resetting => "Resetting",
            Completing => "Completing",
            Complete => "Complete",
        }
    }

    /// Whether a new job may be queued: the cell is ready (Idle, or Complete, which a new job
    /// resets) or producing already, held or not (it waits its turn). Not while it stops or
    /// aborts, nor once stopped or aborted, until a reset.
    pub fn accepts_jobs(self) -> bool {
        use PackMlState::*;
        !matches!(
            self,
            Clearing | Stopping | Stopped | Aborting | Aborted | Resetting
        )
    }

    /// The state an acting state moves to once its action is done (its "state complete").
    fn completes_to(self) -> Option<PackMlState> {
        use PackMlState::*;
        Some(match self {
            Clearing => Stopped,
            Stopping => Stopped,
            Aborting => Aborted,
            Holding => Held,
            Unholding => Execute,
            Suspending => Suspended,
            Unsuspending => Execute,
            Resetting => Idle,
            Completing => Complete,
            Starting => Execute,
            _ => return None,
        })
    }
}

/// PackML unit modes; the cell has one.
pub const UNIT_MODE: (&str, u32) = ("Production", 1);

/// Why the cell last stopped or aborted; kept until the next stop or abort.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StopReason {
    /// `estop`, `stop`, or the driver latch's code.
    pub code: String,
    /// A number for PLCs (OPC 30050 `StopReason.ID`): 1 e-stop, 2 driver latch, 3 stop.
    pub id: i32,
    pub message: String,
}

impl StopReason {
    pub fn estop(message: String) -> StopReason {
        StopReason {
            code: "estop".into(),
            id: 1,
            message,
        }
    }

    pub fn driver_latch(code: &str, reason: &str) -> StopReason {
        StopReason {
            code: code.to_string(),
            id: 2,
            message: format!("the robot driver latched: {reason}"),
        }
    }

    pub fn stop(by: &str) -> StopReason {
        StopReason {
            code: "stop".into(),
            id: 3,
            message: format!("stopped by {by}"),
        }
    }
}

/// Production counters, kept across restarts (OPC 30050 `Admin`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Counters {
    /// Parts the robot moved: jobs that took at least one step (`ProdProcessedCount`).
    pub processed: u64,
    /// Processed parts whose job succeeded.
    pub good: u64,
    /// Processed parts whose job did not succeed (`ProdDefectiveCount`).
    pub defective: u64,
    /// `defective` by the job's failure reason (`contact`, `estop`, `cancelled`, ...).
    pub defective_by_reason: BTreeMap<String, u64>,
    /// E-stop presses.
    pub estops: u64,
    /// Cycle time of the last good part, s: from the job's start on the robot to its end.
    pub last_cycle_time_s: Option<f64>,
    /// Sum of the good parts' cycle times, s (their mean is this over `good`).
    pub total_cycle_time_s: f64,
    pub min_cycle_time_s: Option<f64>,
    pub max_cycle_time_s: Option<f64>,
}

impl Counters {
    /// Counts a job's end; `cycle_time_s` is its time on the robot.
    pub fn count(&mut self, end: &JobEnd, cycle_time_s: f64) {
        if end.steps == 0 && end.status != JobStatus::Succeeded {
            return;
        }
        self.processed += 1;
        if end.status == JobStatus::Succeeded {
            self.good += 1;
            self.last_cycle_time_s = Some(cycle_time_s);
            self.total_cycle_time_s += cycle_time_s;
            self.min_cycle_time_s = Some(
                self.min_cycle_time_s
                    .map_or(cycle_time_s, |m| m.min(cycle_time_s)),
            );
            self.max_cycle_time_s = Some(
                self.max_cycle_time_s
                    .map_or(cycle_time_s, |m| m.max(cycle_time_s)),
            );
        } else {
            self.defective += 1;
            let reason = end
                .failure_reason
                .clone()
                .unwrap_or_else(|| end.status.as_str().to_string());
            *self.defective_by_reason.entry(reason).or_default() += 1;
        }
    }

    pub fn mean_cycle_time_s(&self) -> Option<f64> {
        (self.good > 0).then(|| self.total_cycle_time_s / self.good as f64)
    }
}

/// The machine as `GET /api/cell` shows it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct MachineStatus {
    pub state: PackMlState,
    /// The state's ISA-TR88 number.
    pub state_number: u32,
    pub unit_mode: &'static str,
    pub stop_reason: Option<StopReason>,
    pub counters: Counters,
}

/// One change of state and what caused it.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct Transition {
    pub from: PackMlState,
    pub to: PackMlState,
    pub cause: String,
}

/// What the control thread tells the machine.
#[derive(Debug, Clone, PartialEq)]
pub enum MachineInput<'a> {
    /// A job joined the queue.
    JobQueued,
    /// The queue's next job started on the robot.
    JobStarted,
    /// A job ended after `cycle_time_s` on the robot; `more_queued`: another waits.
    JobEnded {
        end: &'a JobEnd,
        cycle_time_s: f64,
        more_queued: bool,
    },
    /// Whether the running job's last step had a fresh camera frame.
    CameraFresh(bool),
    /// The e-stop was pressed (by whom): Aborting, until [`MachineInput::Done`].
    EStop { by: &'a str },
    /// The driver latched: Aborting, until [`MachineInput::Done`].
    DriverLatched { code: &'a str, reason: &'a str },
    /// An operator's command.
    Command { command: Command, by: &'a str },
    /// The acting state's work is done (the robot holds, the jobs are closed).
    Done,
}

/// The PackML commands an operator gives (Start is a job; Abort is the e-stop).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Command {
    Stop,
    Hold,
    Unhold,
    Clear,
    Reset,
}

impl Command {
    pub fn name(self) -> &'static str {
        match self {
            Command::Stop => "stop",
            Command::Hold => "hold",
            Command::Unhold => "unhold",
            Command::Clear => "clear",
            Command::Reset => "reset",
        }
    }

    /// The states this command is taken in (PackML's state model).
    fn valid_in(self, state: PackMlState) -> bool {
        use PackMlState::*;
        match self {
            Command::Stop => !matches!(state, Stopped | Stopping | Aborting | Aborted | Clearing),
            Command::Hold => matches!(state, Execute | Suspended),
            Command::Unhold => state == Held,
            Command::Clear => state == Aborted,
            Command::Reset => matches!(state, Stopped | Complete),
        }
    }
}

/// A command the state does not take.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("the cell is {}: {} is taken in {valid}", state.name(), command.name())]
pub struct NotNow {
    pub command: Command,
    pub state: PackMlState,
    pub valid: String,
}

/// The state machine and its counters.
#[derive(Debug, Clone)]
pub struct Machine {
    state: PackMlState,
    stop_reason: Option<StopReason>,
    counters: Counters,
}

impl Machine {
    /// A service starting up: Aborted when a latch stands from before, else Idle (its start
    /// checks are its reset).
    pub fn new(latched: Option<StopReason>, counters: Counters) -> Machine {
        Machine {
            state: if latched.is_some() {
                PackMlState::Aborted
            } else {
                PackMlState::Idle
            },
            stop_reason: latched,
            counters,
        }
    }

    pub fn state(&self) -> PackMlState {
        self.state
    }

    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    pub fn status(&self) -> MachineStatus {
        MachineStatus {
            state: self.state,
            state_number: self.state.number(),
            unit_mode: UNIT_MODE.0,
            stop_reason: self.stop_reason.clone(),
            counters: self.counters.clone(),
        }
    }

    /// Whether `command` is taken now, and why not.
    pub fn check(&self, command: Command) -> Result<(), NotNow> {
        if command.valid_in(self.state) {
            return Ok(());
        }
        use PackMlState::*;
        let all = [
            Clearing,
            Stopped,
            Starting,
            Idle,
            Suspended,
            Execute,
            Stopping,
            Aborting,
            Aborted,
            Holding,
            Held,
            Unholding,
            Suspending,
            Unsuspending,
            Resetting,
            Completing,
            Complete,
        ];
        let valid: Vec<&str> = all
            .iter()
            .filter(|s| command.valid_in(**s))
            .map(|s| s.name())
            .collect();
        Err(NotNow {
            command,
            state: self.state,
            valid: valid.join(", "),
        })
    }

    /// Takes one input; answers the transitions it made, in order (none: nothing changed
    /// state, though a job's end may have changed the counters). A command the state does not
    /// take changes nothing.
    pub fn step(&mut self, input: MachineInput) -> Result<Vec<Transition>, NotNow> {
        use PackMlState::*;
        let mut moves = Moves::new(self.state);
        match input {
            MachineInput::JobQueued => moves.begin_starting("a job was queued"),
            MachineInput::JobStarted => {
                moves.begin_starting("a job started");
                if moves.state == Starting {
                    moves.go(Execute, "a job started");
                }
            }
            MachineInput::JobEnded {
                end,
                cycle_time_s,
                more_queued,
            } => {
                self.counters.count(end, cycle_time_s);
                let producing = matches!(
                    self.state,
                    Starting | Execute | Suspending | Suspended | Unsuspending | Holding | Held
                );
                if producing && !more_queued {
                    moves.go(Completing, "the last queued job ended");
                    moves.go(Complete, "done");
                }
            }
            MachineInput::CameraFresh(fresh) => match (self.state, fresh) {
                (Execute, false) => {
                    moves.go(Suspending, "the job waits for a fresh camera frame");
                    moves.go(Suspended, "done");
                }
                (Suspended, true) => {
                    moves.go(Unsuspending, "a fresh camera frame came");
                    moves.go(Execute, "done");
                }
                _ => {}
            },
            MachineInput::EStop { by } => {
                self.counters.estops += 1;
                self.stop_reason = Some(StopReason::estop(format!("e-stop pressed by {by}")));
                if !matches!(self.state, Aborting | Aborted) {
                    moves.go(Aborting, "e-stop");
                }
            }
            MachineInput::DriverLatched { code, reason } => {
                if !matches!(self.state, Aborting | Aborted) {
                    self.stop_reason = Some(StopReason::driver_latch(code, reason));
                    moves.go(Aborting, "the robot driver latched");
                }
            }
            MachineInput::Command { command, by } => {
                self.check(command)?;
                let cause = format!("{} by {by}", command.name());
                match command {
                    Command::Stop => {
                        self.stop_reason = Some(StopReason::stop(by));
                        moves.go(Stopping, &cause);
                    }
                    Command::Hold => moves.go(Holding, &cause),
                    Command::Unhold => moves.go(Unholding, &cause),
                    Command::Clear => {
                        moves.go(Clearing, &cause);
                        moves.go(Stopped, "done");
                    }
                    Command::Reset => {
                        moves.go(Resetting, &cause);
                        moves.go(Idle, "done");
                    }
                }
            }
            MachineInput::Done => {
                if let Some(next) = self.state.completes_to()
                    && self.state != Starting
                {
                    moves.go(next, "done");
                }
            }
        }
        self.state = moves.state;
        Ok(moves.made)
    }
}

/// Transitions made while handling one input.
struct Moves {
    state: PackMlState,
    made: Vec<Transition>,
}

impl Moves {
    fn new(state: PackMlState) -> Moves {
        Moves {
            state,
            made: Vec::new(),
        }
    }

    /// From Idle to Starting; from Complete through Resetting and Idle to Starting (a new job
    /// resets a complete cell); from any other state nowhere.
    fn begin_starting(&mut self, cause: &str) {
        use PackMlState::*;
        if self.state == Complete {
            self.go(Resetting, cause);
            self.go(Idle, "reset");
        }
        if self.state == Idle {
            self.go(Starting, cause);
        }
    }

    fn go(&mut self, to: PackMlState, cause: &str) {
        self.made.push(Transition {
            from: self.state,
            to,
            cause: cause.to_string(),
        });
        self.state = to;
    }
}

#[cfg(test)]
mod tests {
    use super::PackMlState::*;
    use super::*;

    fn end(status: JobStatus, reason: Option<&str>, steps: u32) -> JobEnd {
        JobEnd {
            status,
            failure_reason: reason.map(str::to_string),
            steps,
            reward: 0.0,
            final_errors: None,
            demonstration: None,
        }
    }

    fn states(transitions: &[Transition]) -> Vec<PackMlState> {
        transitions.iter().map(|t| t.to).collect()
    }

    fn command(machine: &mut Machine, command: Command) -> Result<Vec<PackMlState>, NotNow> {
        machine
            .step(MachineInput::Command { command, by: "ana" })
            .map(|t| states(&t))
    }

    /// The cycle of OPC 30050's figure: Idle → Starting → Execute → Completing → Complete,
    /// then Reset back to Idle; counters count the part and its cycle time.
    #[test]
    fn a_job_runs_through_execute_to_complete_and_is_counted() {
        let mut machine = Machine::new(None, Counters::default());
        assert_eq!(machine.state(), Idle);
        let t = machine.step(MachineInput::JobQueued).unwrap();
        assert_eq!(states(&t), [Starting]);
        let t = machine.step(MachineInput::JobStarted).unwrap();
        assert_eq!(states(&t), [Execute]);
        let done = end(JobStatus::Succeeded, None, 12);
        let t = machine
            .step(MachineInput::JobEnded {
                end: &done,
                cycle_time_s: 2.5,
                more_queued: false,
            })
            .unwrap();
        assert_eq!(states(&t), [Completing, Complete]);
        let counters = machine.status().counters;
        assert_eq!(
            (counters.processed, counters.good, counters.defective),
            (1, 1, 0)
        );
        assert_eq!(counters.last_cycle_time_s, Some(2.5));
        assert_eq!(
            command(&mut machine, Command::Reset).unwrap(),
            [Resetting, Idle]
        );
    }

    /// Two queued jobs are one production run: the cell stays in Execute between them.
    #[test]
    fn queued_jobs_keep_the_cell_in_execute() {
        let mut machine = Machine::new(None, Counters::default());
        machine.step(MachineInput::JobQueued).unwrap();
        machine.step(MachineInput::JobQueued).unwrap();
        machine.step(MachineInput::JobStarted).unwrap();
        let failed = end(JobStatus::Failed, Some("contact"), 30);
        let t = machine
            .step(MachineInput::JobEnded {
                end: &failed,
                cycle_time_s: 9.0,
                more_queued: true,
            })
            .unwrap();
        assert!(t.is_empty());
        assert_eq!(machine.state(), Execute);
        let counters = machine.status().counters;
        assert_eq!(counters.defective_by_reason["contact"], 1);
        assert_eq!(
            counters.last_cycle_time_s, None,
            "only good parts are timed"
        );
    }

    /// A new job after Complete resets the cell on its way (no separate Reset needed).
    #[test]
    fn a_job_queued_in_complete_passes_through_resetting() {
        let mut machine = Machine::new(None, Counters::default());
        machine.step(MachineInput::JobStarted).unwrap();
        let done = end(JobStatus::Succeeded, None, 3);
        machine
            .step(MachineInput::JobEnded {
                end: &done,
                cycle_time_s: 1.0,
                more_queued: false,
            })
            .unwrap();
        let t = machine.step(MachineInput::JobQueued).unwrap();
        assert_eq!(states(&t), [Resetting, Idle, Starting]);
    }

    /// The e-stop: Aborting while the job is closed, Aborted after; Clear then Reset to Idle;
    /// Reset alone is refused, naming the states it is taken in.
    #[test]
    fn an_estop_aborts_and_clear_then_reset_bring_the_cell_back() {
        let mut machine = Machine::new(None, Counters::default());
        machine.step(MachineInput::JobStarted).unwrap();
        let t = machine.step(MachineInput::EStop { by: "ana" }).unwrap();
        assert_eq!(states(&t), [Aborting]);
        let stopped = end(JobStatus::Failed, Some("estop"), 4);
        let t = machine
            .step(MachineInput::JobEnded {
                end: &stopped,
                cycle_time_s: 0.4,
                more_queued: false,
            })
            .unwrap();
        assert!(t.is_empty(), "a job's end does not leave Aborting");
        assert_eq!(
            states(&machine.step(MachineInput::Done).unwrap()),
            [Aborted]
        );
        let status = machine.status();
        assert_eq!(status.stop_reason.unwrap().id, 1);
        assert_eq!(status.counters.estops, 1);
        assert_eq!(status.counters.defective_by_reason["estop"], 1);
        assert!(!machine.state().accepts_jobs());
        let refused = command(&mut machine, Command::Reset).unwrap_err();
        assert_eq!(refused.valid, "Stopped, Complete");
        assert_eq!(machine.state(), Aborted);
        assert_eq!(
            command(&mut machine, Command::Clear).unwrap(),
            [Clearing, Stopped]
        );
        assert!(!machine.state().accepts_jobs());
        assert_eq!(
            command(&mut machine, Command::Reset).unwrap(),
            [Resetting, Idle]
        );
    }

    /// Stop from Execute: Stopping, then Stopped once the shell has closed the jobs; a second
    /// press of the e-stop in Aborted counts but makes no transition.
    #[test]
    fn stop_and_repeated_estops() {
        let mut machine = Machine::new(None, Counters::default());
        machine.step(MachineInput::JobStarted).unwrap();
        assert_eq!(command(&mut machine, Command::Stop).unwrap(), [Stopping]);
        assert_eq!(
            states(&machine.step(MachineInput::Done).unwrap()),
            [Stopped]
        );
        assert_eq!(machine.status().stop_reason.unwrap().code, "stop");
        assert!(command(&mut machine, Command::Stop).is_err());
        machine.step(MachineInput::EStop { by: "ana" }).unwrap();
        machine.step(MachineInput::Done).unwrap();
        assert!(
            machine
                .step(MachineInput::EStop { by: "ana" })
                .unwrap()
                .is_empty()
        );
        assert_eq!(machine.status().counters.estops, 2);
    }

    /// Hold and unhold, and a stale camera suspending the job.
    #[test]
    fn hold_and_suspend() {
        let mut machine = Machine::new(None, Counters::default());
        machine.step(MachineInput::JobStarted).unwrap();
        let t = machine.step(MachineInput::CameraFresh(false)).unwrap();
        assert_eq!(states(&t), [Suspending, Suspended]);
        let t = machine.step(MachineInput::CameraFresh(true)).unwrap();
        assert_eq!(states(&t), [Unsuspending, Execute]);
        assert_eq!(command(&mut machine, Command::Hold).unwrap(), [Holding]);
        assert_eq!(states(&machine.step(MachineInput::Done).unwrap()), [Held]);
        assert!(command(&mut machine, Command::Hold).is_err());
        assert_eq!(command(&mut machine, Command::Unhold).unwrap(), [Unholding]);
        assert_eq!(
            states(&machine.step(MachineInput::Done).unwrap()),
            [Execute]
        );
    }

    /// A job that never took a step moved no part; the driver latch aborts with its code.
    #[test]
    fn unstarted_jobs_are_not_parts_and_a_driver_latch_aborts() {
        let mut machine = Machine::new(None, Counters::default());
        let refused = JobEnd::unstarted(JobStatus::Failed, "controller: unknown");
        machine
            .step(MachineInput::JobEnded {
                end: &refused,
                cycle_time_s: 0.0,
                more_queued: false,
            })
            .unwrap();
        assert_eq!(machine.status().counters.processed, 0);
        let t = machine
            .step(MachineInput::DriverLatched {
                code: "robot_unreachable",
                reason: "no answer",
            })
            .unwrap();
        assert_eq!(states(&t), [Aborting]);
        assert_eq!(
            machine.status().stop_reason.unwrap().code,
            "robot_unreachable"
        );
    }

    /// Every state has its ISA-TR88 number, each once.
    #[test]
    fn state_numbers_are_the_standards() {
        let named = [
            (Clearing, 1),
            (Stopped, 2),
            (Starting, 3),
            (Idle, 4),
            (Suspended, 5),
            (Execute, 6),
            (Stopping, 7),
            (Aborting, 8),
            (Aborted, 9),
            (Holding, 10),
            (Held, 11),
            (Unholding, 12),
            (Suspending, 13),
            (Unsuspending, 14),
            (Resetting, 15),
            (Completing, 16),
            (Complete, 17),
        ];
        for (state, number) in named {
            assert_eq!(state.number(), number, "{}", state.name());
        }
    }
}
