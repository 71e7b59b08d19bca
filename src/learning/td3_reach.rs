//! A toy task with a known optimum on which TD3 must beat the demonstrator it starts from.
//!
//! A point `x` (true distance to the goal, 0.4–1.0 at the start) moves by −0.1·a per step for
//! an action a ∈ [−1, 1]; the actor sees `x` through noise (σ 0.02), the critics see it
//! exactly. An episode ends in success when |x| ≤ 0.05 and in a crash (−10) when x < −0.05;
//! every step costs 1. The best policy steps a = 1 until the last step, which lands in the
//! goal: ⌈(x₀ − 0.05)/0.1⌉ steps. The demonstrator is safe and slow (|a| ≤ 0.3), the way the
//! scripted experts of the cell are: about three times the optimum's steps.

use super::td3::{ReplayBuffer, Td3, Td3Config, Transition};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

const STEP: f32 = 0.1;
const GOAL: f32 = 0.05;
const NOISE: f64 = 0.02;
const MAX_STEPS: usize = 60;

/// Who acts: the demonstrator, or the learner (with or without exploration).
enum Driver<'a> {
    Demonstrator,
    Learner(&'a mut Td3, bool),
}

struct Episode {
    transitions: Vec<Transition>,
    steps: usize,
    crashed: bool,
}

fn demonstrator(observed: f32) -> f32 {
    (observed / STEP).clamp(-0.3, 0.3)
}

fn run(driver: &mut Driver, seed: u64) -> Episode {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut x: f32 = rng.random_range(0.4..1.0);
    let observe = |x: f32, rng: &mut ChaCha8Rng| {
        let e: f64 = rng.sample(StandardNormal);
        x + (NOISE * e) as f32
    };
    let mut observed = observe(x, &mut rng);
    let mut transitions = Vec::new();
    for step in 1..=MAX_STEPS {
        let a = match driver {
            Driver::Demonstrator => demonstrator(observed),
            Driver::Learner(td3, true) => td3.explore(&[observed]).unwrap()[0],
            Driver::Learner(td3, false) => td3.act(&[observed]).unwrap()[0],
        };
        let before = (observed, x);
        x -= STEP * a;
        observed = observe(x, &mut rng);
        let (reward, done, crashed) = if x < -GOAL {
            (-10.0, true, true)
        } else {
            (-1.0, x.abs() <= GOAL, false)
        };
        transitions.push(Transition {
            state: vec![before.0],
            action: vec![a],
            reward,
            next_state: vec![observed],
            done,
            privileged: vec![before.1],
            next_privileged: vec![x],
            coarse: false,
        });
        if done {
            return Episode {
                transitions,
                steps: step,
                crashed,
            };
        }
    }
    Episode {
        transitions,
        steps: MAX_STEPS,
        crashed: false,
    }
}

/// Mean steps and crashes over the evaluation seeds.
fn evaluate(driver: &mut Driver) -> (f64, usize) {
    let episodes: Vec<Episode> = (0..100).map(|k| run(driver, 10_000 + k)).collect();
    let steps = episodes.iter().map(|e| e.steps).sum::<usize>() as f64 / episodes.len() as f64;
    (steps, episodes.iter().filter(|e| e.crashed).count())
}

fn optimum_steps() -> f64 {
    (0..100)
        .map(|k| {
            let x: f32 = ChaCha8Rng::seed_from_u64(10_000 + k).random_range(0.4..1.0);
            ((x - GOAL) / STEP).ceil().max(1.0) as f64
        })
        .sum::<f64>()
        / 100.0
}

#[test]
fn td3_from_demonstrations_beats_its_slow_demonstrator_on_a_task_with_a_known_optimum() {
    let mut demos = ReplayBuffer::new(100_000);
    for k in 0..30 {
        for t in run(&mut Driver::Demonstrator, k).transitions {
            demos.push(t);
        }
    }
    let config = Td3Config {
        hidden: 64,
        batch_size: 64,
        actor_learning_rate: 1e-3,
        critic_learning_rate: 1e-3,
        exploration_noise: 0.2,
        privileged_dim: 1,
        demo_regularisation: Some(2.5),
        seed: 11,
        ..Td3Config::default()
    };
    let mut td3 = Td3::new(1, 1, config, None).unwrap();
    // Behaviour cloning, then the critics learn the cloned actor's values before it moves.
    td3.clone_behaviour(&demos, 1500).unwrap();
    let (cloned_steps, _) = evaluate(&mut Driver::Learner(&mut td3, false));
    td3.freeze_actor(true);
    let mut online = ReplayBuffer::new(100_000);
    for _ in 0..1000 {
        td3.update_with(&online, &demos).unwrap();
    }
    td3.freeze_actor(false);
    for k in 0..200 {
        let episode = run(&mut Driver::Learner(&mut td3, true), 1_000 + k);
        for t in episode.transitions {
            online.push(t);
            td3.update_with(&online, &demos).unwrap();
        }
    }
    let (demonstrator_steps, demonstrator_crashes) = evaluate(&mut Driver::Demonstrator);
    let (learned_steps, learned_crashes) = evaluate(&mut Driver::Learner(&mut td3, false));
    let optimum = optimum_steps();
    eprintln!(
        "steps: demonstrator {demonstrator_steps:.2} ({demonstrator_crashes} crashes), \
         cloned {cloned_steps:.2}, TD3 {learned_steps:.2} ({learned_crashes} crashes), \
         optimum {optimum:.2}"
    );
    assert_eq!(demonstrator_crashes, 0);
    assert!(
        (cloned_steps - demonstrator_steps).abs() < 0.2 * demonstrator_steps,
        "behaviour cloning should start near the demonstrator: {cloned_steps} vs {demonstrator_steps}"
    );
    assert!(
        learned_steps < 0.6 * demonstrator_steps,
        "TD3 took {learned_steps} steps, the demonstrator {demonstrator_steps}"
    );
    assert!(learned_steps >= optimum - 1e-9, "better than the optimum?");
    assert!(learned_crashes <= 2, "{learned_crashes} crashes in 100");
}
