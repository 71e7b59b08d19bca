//! A cell that keeps its robot remembers the drift it learned (docs/estimation.md §3a): its
//! episodes get faster, a robot changed without the cell being told is noticed and forgotten,
//! and an evaluation over kept robots does not depend on the number of threads.

use assembly_cell::camera::DriftKnowledge;
use assembly_cell::config::cell::CellConfig;
use assembly_cell::policy::eval::{self, episode_seed};
use assembly_cell::policy::{Controller, expert::Expert};
use assembly_cell::sim::{AssemblyEnv, EnvOptions, Outcome};

fn options(cell: &CellConfig, kept_robots: u32, robot_seed: u64) -> EnvOptions {
    EnvOptions {
        kept_robots,
        robot_seed,
        ..EnvOptions::from_cell(cell)
    }
}

/// Runs one expert episode; its outcome, steps and the faults named at its steps.
fn episode(env: &mut AssemblyEnv, seed: u64) -> (Option<Outcome>, u32, Vec<&'static str>) {
    let mut controller = Expert::new(env.cell());
    controller.reset(seed);
    let mut observation = env.reset(seed).unwrap();
    let mut named = Vec::new();
    loop {
        let result = env.step(&controller.act(&observation).action).unwrap();
        named.extend(result.detected);
        observation = result.observation;
        if result.done {
            return (result.outcome, env.steps(), named);
        }
    }
}

#[test]
fn a_kept_robot_is_learned_and_its_episodes_get_faster() {
    let cell = CellConfig::reference();
    let mut kept = AssemblyEnv::new(&cell, options(&cell, 1, 7));
    let mut unseen = AssemblyEnv::new(&cell, options(&cell, 0, 0));
    let (mut kept_steps, mut unseen_steps) = (0, 0);
    // Episodes in which the guard took the kept robot for a changed one and forgot it: a false
    // alarm, which costs that episode's speed, and the memory starts again
    // (docs/estimation.md §3a).
    let mut false_alarms = Vec::new();
    let mut longest_memory = None;
    for i in 0..60 {
        let seed = episode_seed(3, i);
        let remembered = kept.drift_memory().is_some();
        let (kept_outcome, steps, _) = episode(&mut kept, seed);
        if remembered && kept.drift_memory().is_none() {
            false_alarms.push(i);
        }
        if let Some(memory) = kept.drift_memory().copied()
            && longest_memory.is_none_or(|m: DriftKnowledge| m.episodes < memory.episodes)
        {
            longest_memory = Some(memory);
        }
        let (unseen_outcome, unseen_episode_steps, _) = episode(&mut unseen, seed);
        assert_eq!(
            kept_outcome,
            Some(Outcome::Success),
            "kept robot, episode {i}"
        );
        assert_eq!(
            unseen_outcome,
            Some(Outcome::Success),
            "new robot, episode {i}"
        );
        if i >= 20 {
            kept_steps += steps;
            unseen_steps += unseen_episode_steps;
        }
    }
    // Measured: about 27 against 45 steps an episode (celld eval, 1000 episodes).
    let (kept_mean, unseen_mean) = (f64::from(kept_steps) / 40.0, f64::from(unseen_steps) / 40.0);
    assert!(
        kept_mean < unseen_mean - 8.0,
        "kept {kept_mean:.1} steps against {unseen_mean:.1} for a new robot each episode"
    );
    // At most one false alarm in 60 episodes (one in this sequence since the expert corrects
    // the tilt to what the cell takes; none before).
    assert!(
        false_alarms.len() <= 1,
        "false alarms in episodes {false_alarms:?}"
    );
    // Every episode after the last alarm taught it but the last, whose knowledge is taken at
    // the 61st's start; an alarmed episode teaches nothing. Without an alarm, 59.
    let taught = false_alarms.last().map_or(59, |alarm| 58 - alarm) as u32;
    let memory = kept.drift_memory().expect("a memory after 60 episodes");
    assert_eq!(memory.episodes, taught);
    // The memory at its longest knew the drift far better than the prior.
    let longest = longest_memory.expect("a memory");
    assert!(longest.episodes >= 40, "{}", longest.episodes);
    let prior_sd = 0.002;
    assert!(
        longest.sd_per_mm().iter().all(|sd| *sd < prior_sd / 5.0),
        "{:?}",
        longest.sd_per_mm()
    );
    assert!(unseen.drift_memory().is_none());
}

#[test]
fn a_kept_robot_three_times_as_far_off_its_calibration_is_not_taken_for_a_changed_one() {
    let cell = CellConfig::reference();
    let mut env = AssemblyEnv::new(
        &cell,
        EnvOptions {
            calibration_scale: 3.0,
            ..options(&cell, 1, 7)
        },
    );
    // The robot is never changed, so every episode in which the cell names it changed is a
    // false alarm, after which the cell goes on with what this episode alone learned.
    let mut alarms = Vec::new();
    let mut failures = Vec::new();
    for i in 0..60 {
        let (outcome, _, named) = episode(&mut env, episode_seed(4, i));
        if named.contains(&"robot_changed") {
            alarms.push(i);
        }
        if outcome != Some(Outcome::Success) {
            failures.push((i, outcome));
        }
    }
    // Measured: 2 false alarms in these 60 episodes; 21 when the check started from the prior
    // for an unseen robot of the reference's calibration (docs/estimation.md §3a).
    assert!(alarms.len() <= 6, "false alarms in episodes {alarms:?}");
    assert!(failures.is_empty(), "{failures:?}");
}

#[test]
fn a_robot_replaced_without_telling_the_cell_is_noticed_and_relearned() {
    let cell = CellConfig::reference();
    let pairs = 30;
    let (mut named, mut relearned, mut second_contacts) = (0, 0, 0);
    for pair in 0..pairs {
        let mut env = AssemblyEnv::new(&cell, options(&cell, 1, 100 + pair));
        for i in 0..10 {
            episode(&mut env, episode_seed(pair, i));
        }
        assert!(env.drift_memory().is_some());
        env.swap_robot(500 + pair);
        let (_, _, seen) = episode(&mut env, episode_seed(pair, 10));
        named += usize::from(seen.contains(&"robot_changed"));
        let (outcome, _, _) = episode(&mut env, episode_seed(pair, 11));
        second_contacts += usize::from(
            outcome == Some(Outcome::Failure(assembly_cell::sim::FailureReason::Contact)),
        );
        // Learned from the new robot alone: the first episode after the swap started it again
        // (the check, the end-of-episode test or a contact), the second added to it.
        relearned += usize::from(env.drift_memory().is_some_and(|m| m.episodes <= 2));
    }
    // Measured: the check names the change in 22 of these 30 first episodes at the data
    // sheet's noise (the end-of-episode test or a contact starts the memory again in most
    // others), and 28 of the 30 memories start again. Two did not: their episode after the
    // swap agreed with what was remembered well enough to be added to it.
    assert!(named * 2 >= pairs as usize, "named in {named} of {pairs}");
    assert!(
        relearned * 10 >= pairs as usize * 9,
        "relearned in {relearned} of {pairs}"
    );
    assert_eq!(
        second_contacts, 0,
        "contacts in the second episode after the swap"
    );
}

#[test]
fn an_evaluation_over_kept_robots_does_not_depend_on_the_threads() {
    let cell = CellConfig::reference();
    let make = || Box::new(Expert::new(&cell)) as Box<dyn Controller>;
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| eval::evaluate(&cell, options(&cell, 4, 0), 24, 5, &make, &|_| {}).1)
    };
    let (one, two) = (run(1), run(2));
    assert_eq!(one, two);
    assert_eq!(one.len(), 24);
    assert!(one.iter().enumerate().all(|(i, r)| r.index == i));
    // The same episodes with a new robot each: different robots, different steps.
    let fleet = eval::evaluate(&cell, options(&cell, 0, 0), 24, 5, &make, &|_| {}).1;
    assert_ne!(one, fleet);
}
