//! Camera ingestion on its own thread against inline, as the control thread sees it: the time
//! of one control tick (settle the last move, decide, send the next) with `TwinBackend`'s
//! ingestion thread, and of one `AssemblyEnv::step` (decide, move, capture, ingest) inline.
//! The expert drives both through the same episodes, with a pause between ticks standing in for
//! the control period.
//!
//! `cargo bench --bench ingestion -- [CPU|any] [PERIOD_MS]`: CPU pins this thread and the
//! ingestion thread to one CPU, as `control.cpu` does in the service (default: any, 20 ms).

mod support;

use assembly_cell::cell::{CellBackend, TwinBackend};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy;
use assembly_cell::sim::{AssemblyEnv, EnvOptions, InitialConditions};
use std::time::{Duration, Instant};

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let cpu: Option<usize> = args.first().and_then(|a| a.parse().ok());
    let period = Duration::from_millis(args.get(1).and_then(|a| a.parse().ok()).unwrap_or(20));
    if let Some(cpu) = cpu {
        assembly_cell::cell::cpu::pin_current_thread(&[cpu]).expect("pin to the CPU");
    }
    let cell = CellConfig::reference();
    let initial = InitialConditions::from_cell(&cell);
    let mut backend = TwinBackend::new(&cell, cpu);
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    let mut expert = policy::builtin("expert", &cell).unwrap();
    let (mut threaded, mut inline) = (Vec::new(), Vec::new());
    let episodes = (10_000 / period.as_millis().max(1) as u64 / 45).max(4);
    for seed in 0..episodes {
        expert.reset(seed);
        let observation = backend.start(seed, initial).unwrap();
        backend.act(&expert.act(&observation).action).unwrap();
        loop {
            std::thread::sleep(period);
            let tick = Instant::now();
            let result = backend.settle().unwrap();
            if result.done {
                break;
            }
            backend
                .act(&expert.act(&result.observation).action)
                .unwrap();
            threaded.push(tick.elapsed().as_secs_f64() * 1e6);
        }
        expert.reset(seed);
        let mut observation = env.reset_with(seed, initial).unwrap();
        loop {
            std::thread::sleep(period);
            let tick = Instant::now();
            let result = env.step(&expert.act(&observation).action).unwrap();
            inline.push(tick.elapsed().as_secs_f64() * 1e6);
            observation = result.observation;
            if result.done {
                break;
            }
        }
    }
    let place = cpu.map_or("any CPU".to_string(), |c| format!("CPU {c}"));
    println!("{} ms period, {place}:", period.as_millis());
    for (name, ticks) in [
        ("ingestion thread, tick", &mut threaded),
        ("inline, step", &mut inline),
    ] {
        let count = ticks.len();
        let mut at = |p: f64| support::percentile(ticks, p);
        println!(
            "  {name}: {} ticks, p50 {:.1} µs, p99 {:.1} µs, max {:.1} µs",
            count,
            at(0.5),
            at(0.99),
            at(1.0)
        );
    }
}
