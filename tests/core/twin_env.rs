//! The digital twin as a whole: determinism, bad input, the batched form, and the expert on the
//! Table 5 protocol.

use assembly_cell::camera::ingest::Ingest;
use assembly_cell::config::cell::CellConfig;
use assembly_cell::geometry::CellFrames;
use assembly_cell::geometry::Move;
use assembly_cell::policy::{self, eval};
use assembly_cell::sim::env::first_usable_estimate;
use assembly_cell::sim::{
    AssemblyEnv, BatchEnv, EnvError, EnvOptions, InitialConditions, Outcome, StepResult,
};

fn bits(result: &StepResult) -> Vec<u64> {
    let mut v: Vec<u64> = result
        .observation
        .state
        .iter()
        .map(|x| x.to_bits())
        .collect();
    v.push(result.reward.total.to_bits());
    v.extend(result.legs_mm.iter().map(|x| x.to_bits()));
    v.push(result.true_errors.depth_error_mm.to_bits());
    v
}

fn run(cell: &CellConfig, seed: u64) -> Vec<Vec<u64>> {
    let mut env = AssemblyEnv::new(cell, EnvOptions::from_cell(cell));
    let mut expert = policy::builtin("expert", cell).unwrap();
    expert.reset(seed);
    let mut observation = env.reset(seed).unwrap();
    let mut trace = vec![observation.state.iter().map(|x| x.to_bits()).collect()];
    loop {
        let result = env.step(&expert.act(&observation).action).unwrap();
        trace.push(bits(&result));
        observation = result.observation.clone();
        if result.done {
            return trace;
        }
    }
}

#[test]
fn same_seed_same_episode_bit_for_bit() {
    let cell = CellConfig::reference();
    for seed in [1, 2, 99] {
        let a = run(&cell, seed);
        let b = run(&cell, seed);
        assert!(a.len() > 5);
        assert_eq!(a, b, "seed {seed}");
    }
    assert_ne!(run(&cell, 1), run(&cell, 2));
}

#[test]
fn nan_action_is_a_veto_and_moves_nothing() {
    let cell = CellConfig::reference();
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    env.reset(5).unwrap();
    let before = env.true_f_m();
    let result = env
        .step(&Move::from_array([f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0]))
        .unwrap();
    assert_eq!(result.veto.as_ref().map(|v| v.code()), Some("non_finite"));
    assert!(result.observation.state.iter().all(|x| x.is_finite()));
    assert_eq!(env.true_f_m(), before);
    // Over the step limit: vetoed, not clipped.
    let result = env.step(&Move::translation(0.0, 0.0, -5.5)).unwrap();
    assert_eq!(result.veto.as_ref().map(|v| v.code()), Some("step_limit"));
    assert_eq!(env.true_f_m(), before);
}

#[test]
fn twenty_vetoes_in_a_row_fail_the_episode() {
    let cell = CellConfig::reference();
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    env.reset(11).unwrap();
    let mut last = None;
    for _ in 0..cell.episode.max_consecutive_vetoes {
        last = Some(env.step(&Move::rotation(2.0, 0.0, 0.0)).unwrap());
    }
    let last = last.unwrap();
    assert_eq!(
        last.outcome,
        Some(Outcome::Failure(
            assembly_cell::sim::FailureReason::CollisionLimit
        ))
    );
    assert!(last.reward.global < 0.0);
    assert!(
        env.step(&Move::default()).is_err(),
        "a finished episode refuses steps"
    );
}

#[test]
fn driving_into_the_entrance_face_is_vetoed_before_contact() {
    // Noiseless twin: push straight down without aligning; the supervisor must stop it.
    let mut cell = CellConfig::reference();
    cell.imperfections.camera_noise = false;
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    env.reset(3).unwrap();
    let mut vetoed = false;
    for _ in 0..40 {
        let result = env.step(&Move::translation(0.0, 0.0, -5.0)).unwrap();
        assert_ne!(
            result.outcome,
            Some(Outcome::Failure(assembly_cell::sim::FailureReason::Contact))
        );
        if result.veto.as_ref().map(|v| v.code()) == Some("collision") {
            vetoed = true;
            break;
        }
    }
    assert!(vetoed, "the supervisor never vetoed a move into the face");
}

#[test]
fn batched_env_matches_single_episodes() {
    let cell = CellConfig::reference();
    let options = EnvOptions::from_cell(&cell);
    let seeds = [10, 20, 30, 40];
    let mut batch = BatchEnv::new(&cell, options, seeds.len());
    let observations = batch.reset(&seeds).unwrap();
    let mut singles: Vec<AssemblyEnv> = seeds
        .iter()
        .map(|_| AssemblyEnv::new(&cell, options))
        .collect();
    for (env, seed) in singles.iter_mut().zip(seeds) {
        let observation = env.reset(seed).unwrap();
        assert!(observations.contains(&observation));
    }
    let action = Move::translation(1.0, -1.0, -2.0);
    for _ in 0..5 {
        let results = batch.step(&vec![action; seeds.len()]);
        for (result, env) in results.iter().zip(singles.iter_mut()) {
            // A finished episode answers None in the batch and an error on its own.
            assert_eq!(result, &env.step(&action).ok());
        }
    }
}

#[test]
fn expert_solves_the_table5_protocol() {
    let cell = CellConfig::reference();
    let make = || policy::builtin("expert", &cell).unwrap();
    let (summary, _) = eval::evaluate(
        &cell,
        EnvOptions::from_cell(&cell),
        1000,
        2026,
        &make,
        &|_| {},
    );
    eprintln!("{summary:?}");
    assert_eq!(summary.episodes, 1000);
    assert!(
        summary.success_rate >= 0.99,
        "expert success {}",
        summary.success_rate
    );
}

/// The expert's episode with camera ingestion run outside the twin, as the service does.
fn run_split(cell: &CellConfig, seed: u64) -> Vec<Vec<u64>> {
    let mut env = AssemblyEnv::new(cell, EnvOptions::from_cell(cell));
    let mut ingest = Ingest::new(cell, &CellFrames::from_config(cell));
    let mut expert = policy::builtin("expert", cell).unwrap();
    expert.reset(seed);
    env.begin_episode(seed, InitialConditions::from_cell(cell))
        .unwrap();
    let Ok(estimate) = first_usable_estimate(|first| {
        Ok::<_, std::convert::Infallible>(ingest.take(env.capture_still(first)))
    });
    let mut observation = env.start_from(&estimate);
    let mut trace = vec![observation.state.iter().map(|x| x.to_bits()).collect()];
    loop {
        let shot = env.act(&expert.act(&observation).action).unwrap();
        let estimate = ingest.take(shot);
        let result = env.settle(&estimate).unwrap();
        trace.push(bits(&result));
        observation = result.observation.clone();
        if result.done {
            return trace;
        }
    }
}

#[test]
fn ingestion_outside_the_twin_gives_the_same_episode() {
    let mut cell = CellConfig::reference();
    // Dropped points make some captures unusable, so the retries and stale steps are covered.
    cell.camera.dropout_probability = 0.3;
    for seed in [1, 4] {
        assert_eq!(run_split(&cell, seed), run(&cell, seed), "seed {seed}");
    }
}

#[test]
fn act_and_settle_out_of_order_are_refused() {
    let cell = CellConfig::reference();
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    let still = Move::translation(0.0, 0.0, 0.0);
    assert!(matches!(env.act(&still), Err(EnvError::EpisodeOver)));
    env.begin_episode(3, InitialConditions::from_cell(&cell))
        .unwrap();
    assert!(matches!(env.act(&still), Err(EnvError::OutOfOrder(_))));
    let mut ingest = Ingest::new(&cell, &CellFrames::from_config(&cell));
    let estimate = ingest.take(env.capture_still(true));
    env.start_from(&estimate);
    let error = env.settle(&estimate).unwrap_err();
    assert_eq!(
        error.to_string(),
        "out of order: settle without a move; call act first"
    );
    env.act(&still).unwrap();
    assert!(matches!(env.act(&still), Err(EnvError::OutOfOrder(_))));
}

/// The true state is what a camera without noise or calibration error reports; with the
/// data sheet's noise the camera's frame scatters around it by about that noise.
#[test]
fn the_true_state_is_what_a_perfect_camera_sees() {
    let cell = CellConfig::reference();
    let perfect = EnvOptions {
        noise_scale: 0.0,
        calibration_scale: 0.0,
        ..EnvOptions::from_cell(&cell)
    };
    let mut env = AssemblyEnv::new(&cell, perfect);
    let observation = env.reset(4).unwrap();
    let truth = env.true_state();
    for (k, (seen, true_value)) in observation.raw_state.iter().zip(&truth).enumerate() {
        assert!(
            (seen - true_value).abs() < 1e-6,
            "slot {k}: seen {seen}, true {true_value}"
        );
    }
    let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
    let observation = env.reset(4).unwrap();
    let truth = env.true_state();
    let lateral_gap =
        (observation.raw_state[6] - truth[6]).hypot(observation.raw_state[7] - truth[7]);
    assert!(
        lateral_gap > 0.0 && lateral_gap < 0.5,
        "gap {lateral_gap} mm"
    );
}
