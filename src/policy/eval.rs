//! Evaluating a controller in the twin: many seeded episodes on all cores, summarised.

use super::shield::{RuleId, ShieldTrace};
use super::{Controller, Decision};
use crate::config::cell::CellConfig;
use crate::sim::randomise::{CellRanges, cell_for};
use crate::sim::{AssemblyEnv, EnvOptions, Observation, Outcome, PoseErrors, StepResult};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::time::Instant;

mod per_cell;
pub use per_cell::{DrawnCell, per_drawn_cell, reaching};

/// What one episode came to.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeReport {
    pub index: usize,
    pub seed: u64,
    /// `success` or a failure code (`collision_limit`, `step_limit`, ...).
    pub outcome: String,
    pub steps: u32,
    pub reward: f64,
    pub vetoes: u32,
    pub final_errors: PoseErrors,
    /// What the shield's rules did to a learned policy's decisions (empty for other
    /// controllers).
    pub rules: RuleUse,
}

impl EpisodeReport {
    pub fn succeeded(&self) -> bool {
        self.outcome == "success"
    }
}

/// Summary of an evaluation (the JSON `celld eval --json` prints).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalSummary {
    pub controller: String,
    pub cell: String,
    pub episodes: usize,
    pub seed: u64,
    pub init_pos_mm: f64,
    pub init_ori_deg: f64,
    pub noise_scale: f64,
    /// The robot's calibration error × the cell file's.
    pub calibration_scale: f64,
    /// The fault injected in every episode (`sim::Fault::code`), if any.
    pub fault: Option<String>,
    /// Robots the episodes were shared among, each kept and its drift remembered (0: a new
    /// robot every episode, nothing remembered).
    pub kept_robots: u32,
    pub successes: usize,
    pub success_rate: f64,
    /// Average steps over the successful episodes (null when none succeeded).
    pub avg_steps: Option<f64>,
    pub avg_steps_all: f64,
    pub avg_reward: f64,
    pub avg_vetoes: f64,
    /// Failures counted by reason.
    pub failures: BTreeMap<String, usize>,
    /// How often the shield's rules changed a learned policy's decisions (absent for a
    /// controller without rules).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rules: Option<RuleUse>,
    /// Cells drawn around `cell` when the episodes ran on drawn cells
    /// ([`evaluate_on_drawn_cells`]); each cell's noise and calibration scales were drawn
    /// with it, and `noise_scale` and `calibration_scale` above were not used.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drawn_cells: Option<usize>,
    pub wall_s: f64,
}

/// How often the shield's rules changed a learned policy's decisions: over its decisions with
/// a [`ShieldTrace`], how many any rule changed and how many each rule did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RuleUse {
    pub decisions: u64,
    pub changed: u64,
    /// By rule, in [`RuleId::ALL`]'s order.
    pub by_rule: [u64; RuleId::ALL.len()],
}

impl RuleUse {
    /// Counts one decision's trace.
    pub fn add(&mut self, trace: &ShieldTrace) {
        self.decisions += 1;
        self.changed += u64::from(!trace.fired.is_empty());
        for id in trace.fired.iter() {
            self.by_rule[id as usize] += 1;
        }
    }

    /// Adds another count to this one.
    pub fn merge(&mut self, other: &RuleUse) {
        self.decisions += other.decisions;
        self.changed += other.changed;
        for (mine, theirs) in self.by_rule.iter_mut().zip(other.by_rule) {
            *mine += theirs;
        }
    }

    /// The share of decisions rule `id` changed (0 without decisions).
    pub fn share(&self, id: RuleId) -> f64 {
        self.by_rule[id as usize] as f64 / self.decisions.max(1) as f64
    }

    /// The share of decisions any rule changed.
    pub fn changed_share(&self) -> f64 {
        self.changed as f64 / self.decisions.max(1) as f64
    }
}

/// `{"decisions", "changed", "by_rule": {name: count}}`.
impl Serialize for RuleUse {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct;
        let by_rule: BTreeMap<&str, u64> = RuleId::ALL
            .into_iter()
            .map(|id| (id.name(), self.by_rule[id as usize]))
            .collect();
        let mut out = serializer.serialize_struct("RuleUse", 3)?;
        out.serialize_field("decisions", &self.decisions)?;
        out.serialize_field("changed", &self.changed)?;
        out.serialize_field("by_rule", &by_rule)?;
        out.end()
    }
}

/// The seed of episode `index` of an evaluation seeded with `seed` (SplitMix64), so that an
/// episode is the same whichever thread runs it and however many episodes are asked for.
pub fn episode_seed(seed: u64, index: usize) -> u64 {
    let mut z = seed.wrapping_add((index as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Runs one episode to its end.
pub fn run_episode(
    env: &mut AssemblyEnv,
    controller: &mut dyn Controller,
    index: usize,
    seed: u64,
) -> EpisodeReport {
    run_episode_watched(env, controller, index, seed, &mut |_, _, _| {})
}

/// [`run_episode`], showing `watch` every step: the observation the controller acted on, its
/// decision, and what the step did (for tools that look inside the episodes of an evaluation).
pub fn run_episode_watched(
    env: &mut AssemblyEnv,
    controller: &mut dyn Controller,
    index: usize,
    seed: u64,
    watch: &mut dyn FnMut(&Observation, &Decision, &StepResult),
) -> EpisodeReport {
    controller.reset(seed ^ 0x5EED_C0DE);
    let mut observation = match env.reset(seed) {
        Ok(observation) => observation,
        Err(error) => {
            return EpisodeReport {
                index,
                seed,
                outcome: format!("reset_failed: {error}"),
                steps: 0,
                reward: 0.0,
                vetoes: 0,
                final_errors: PoseErrors::default(),
                rules: RuleUse::default(),
            };
        }
    };
    let mut reward = 0.0;
    let mut vetoes = 0;
    let mut rules = RuleUse::default();
    loop {
        let decision = controller.act(&observation);
        if let Some(trace) = &decision.shield {
            rules.add(trace);
        }
        let result = env
            .step(&decision.action)
            .expect("the loop stops when the episode ends");
        watch(&observation, &decision, &result);
        reward += result.reward.total;
        vetoes += u32::from(result.veto.is_some());
        observation = result.observation;
        if let Some(outcome) = result.outcome {
            return EpisodeReport {
                index,
                seed,
                outcome: match outcome {
                    Outcome::Success => "success".to_string(),
                    Outcome::Failure(reason) => reason.code().to_string(),
                },
                steps: env.steps(),
                reward,
                vetoes,
                final_errors: result.true_errors,
                rules,
            };
        }
    }
}

/// Robots an evaluation shares its episodes among unless told otherwise: enough that its
/// figures average over robots, few enough that each robot's first, cold episode is a small
/// share of a thousand (`EnvOptions::kept_robots`).
pub const DEFAULT_KEPT_ROBOTS: u32 = 10;

/// The seed of robot `index` of an evaluation seeded with `seed` (`EnvOptions::kept_robots`).
pub fn robot_seed(seed: u64, index: usize) -> u64 {
    episode_seed(seed ^ 0x0B07_C0DE_5EED_0001, index)
}

/// How many of `kept_robots` (≥ 1) share `episodes` episodes: at least one, and no more than
/// there are episodes.
fn robots_of(kept_robots: u32, episodes: usize) -> usize {
    (kept_robots as usize).clamp(1, episodes.max(1))
}

/// The kept robots of `episodes` episodes seeded with `seed` (`options.kept_robots` ≥ 1): each
/// robot's options and the consecutive block of episode indices it runs in order.
pub fn robot_blocks(
    options: EnvOptions,
    episodes: usize,
    seed: u64,
) -> Vec<(EnvOptions, std::ops::Range<usize>)> {
    let robots = robots_of(options.kept_robots, episodes);
    (0..robots)
        .map(|robot| {
            let kept = EnvOptions {
                robot_seed: robot_seed(seed, robot),
                ..options
            };
            (
                kept,
                robot * episodes / robots..(robot + 1) * episodes / robots,
            )
        })
        .collect()
}

/// Runs `episodes` episodes on all cores; `make_controller` builds one controller per worker;
/// `on_episode` is called after each episode (for a progress bar).
///
/// With `options.kept_robots` = n ≥ 1, the episodes are shared among n robots in consecutive
/// blocks: each robot runs its block in order, the cell remembering its drift from episode to
/// episode, and the robots run in parallel. Either way an episode's outcome does not depend on
/// the number of threads.
pub fn evaluate(
    cell: &CellConfig,
    options: EnvOptions,
    episodes: usize,
    seed: u64,
    make_controller: &(dyn Fn() -> Box<dyn Controller> + Sync),
    on_episode: &(dyn Fn(&EpisodeReport) + Sync),
) -> (EvalSummary, Vec<EpisodeReport>) {
    evaluate_until(
        cell,
        None,
        options,
        episodes,
        seed,
        &|_| make_controller(),
        on_episode,
        &|| false,
    )
    .expect("never stopped")
}

/// [`evaluate`] on cells drawn over `ranges` around `base`, as training with randomised cells
/// draws them (`sim::randomise`): each kept robot on a cell of its own, or with
/// `options.kept_robots` = 0 each episode. The camera noise and calibration error of each
/// draw replace `options`'. `make_controller` builds a controller for a drawn cell. The seeds
/// are an evaluation's, so the cells are not the ones a training run drew.
pub fn evaluate_on_drawn_cells(
    base: &CellConfig,
    ranges: &CellRanges,
    options: EnvOptions,
    episodes: usize,
    seed: u64,
    make_controller: &(dyn Fn(&CellConfig) -> Box<dyn Controller> + Sync),
    on_episode: &(dyn Fn(&EpisodeReport) + Sync),
) -> (EvalSummary, Vec<EpisodeReport>) {
    evaluate_until(
        base,
        Some(ranges),
        options,
        episodes,
        seed,
        make_controller,
        on_episode,
        &|| false,
    )
    .expect("never stopped")
}

/// [`evaluate`] (no `ranges`) or [`evaluate_on_drawn_cells`] that a caller can stop: `stop` is
/// asked before each episode, and once it says so the episodes not begun are skipped and the
/// answer is `None` (a service stopping does not wait for thousands of episodes). Episodes
/// that run are the same as without it.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_until(
    cell: &CellConfig,
    ranges: Option<&CellRanges>,
    options: EnvOptions,
    episodes: usize,
    seed: u64,
    make_controller: &(dyn Fn(&CellConfig) -> Box<dyn Controller> + Sync),
    on_episode: &(dyn Fn(&EpisodeReport) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<(EvalSummary, Vec<EpisodeReport>)> {
    let started = Instant::now();
    let name = make_controller(cell).name().to_string();
    let reports = run_all(
        cell,
        options,
        ranges,
        episodes,
        seed,
        make_controller,
        on_episode,
        stop,
    )?;
    let mut summary = summarise(
        cell,
        options,
        seed,
        &name,
        &reports,
        started.elapsed().as_secs_f64(),
    );
    summary.drawn_cells = ranges.map(|_| match options.kept_robots {
        0 => episodes,
        kept => robots_of(kept, episodes),
    });
    Some((summary, reports))
}

/// The episodes of an evaluation, on `cell` or on cells drawn over `ranges` around it; `None`
/// once `stop` says so.
#[allow(clippy::too_many_arguments)]
fn run_all(
    cell: &CellConfig,
    options: EnvOptions,
    ranges: Option<&CellRanges>,
    episodes: usize,
    seed: u64,
    make_controller: &(dyn Fn(&CellConfig) -> Box<dyn Controller> + Sync),
    on_episode: &(dyn Fn(&EpisodeReport) + Sync),
    stop: &(dyn Fn() -> bool + Sync),
) -> Option<Vec<EpisodeReport>> {
    let run = |env: &mut AssemblyEnv, controller: &mut Box<dyn Controller>, index: usize| {
        if stop() {
            return None;
        }
        let report = run_episode(env, controller.as_mut(), index, episode_seed(seed, index));
        on_episode(&report);
        Some(report)
    };
    if options.kept_robots == 0 {
        return match ranges {
            None => (0..episodes)
                .into_par_iter()
                .map_init(
                    || (AssemblyEnv::new(cell, options), make_controller(cell)),
                    |(env, controller), index| run(env, controller, index),
                )
                .collect(),
            // A cell of its own for every episode, drawn from the episode's seed.
            Some(_) => (0..episodes)
                .into_par_iter()
                .map(|index| {
                    if stop() {
                        return None;
                    }
                    let (drawn, options) =
                        cell_for(cell, &options, ranges, episode_seed(seed, index));
                    run(
                        &mut AssemblyEnv::new(&drawn, options),
                        &mut make_controller(&drawn),
                        index,
                    )
                })
                .collect(),
        };
    }
    let blocks: Option<Vec<Vec<EpisodeReport>>> = robot_blocks(options, episodes, seed)
        .into_par_iter()
        .map(|(kept, block)| {
            if stop() {
                return None;
            }
            let (cell, kept) = cell_for(cell, &kept, ranges, kept.robot_seed);
            let mut env = AssemblyEnv::new(&cell, kept);
            let mut controller = make_controller(&cell);
            block
                .map(|index| run(&mut env, &mut controller, index))
                .collect()
        })
        .collect();
    Some(blocks?.into_iter().flatten().collect())
}

fn summarise(
    cell: &CellConfig,
    options: EnvOptions,
    seed: u64,
    controller: &str,
    reports: &[EpisodeReport],
    wall_s: f64,
) -> EvalSummary {
    let n = reports.len().max(1) as f64;
    let successes: Vec<&EpisodeReport> = reports.iter().filter(|r| r.succeeded()).collect();
    let mut failures = BTreeMap::new();
    for report in reports.iter().filter(|r| !r.succeeded()) {
        *failures.entry(report.outcome.clone()).or_insert(0) += 1;
    }
    EvalSummary {
        controller: controller.to_string(),
        cell: cell.name.clone(),
        episodes: reports.len(),
        seed,
        init_pos_mm: options.initial.offset_mm,
        init_ori_deg: options.initial.orientation_deg,
        noise_scale: options.noise_scale,
        calibration_scale: options.calibration_scale,
        fault: options.fault.map(|f| f.code().to_string()),
        kept_robots: options.kept_robots,
        successes: successes.len(),
        success_rate: successes.len() as f64 / n,
        avg_steps: (!successes.is_empty()).then(|| {
            successes.iter().map(|r| f64::from(r.steps)).sum::<f64>() / successes.len() as f64
        }),
        avg_steps_all: reports.iter().map(|r| f64::from(r.steps)).sum::<f64>() / n,
        avg_reward: reports.iter().map(|r| r.reward).sum::<f64>() / n,
        avg_vetoes: reports.iter().map(|r| f64::from(r.vetoes)).sum::<f64>() / n,
        failures,
        rules: reports.iter().any(|r| r.rules.decisions > 0).then(|| {
            let mut total = RuleUse::default();
            reports.iter().for_each(|r| total.merge(&r.rules));
            total
        }),
        drawn_cells: None,
        wall_s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_seeds_differ_and_repeat() {
        assert_eq!(episode_seed(7, 3), episode_seed(7, 3));
        assert_ne!(episode_seed(7, 3), episode_seed(7, 4));
        assert_ne!(episode_seed(7, 3), episode_seed(8, 3));
    }

    /// Runs `episodes` episodes of `expert` on drawn cells; returns the summary and the bore
    /// diameter (mm) of every cell a controller was made for.
    fn on_drawn_cells(kept_robots: u32, episodes: usize) -> (EvalSummary, Vec<f64>) {
        let base = CellConfig::reference();
        let options = EnvOptions {
            kept_robots,
            ..EnvOptions::from_cell(&base)
        };
        let made_for = std::sync::Mutex::new(Vec::new());
        let make = |cell: &CellConfig| -> Box<dyn Controller> {
            made_for.lock().unwrap().push(cell.bore.diameter_mm);
            Box::new(crate::policy::expert::Expert::new(cell))
        };
        let (summary, reports) = evaluate_on_drawn_cells(
            &base,
            &CellRanges::default(),
            options,
            episodes,
            5,
            &make,
            &|_| {},
        );
        assert_eq!(reports.len(), episodes);
        let mut diameters = made_for.into_inner().unwrap();
        // The first controller is made on the base cell, for its name.
        assert_eq!(diameters.remove(0), base.bore.diameter_mm);
        diameters.sort_by(f64::total_cmp);
        (summary, diameters)
    }

    /// The draws `sim::randomise` makes from `seeds`, as sorted bore diameters (mm).
    fn drawn_diameters(seeds: impl Iterator<Item = u64>) -> Vec<f64> {
        let base = CellConfig::reference();
        let options = EnvOptions::from_cell(&base);
        let mut diameters: Vec<f64> = seeds
            .map(|seed| {
                let (cell, _) = cell_for(&base, &options, Some(&CellRanges::default()), seed);
                cell.bore.diameter_mm
            })
            .collect();
        diameters.sort_by(f64::total_cmp);
        diameters
    }

    #[test]
    fn each_kept_robot_runs_on_the_cell_its_seed_draws() {
        let (summary, diameters) = on_drawn_cells(3, 6);
        assert_eq!(summary.drawn_cells, Some(3));
        assert_eq!(diameters, drawn_diameters((0..3).map(|r| robot_seed(5, r))));
        assert!(diameters.iter().all(|d| (100.0..=250.0).contains(d)));
        assert!(diameters.windows(2).all(|pair| pair[0] != pair[1]));
        assert!(summary.successes >= 5, "expert on drawn cells: {summary:?}");
    }

    #[test]
    fn without_kept_robots_every_episode_runs_on_a_cell_of_its_own() {
        let (summary, diameters) = on_drawn_cells(0, 4);
        assert_eq!(summary.drawn_cells, Some(4));
        assert_eq!(
            diameters,
            drawn_diameters((0..4).map(|i| episode_seed(5, i)))
        );
        let (again, _) = on_drawn_cells(0, 4);
        assert_eq!(
            (again.successes, again.avg_steps_all, again.avg_reward),
            (summary.successes, summary.avg_steps_all, summary.avg_reward),
            "the same seed runs the same episodes"
        );
    }

    /// A stop asked for mid-way skips the episodes not begun and answers nothing; never asked,
    /// the episodes are those of [`evaluate`].
    #[test]
    fn a_stopped_evaluation_runs_no_episode_after_the_stop() {
        let cell = CellConfig::reference();
        let options = EnvOptions {
            kept_robots: 2,
            ..EnvOptions::from_cell(&cell)
        };
        let make = |c: &CellConfig| -> Box<dyn Controller> {
            Box::new(crate::policy::expert::Expert::new(c))
        };
        let ran = std::sync::atomic::AtomicUsize::new(0);
        let count = |_: &EpisodeReport| {
            ran.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let stop = || ran.load(std::sync::atomic::Ordering::SeqCst) >= 3;
        let stopped =
            pool.install(|| evaluate_until(&cell, None, options, 8, 2, &make, &count, &stop));
        assert!(stopped.is_none());
        assert_eq!(
            ran.into_inner(),
            3,
            "one thread: the stop is seen before the fourth"
        );

        let whole = evaluate_until(&cell, None, options, 4, 2, &make, &|_| {}, &|| false)
            .unwrap()
            .1;
        let plain = evaluate(&cell, options, 4, 2, &|| make(&cell), &|_| {}).1;
        let outcomes = |r: &[EpisodeReport]| -> Vec<(String, u32)> {
            r.iter().map(|e| (e.outcome.clone(), e.steps)).collect()
        };
        assert_eq!(outcomes(&whole), outcomes(&plain));
    }
}
