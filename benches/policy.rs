//! How long the hierarchical policy takes to decide (the goal: a batch-1 decision's p99 ≤
//! 50 µs), on the states it really meets: the policy first drives the twin for EPISODES
//! episodes, then its decisions on the states of its fresh frames are timed one by one, each
//! episode from a zero LSTM state, through
//! - `HierarchicalPolicy::step`: the plain f32 path of every `Controller::act` (batch 1);
//! - `step_batch_candle` with one row: the candle reference, for comparison;
//! - `step_batch` with BATCH rows (the batched environment's path): per call and per decision.
//!
//! `cargo bench --bench policy -- [EPISODES] [BATCH] [POLICY_FILE]` (default: 200 episodes,
//! 64 rows, the bundled `hierarchical-reference` policy). `celld` and this bench set `RAYON_NUM_THREADS`
//! to the core count when it is unset (`init_cpu_threads`).

mod support;

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::Controller;
use assembly_cell::policy::eval::episode_seed;
use assembly_cell::policy::file::PolicyFile;
use assembly_cell::policy::hierarchical::{BatchState, HierarchicalPolicy};
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::sim::{AssemblyEnv, EnvOptions};
use std::time::Instant;

/// Timing passes over all decisions; the first is a warm-up and is not counted.
const PASSES: usize = 4;

fn main() {
    assembly_cell::threads::init_cpu_threads();
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let episodes = count_argument(args.first(), "EPISODES", 200);
    let batch = count_argument(args.get(1), "BATCH", 64);
    let file = match args.get(2) {
        Some(path) => PolicyFile::from_path(path).unwrap_or_else(|e| {
            eprintln!("POLICY_FILE {path}: {e}");
            std::process::exit(2)
        }),
        None => PolicyFile::from_bytes(
            assembly_cell::policy::bundled_policy("hierarchical-reference").expect("bundled"),
        )
        .expect("the bundled policy is valid"),
    };
    let mut policy = HierarchicalPolicy::from_file(&file).expect("the policy loads");
    let cell = CellConfig::reference();
    let runs = record_states(&policy, &cell, episodes);
    let decisions: usize = runs.iter().map(Vec::len).sum();
    let config = *policy.config();
    println!(
        "H = {}, D = {}; {} CPUs, RAYON_NUM_THREADS={}; {episodes} episodes, {decisions} decisions, {} timed passes",
        config.hidden_size,
        config.actor_width,
        std::thread::available_parallelism().map_or(1, |n| n.get()),
        std::env::var("RAYON_NUM_THREADS").unwrap_or_default(),
        PASSES - 1,
    );

    let mut plain = time_one_by_one(&runs, &mut policy, |policy, state, _| {
        std::hint::black_box(policy.step(state).expect("a finite step"));
    });
    let mut candle = time_one_by_one(&runs, &mut policy, |policy, state, one| {
        let out = policy.step_batch_candle(std::slice::from_ref(state), one);
        std::hint::black_box(out.expect("a finite step"));
    });
    print_latency("batch 1, plain f32 (`step`)", &mut plain);
    print_latency("batch 1, candle (`step_batch_candle`)", &mut candle);

    // B episodes side by side, each row restarting its episode when it runs out of states.
    let mut calls = Vec::new();
    let longest = runs.iter().map(Vec::len).max().unwrap_or(0);
    let mut state = policy.batch_state(batch);
    for pass in 0..PASSES {
        state.reset_all();
        for t in 0..longest {
            let rows: Vec<[f64; 12]> = (0..batch)
                .map(|row| {
                    let states = &runs[(pass * batch + row) % runs.len()];
                    if t % states.len() == 0 && t > 0 {
                        state.reset_row(row);
                    }
                    states[t % states.len()]
                })
                .collect();
            let started = Instant::now();
            let out = policy.step_batch(&rows, &mut state);
            let call_us = started.elapsed().as_secs_f64() * 1e6;
            std::hint::black_box(out.expect("a finite step"));
            if pass > 0 {
                calls.push(call_us);
            }
        }
    }
    let per_decision_us = calls.iter().sum::<f64>() / (calls.len() * batch) as f64;
    print_latency(
        &format!("batch {batch}, plain f32 (`step_batch`), per call"),
        &mut calls,
    );
    println!(
        "  batch {batch}: {per_decision_us:.2} µs per decision, {:.0} decisions/s",
        1e6 / per_decision_us
    );
}

/// A positive count from the command line, `default` when it is absent; exits on anything else.
fn count_argument(argument: Option<&String>, name: &str, default: usize) -> usize {
    match argument.map(|a| a.parse::<usize>()) {
        None => default,
        Some(Ok(n)) if n > 0 => n,
        _ => {
            eprintln!(
                "{name} must be a positive whole number, not {:?}",
                argument.unwrap()
            );
            std::process::exit(2)
        }
    }
}

/// The states of the policy's fresh frames in `episodes` twin episodes it drives itself, with
/// the rules training runs it with (episodes without a fresh frame left out).
fn record_states(
    policy: &HierarchicalPolicy,
    cell: &CellConfig,
    episodes: usize,
) -> Vec<Vec<[f64; 12]>> {
    let mut policy =
        LearnedPolicy::hierarchical(policy.clone()).with_rules(&cell.rules.in_training());
    let mut env = AssemblyEnv::new(cell, EnvOptions::from_cell(cell));
    (0..episodes)
        .map(|index| {
            let seed = episode_seed(1, index);
            policy.reset(seed);
            let mut observation = env.reset(seed).expect("an episode starts");
            let mut states = Vec::new();
            loop {
                if observation.measurement_fresh {
                    states.push(observation.state);
                }
                let decision = policy.act(&observation);
                let result = env.step(&decision.action).expect("a step");
                observation = result.observation;
                if result.done {
                    return states;
                }
            }
        })
        .filter(|states| !states.is_empty())
        .collect()
}

/// Times `decide` on every state, episode by episode from a zero LSTM state (that of the
/// policy and that of a one-row batch), over [`PASSES`] passes less the warm-up; µs per call.
fn time_one_by_one(
    runs: &[Vec<[f64; 12]>],
    policy: &mut HierarchicalPolicy,
    decide: impl Fn(&mut HierarchicalPolicy, &[f64; 12], &mut BatchState),
) -> Vec<f64> {
    let mut times_us = Vec::new();
    for pass in 0..PASSES {
        for states in runs {
            policy.reset();
            let mut one = policy.batch_state(1);
            for state in states {
                let started = Instant::now();
                decide(policy, state, &mut one);
                let elapsed_us = started.elapsed().as_secs_f64() * 1e6;
                if pass > 0 {
                    times_us.push(elapsed_us);
                }
            }
        }
    }
    times_us
}

/// Prints nearest-rank percentiles of `values_us` (sorted in place).
fn print_latency(name: &str, values_us: &mut [f64]) {
    let calls = values_us.len();
    let mut at = |p: f64| support::percentile(values_us, p);
    println!(
        "  {name}: {} calls, p50 {:.1} µs, p90 {:.1} µs, p99 {:.1} µs, p99.9 {:.1} µs, max {:.1} µs",
        calls,
        at(0.5),
        at(0.9),
        at(0.99),
        at(0.999),
        at(1.0)
    );
}
