//! `celld check`: the bundled policies against the goals they are held to (docs/policy-rules.md,
//! "Checking the goals"). A bundled file stays as it was while the code around it changes, so
//! whoever changes the policies, the rules or the twin runs this: under decisions 0044–0046 the
//! careful cross-cell file came to hit the step limit in 3.5 % of episodes on phi100-deep, and
//! nothing showed it until its recipe was run again (decision 0050).
//!
//! The goals are data ([`goals::GOALS`]): each holds some policies, on some conditions (a cell, a
//! camera noise, episodes and a seed), to some bounds, most of them against `expert` on the
//! same episodes. `--smoke` runs the same goals on far fewer episodes, on seeds where the
//! bundled files hold them, the bounds unchanged.

mod goals;

use super::progress::Progress;
use anyhow::{Context, Result, bail};
use assembly_cell::policy::eval::{DEFAULT_KEPT_ROBOTS, EvalSummary, evaluate};
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::{ControllerFactory, builtin_factory};
use assembly_cell::sim::EnvOptions;
use clap::Args;
use goals::{BASELINE, Condition, Episodes, HIERARCHICAL, Measured, selected};
use serde_json::json;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
pub struct CheckArgs {
    /// Goals or policies to check (comma-separated or repeated): goals deep-tight, reference,
    /// reference-fast, noise-x2, noise-x4; policies hierarchical-reference,
    /// hierarchical-cells, hierarchical-swift-reference, hierarchical-swift-cells. Default: all.
    #[arg(long, value_delimiter = ',', value_name = "NAME")]
    only: Vec<String>,
    /// Each goal on a few episodes (on seeds where the bundled files hold it), in seconds:
    /// the check `cargo test` runs. The bounds are the goals' own.
    #[arg(long)]
    smoke: bool,
    /// Checks a policy file in place of a bundled policy, as NAME=FILE (repeatable).
    #[arg(long = "policy", value_name = "NAME=FILE")]
    policies: Vec<String>,
    /// Also print the results as one JSON object on the last line.
    #[arg(long)]
    json: bool,
}

/// `--policy NAME=FILE`: the policy files checked in place of bundled policies, by name.
fn replacements(values: &[String]) -> Result<BTreeMap<String, (PathBuf, LearnedPolicy)>> {
    let mut replaced = BTreeMap::new();
    for value in values {
        let Some((name, path)) = value
            .split_once('=')
            .filter(|(n, p)| !n.is_empty() && !p.is_empty())
        else {
            bail!("--policy {value}: expected NAME=FILE");
        };
        if !HIERARCHICAL.contains(&name) {
            bail!(
                "--policy {value}: {name} is not a policy the goals check ({})",
                HIERARCHICAL.join(", ")
            );
        }
        // Checked now, before any work starts.
        let loaded = LearnedPolicy::from_path(path)
            .with_context(|| format!("--policy {value}"))?
            .with_name(name);
        if replaced
            .insert(name.to_string(), (PathBuf::from(path), loaded))
            .is_some()
        {
            bail!("--policy {name}= given twice");
        }
    }
    Ok(replaced)
}

/// One line of the check: a goal, one policy, one condition, each bound measured.
struct Line {
    goal: &'static str,
    policy: String,
    condition: &'static str,
    episodes: Episodes,
    measured: Vec<Measured>,
}

impl Line {
    fn held(&self) -> bool {
        self.measured.iter().all(|m| m.held)
    }

    fn text(&self) -> String {
        let figures: Vec<&str> = self.measured.iter().map(|m| m.text.as_str()).collect();
        format!(
            "{:<15} {:<28} {:<28} {:>4} ep seed {:<3} {}  {}",
            self.goal,
            self.policy,
            self.condition,
            self.episodes.episodes,
            self.episodes.seed,
            figures.join("; "),
            if self.held() { "PASS" } else { "MISS" }
        )
    }

    fn json(&self) -> serde_json::Value {
        let bounds: Vec<_> = self
            .measured
            .iter()
            .map(|m| {
                json!({
                    "figure": m.figure,
                    "measured": m.measured,
                    "relation": m.relation,
                    "bound": m.bound,
                    "held": m.held,
                })
            })
            .collect();
        json!({
            "goal": self.goal,
            "policy": self.policy,
            "condition": self.condition,
            "episodes": self.episodes.episodes,
            "seed": self.episodes.seed,
            "bounds": bounds,
            "held": self.held(),
        })
    }
}

/// The evaluations already run, by controller, condition and episodes: `expert` and a policy
/// shared by two goals run once.
type Evaluated = BTreeMap<(&'static str, &'static str, Episodes), EvalSummary>;

pub fn run(args: CheckArgs) -> Result<()> {
    let goals = selected(&args.only)?;
    let replaced = replacements(&args.policies)?;
    let started = Instant::now();
    let mut evaluated = Evaluated::new();
    let mut lines = Vec::new();
    let mut episodes_run = 0;
    for (goal, policies) in &goals {
        // The evaluations this goal needs that no goal before it ran.
        let needs_expert = goal.bounds.iter().any(|b| b.needs_expert());
        let controllers: Vec<&'static str> = needs_expert
            .then_some(BASELINE)
            .into_iter()
            .chain(policies.iter().copied())
            .collect();
        let episodes = |c: &Condition| if args.smoke { c.smoke } else { c.full };
        let to_run: Vec<(&'static str, &Condition)> = goal
            .conditions
            .iter()
            .flat_map(|c| controllers.iter().map(move |name| (*name, c)))
            .filter(|(name, c)| !evaluated.contains_key(&(*name, c.name, episodes(c))))
            .collect();
        let total: usize = to_run.iter().map(|(_, c)| episodes(c).episodes).sum();
        if total > 0 {
            let progress = Progress::new(
                total as u64,
                goal.name,
                "{bar:40} {pos}/{len} episodes  {elapsed} (eta {eta})  {msg}",
            );
            for (name, condition) in to_run {
                progress.set_message(format!("{name} on {}", condition.name));
                let cell = condition.cell.load()?;
                let factory: ControllerFactory = match replaced.get(name) {
                    Some((_, policy)) => {
                        let policy = policy.clone().with_rules(&cell.rules);
                        Box::new(move || Box::new(policy.clone()))
                    }
                    None => builtin_factory(name, &cell)?,
                };
                let options = EnvOptions {
                    kept_robots: DEFAULT_KEPT_ROBOTS,
                    noise_scale: condition.noise_scale,
                    ..EnvOptions::from_cell(&cell)
                };
                let run = episodes(condition);
                let (summary, _) =
                    evaluate(&cell, options, run.episodes, run.seed, &factory, &|_| {
                        progress.inc(1)
                    });
                episodes_run += run.episodes;
                evaluated.insert((name, condition.name, run), summary);
            }
            progress.finish_and_clear();
        }
        for condition in goal.conditions {
            let key = |name| (name, condition.name, episodes(condition));
            let expert = needs_expert.then(|| &evaluated[&key(BASELINE)]);
            for policy in policies {
                let learned = &evaluated[&key(*policy)];
                let line = Line {
                    goal: goal.name,
                    policy: match replaced.get(*policy) {
                        Some((path, _)) => format!("{policy}={}", path.display()),
                        None => policy.to_string(),
                    },
                    condition: condition.name,
                    episodes: episodes(condition),
                    measured: goal
                        .bounds
                        .iter()
                        .map(|b| b.judge(learned, expert))
                        .collect(),
                };
                println!("{}", line.text());
                lines.push(line);
            }
        }
    }
    let wall_s = started.elapsed().as_secs_f64();
    let missed: Vec<&Line> = lines.iter().filter(|l| !l.held()).collect();
    println!(
        "{} of {} goals held, {} missed; {episodes_run} episodes in {wall_s:.1} s",
        lines.len() - missed.len(),
        lines.len(),
        missed.len()
    );
    if args.json {
        let all: Vec<_> = lines.iter().map(Line::json).collect();
        println!(
            "{}",
            json!({
                "smoke": args.smoke,
                "goals": all,
                "held": lines.len() - missed.len(),
                "missed": missed.len(),
                "episodes": episodes_run,
                "wall_s": wall_s,
            })
        );
    }
    if !missed.is_empty() {
        let named: Vec<String> = missed
            .iter()
            .map(|l| format!("{} ({} on {})", l.goal, l.policy, l.condition))
            .collect();
        bail!(
            "missed {} of {} goals: {}",
            missed.len(),
            lines.len(),
            named.join(", ")
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use goals::GOALS;

    #[test]
    fn the_help_names_every_goal_and_policy() {
        use clap::{CommandFactory, Parser};
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            check: CheckArgs,
        }
        let help = Cli::command().render_long_help().to_string();
        for goal in GOALS {
            assert!(help.contains(goal.name), "{}: {help}", goal.name);
            for policy in goal.policies {
                assert!(help.contains(policy), "{policy}: {help}");
            }
        }
    }
}
