//! Whether a controller fails less than a reference on the same episodes: runs both as
//! `celld eval --noise-scale NOISE --seed S --episodes EPISODES` runs them (the reference
//! cell, 10 kept robots) for every seed, pairs the episodes, and counts those both failed and
//! those each failed alone, by how they ended. McNemar's exact test on the episodes failed
//! alone says whether the difference is beyond chance, and how few failures of its own a
//! candidate would need for a lead there (`cell_research::paired`). Steps are compared over the
//! episodes both succeeded in.
//!
//! `cargo run --release -p cell-research -- paired_failures REFERENCE CANDIDATES NOISE SEEDS
//! [EPISODES]` (CANDIDATES comma-separated built-in names or policy files; SEEDS
//! comma-separated, each a seed or a range such as `62-189`; EPISODES per seed, default 4000).

use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{EpisodeReport, evaluate};
use assembly_cell::sim::EnvOptions;
use cell_research::paired::{PairedFailures, paired_episodes};
use std::collections::BTreeMap;

/// One candidate's pairing with the reference over every seed so far.
#[derive(Default)]
struct Tally {
    failures: PairedFailures,
    /// How the episodes each failed alone ended, and those both failed (`reference/candidate`).
    reference_only: BTreeMap<String, usize>,
    candidate_only: BTreeMap<String, usize>,
    both: BTreeMap<String, usize>,
    /// Steps of the episodes both succeeded in: the reference's, the candidate's, how many.
    steps: (u64, u64, u64),
}

impl Tally {
    fn add(
        &mut self,
        reference: &[EpisodeReport],
        candidate: &[EpisodeReport],
    ) -> anyhow::Result<()> {
        for (r, c) in paired_episodes(reference, candidate)? {
            self.failures.count(r, c);
            let count =
                |map: &mut BTreeMap<String, usize>, key: String| *map.entry(key).or_default() += 1;
            match (r.succeeded(), c.succeeded()) {
                (true, true) => {
                    self.steps.0 += u64::from(r.steps);
                    self.steps.1 += u64::from(c.steps);
                    self.steps.2 += 1;
                }
                (false, true) => count(&mut self.reference_only, r.outcome.clone()),
                (true, false) => count(&mut self.candidate_only, c.outcome.clone()),
                (false, false) => count(&mut self.both, format!("{}/{}", r.outcome, c.outcome)),
            }
        }
        Ok(())
    }
}

pub fn main() -> anyhow::Result<()> {
    let reference_name: String = cell_research::arg(1, "expert".to_string())?;
    let candidates: String = cell_research::arg(2, "hierarchical-swift-cells".to_string())?;
    let noise_scale: f64 = cell_research::arg(3, 2.0)?;
    let seeds = cell_research::seeds(&cell_research::arg(4, "62".to_string())?)?;
    let episodes: usize = cell_research::arg(5, 4000)?;
    let cell = CellConfig::reference();
    let options = EnvOptions {
        noise_scale,
        kept_robots: 10,
        ..EnvOptions::from_cell(&cell)
    };
    let reference = cell_research::controller_factory(&reference_name, &cell)?;
    let candidates = candidates
        .split(',')
        .map(|name| {
            Ok((
                name.to_string(),
                cell_research::controller_factory(name, &cell)?,
            ))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut tallies: Vec<Tally> = candidates.iter().map(|_| Tally::default()).collect();
    for &seed in &seeds {
        let (_, reference_run) = evaluate(&cell, options, episodes, seed, &reference, &|_| {});
        for ((_, make), tally) in candidates.iter().zip(&mut tallies) {
            let (_, candidate_run) = evaluate(&cell, options, episodes, seed, make, &|_| {});
            tally.add(&reference_run, &candidate_run)?;
        }
        eprintln!("seed {seed} done");
    }
    let seeds_text = match (seeds.first(), seeds.last()) {
        (Some(first), Some(last)) => format!("{} seeds, {first}–{last}", seeds.len()),
        _ => "no seeds".to_string(),
    };
    for ((name, _), tally) in candidates.iter().zip(&tallies) {
        let f = tally.failures;
        let (reference_steps, candidate_steps, both_succeeded) = tally.steps;
        let mean = |sum: u64| sum as f64 / both_succeeded.max(1) as f64;
        println!(
            "{name} against {reference_name}, noise ×{noise_scale}, {seeds_text}, {} episodes",
            f.episodes
        );
        println!(
            "  failed: {reference_name} {}, {name} {}; both {} {:?}",
            f.both + f.reference_only,
            f.both + f.candidate_only,
            f.both,
            tally.both
        );
        println!(
            "  alone: {reference_name} {} {:?}, {name} {} {:?}; p = {:.2e} (McNemar, exact)",
            f.reference_only,
            tally.reference_only,
            f.candidate_only,
            tally.candidate_only,
            f.p_value()
        );
        let lead = match f.own_failures_for_a_lead(0.05) {
            Some(own) => format!("at most {own} failures of its own"),
            None => "more episodes: even none of its own would not be enough".to_string(),
        };
        println!("  a lead beyond p < 0.05 beside these would take {lead}");
        println!(
            "  steps where both succeeded ({both_succeeded}): {reference_name} {:.2}, {name} {:.2}",
            mean(reference_steps),
            mean(candidate_steps)
        );
    }
    Ok(())
}
