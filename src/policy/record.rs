//! Recording demonstrations: a demonstrator (one of the scripted experts) runs episodes in the
//! twin and every decision it makes on a fresh state is kept, step by step, with its choice of
//! actor and step size (the LSTM selector's labels). `learning::demos` reads and writes them as
//! JSON Lines; the DA-DMP baseline ([`super::dmp`]) is fitted to them.

use super::eval::{episode_seed, robot_blocks};
use super::inputs::PolicyInputs;
use super::{Actor, Controller};
use crate::config::cell::CellConfig;
use crate::sim::randomise::{CellRanges, cell_for, randomised};
use crate::sim::{AssemblyEnv, EnvOptions, Outcome};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// One recorded step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DemoStep {
    pub episode: u32,
    pub step: u32,
    pub state: [f64; 12],
    pub action: [f64; 6],
    pub actor: Actor,
    pub scale: f64,
}

/// One recorded episode, in order.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoEpisode {
    pub steps: Vec<DemoStep>,
    pub succeeded: bool,
}

/// The demonstrator `celld train` records by default: the expert that decides on the 12-value
/// state alone (`expert-state-only`), so that what it does can be learned from what it saw.
pub const DEFAULT_DEMONSTRATOR: &str = "expert-state-only";

/// The demonstrators a run may record: the scripted experts.
pub const DEMONSTRATORS: [&str; 4] = [
    "expert-state-only",
    "expert-careful",
    "expert-swift",
    "expert",
];

/// Refuses a name that is not one of [`DEMONSTRATORS`], listing them.
pub fn check_demonstrator(name: &str) -> Result<(), String> {
    if DEMONSTRATORS.contains(&name) {
        Ok(())
    } else {
        Err(format!(
            "{name}: not a demonstrator; known: {}",
            DEMONSTRATORS.join(", ")
        ))
    }
}

/// Records `episodes` episodes of the `expert` in the twin; see [`record`].
pub fn record_expert(
    cell: &CellConfig,
    options: EnvOptions,
    episodes: usize,
    seed: u64,
) -> Vec<DemoEpisode> {
    record(cell, options, "expert", episodes, seed)
}

/// Records `episodes` episodes of `demonstrator` (one of [`DEMONSTRATORS`]) in the twin (all
/// cores, deterministic under `seed`). Vetoed steps are kept (the expert saw the state and
/// decided), and so are its deliberate holds (a zero move); steps where it held still for want
/// of a fresh frame are left out, having no label.
pub fn record(
    cell: &CellConfig,
    options: EnvOptions,
    demonstrator: &str,
    episodes: usize,
    seed: u64,
) -> Vec<DemoEpisode> {
    record_with(
        cell,
        options,
        demonstrator,
        episodes,
        seed,
        Recording::default(),
    )
}

/// Noise added to the demonstrator's moves before they are executed, while the recorded label
/// stays the move it meant (DART, Laskey et al. 2017): the demonstrations then visit the states
/// just off its path that a learned policy drifts into, each labelled with the correction.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ExecutionNoise {
    /// σ (mm) of the Gaussian added to x and y of every position move that is not a hold.
    pub lateral_mm: f64,
}

/// How a recording is made beyond its cell and demonstrator.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Recording {
    /// Noise on what is executed (not on what is recorded); none in DAgger's episodes, where
    /// the driver's moves are executed.
    pub noise: ExecutionNoise,
    /// What each step's `state` holds: the numbers a policy with these inputs reads.
    pub inputs: PolicyInputs,
    /// Each episode on a cell of its own, drawn around the given one over these ranges
    /// (domain randomisation); none: every episode on the given cell.
    pub randomise: Option<CellRanges>,
}

/// [`record`], made as `recording` says.
pub fn record_with(
    cell: &CellConfig,
    options: EnvOptions,
    demonstrator: &str,
    episodes: usize,
    seed: u64,
    recording: Recording,
) -> Vec<DemoEpisode> {
    record_driven(cell, options, demonstrator, episodes, seed, recording, None)
}

/// Makes a fresh copy of the controller that drives DAgger's episodes (one per thread).
pub type DriverFactory<'a> = &'a (dyn Fn() -> Box<dyn Controller> + Sync);

/// DAgger (Ross, Gordon & Bagnell 2011): `driver` (a learned policy) moves the shaft, and
/// `demonstrator` labels every state the policy visits with what it would have done there. A
/// policy trained on its demonstrator's episodes alone drifts into states the demonstrator
/// never visits (overshooting the standoff, creeping in sideways) and has no label for them;
/// these episodes give it one. Each episode's `succeeded` is the driver's outcome. The
/// demonstrator keeps its own count of holds, as if its decisions had been executed.
pub fn relabel_rollouts(
    cell: &CellConfig,
    options: EnvOptions,
    demonstrator: &str,
    driver: DriverFactory,
    episodes: usize,
    seed: u64,
    recording: Recording,
) -> Vec<DemoEpisode> {
    record_driven(
        cell,
        options,
        demonstrator,
        episodes,
        seed,
        recording,
        Some(driver),
    )
}

/// Seed of the demonstrator's own randomness (its step-length variability) in episode `seed`.
pub fn demonstrator_seed(episode_seed: u64) -> u64 {
    episode_seed ^ 0x5EED_C0DE
}

/// Runs the episodes, recording the demonstrator's decision on every state; what is executed
/// is the driver's decision if there is one, else the demonstrator's with the recording's
/// noise.
fn record_driven(
    cell: &CellConfig,
    options: EnvOptions,
    demonstrator: &str,
    episodes: usize,
    seed: u64,
    recording: Recording,
    driver: Option<DriverFactory>,
) -> Vec<DemoEpisode> {
    assert!(
        DEMONSTRATORS.contains(&demonstrator),
        "unknown demonstrator {demonstrator}"
    );
    let noise = recording.noise;
    let demonstrator_for =
        |cell: &CellConfig| super::builtin(demonstrator, cell).expect("a demonstrator is built in");
    let run = |env: &mut AssemblyEnv,
               expert: &mut Box<dyn Controller>,
               driver: &mut Option<Box<dyn Controller>>,
               index: usize| {
        let seed = episode_seed(seed, index);
        expert.reset(demonstrator_seed(seed));
        if let Some(driver) = driver {
            driver.reset(seed);
        }
        let mut noise_rng = ChaCha8Rng::seed_from_u64(seed ^ 0xDA57_0000);
        let mut steps = Vec::new();
        let Ok(mut observation) = env.reset(seed) else {
            return DemoEpisode {
                steps,
                succeeded: false,
            };
        };
        loop {
            let decision = expert.act(&observation);
            if let (Some(actor), Some(scale)) = (decision.actor, decision.scale) {
                steps.push(DemoStep {
                    episode: index as u32,
                    step: observation.step,
                    state: recording.inputs.of(&observation),
                    action: decision.action.to_array(),
                    actor,
                    scale,
                });
            }
            let mut executed = match driver {
                Some(driver) => driver.act(&observation).action,
                None => decision.action,
            };
            if noise.lateral_mm > 0.0
                && driver.is_none()
                && decision.actor == Some(Actor::Position)
                && executed.translation_mm != nalgebra::Vector3::zeros()
            {
                for axis in 0..2 {
                    let z: f64 = noise_rng.sample(StandardNormal);
                    executed.translation_mm[axis] += noise.lateral_mm * z;
                }
            }
            let result = env.step(&executed).expect("stepped until done");
            observation = result.observation;
            if let Some(outcome) = result.outcome {
                return DemoEpisode {
                    steps,
                    succeeded: outcome == Outcome::Success,
                };
            }
        }
    };
    if options.kept_robots == 0 {
        return (0..episodes)
            .into_par_iter()
            .map_init(
                || {
                    (
                        AssemblyEnv::new(cell, options),
                        demonstrator_for(cell),
                        driver.map(|make| make()),
                    )
                },
                |(env, expert, driver), index| {
                    if let Some(ranges) = &recording.randomise {
                        let (drawn, mismatch) =
                            randomised(cell, &options, ranges, episode_seed(seed, index));
                        *env = AssemblyEnv::new(&drawn, mismatch);
                        *expert = demonstrator_for(&drawn);
                    }
                    run(env, expert, driver, index)
                },
            )
            .collect();
    }
    // Kept robots, as a cell keeps its robot: each runs its block of episodes in order,
    // remembering its drift; when randomising, each robot is on a cell of its own.
    let blocks: Vec<Vec<DemoEpisode>> = robot_blocks(options, episodes, seed)
        .into_par_iter()
        .map(|(kept, block)| {
            let (cell, kept) = cell_for(cell, &kept, recording.randomise.as_ref(), kept.robot_seed);
            let mut env = AssemblyEnv::new(&cell, kept);
            let mut expert = demonstrator_for(&cell);
            let mut driver = driver.map(|make| make());
            block
                .map(|index| run(&mut env, &mut expert, &mut driver, index))
                .collect()
        })
        .collect();
    blocks.into_iter().flatten().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy;

    #[test]
    fn the_state_only_demonstrator_holds_five_times_then_goes_in_by_at_most_3_mm() {
        let cell = CellConfig::reference();
        let episodes = record(
            &cell,
            EnvOptions::from_cell(&cell),
            DEFAULT_DEMONSTRATOR,
            6,
            9,
        );
        let mut succeeded = 0;
        for episode in &episodes {
            let holds: Vec<_> = episode
                .steps
                .iter()
                .filter(|s| s.action == [0.0; 6])
                .collect();
            if episode.succeeded {
                succeeded += 1;
                assert_eq!(
                    holds.len(),
                    5,
                    "one hold per frame at the standoff, 5 in all"
                );
            }
            assert!(
                holds
                    .iter()
                    .all(|s| s.actor == Actor::Position && s.scale == 0.0)
            );
            let last_hold = episode.steps.iter().rposition(|s| s.action == [0.0; 6]);
            // After the holds, every insertion step is at most 3 mm deep.
            for step in &episode.steps[last_hold.map_or(0, |i| i + 1)..] {
                assert!(step.action[2].abs() <= 3.0 + 1e-9, "{:?}", step.action);
            }
        }
        assert!(succeeded >= 5, "{succeeded} of 6 succeeded");
    }

    #[test]
    fn execution_noise_moves_the_shaft_but_each_label_is_what_the_demonstrator_meant() {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let plain = record(&cell, options, DEFAULT_DEMONSTRATOR, 2, 4);
        let none = Recording::default();
        let same = record_with(&cell, options, DEFAULT_DEMONSTRATOR, 2, 4, none);
        assert_eq!(plain, same, "no noise is the plain recording");
        let noise = Recording {
            noise: ExecutionNoise { lateral_mm: 0.05 },
            ..Recording::default()
        };
        let noisy = record_with(&cell, options, DEFAULT_DEMONSTRATOR, 2, 4, noise);
        for (clean, noisy) in plain.iter().zip(&noisy) {
            // The first state is seen before anything is executed: the same state, the same
            // label. From there on the executed moves differ, and so do the states.
            assert_eq!(clean.steps[0], noisy.steps[0]);
            let after = |e: &DemoEpisode| e.steps.iter().skip(1).map(|s| s.state).collect();
            let (clean_states, noisy_states): (Vec<_>, Vec<_>) = (after(clean), after(noisy));
            assert_ne!(clean_states, noisy_states);
        }
        // Each label is still the demonstrator's own decision on the state it saw: replaying
        // the recorded states through a fresh demonstrator gives the recorded moves.
        let labels: Vec<_> = noisy[0].steps.iter().map(|s| s.action).collect();
        assert_eq!(
            labels,
            replayed_labels(&cell, episode_seed(4, 0), &noisy[0])
        );
    }

    #[test]
    fn on_kept_robots_a_recording_is_the_same_on_any_number_of_threads() {
        let cell = CellConfig::reference();
        let kept = EnvOptions {
            kept_robots: 2,
            ..EnvOptions::from_cell(&cell)
        };
        let on = |threads: usize, options: EnvOptions| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| record(&cell, options, "expert-swift", 4, 5))
        };
        let one = on(1, kept);
        assert_eq!(one.len(), 4);
        assert_eq!(one, on(2, kept));
        // Each episode is still labelled with its own index, in order.
        for (index, episode) in one.iter().enumerate() {
            assert!(episode.steps.iter().all(|s| s.episode == index as u32));
        }
        // Robots the cell keeps are not the robots new to it of every episode.
        assert_ne!(one, on(2, EnvOptions::from_cell(&cell)));
    }

    /// Replays recorded states through a fresh demonstrator: the labels it gives back.
    fn replayed_labels(
        cell: &CellConfig,
        episode_seed: u64,
        episode: &DemoEpisode,
    ) -> Vec<[f64; 6]> {
        let mut expert = policy::builtin(DEFAULT_DEMONSTRATOR, cell).unwrap();
        let mut env = AssemblyEnv::new(cell, EnvOptions::from_cell(cell));
        expert.reset(demonstrator_seed(episode_seed));
        let mut observation = env.reset(episode_seed).unwrap();
        episode
            .steps
            .iter()
            .map(|recorded| {
                observation.state = recorded.state;
                observation.step = recorded.step;
                observation.measurement_fresh = true;
                expert.act(&observation).action.to_array()
            })
            .collect()
    }

    /// A controller reset the way [`record`] resets its demonstrator.
    struct AsDemonstrator(Box<dyn Controller>);

    impl Controller for AsDemonstrator {
        fn name(&self) -> &str {
            self.0.name()
        }
        fn reset(&mut self, seed: u64) {
            self.0.reset(demonstrator_seed(seed))
        }
        fn act(&mut self, observation: &crate::sim::Observation) -> crate::policy::Decision {
            self.0.act(observation)
        }
    }

    #[test]
    fn the_demonstrator_driving_its_own_relabelling_is_the_plain_recording() {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let make = || {
            let demonstrator = policy::builtin(DEFAULT_DEMONSTRATOR, &cell).unwrap();
            Box::new(AsDemonstrator(demonstrator)) as Box<dyn Controller>
        };
        let relabelled = relabel_rollouts(
            &cell,
            options,
            DEFAULT_DEMONSTRATOR,
            &make,
            3,
            8,
            Recording::default(),
        );
        assert_eq!(
            relabelled,
            record(&cell, options, DEFAULT_DEMONSTRATOR, 3, 8)
        );
    }

    #[test]
    fn another_controller_drives_and_every_state_it_visits_gets_the_demonstrators_label() {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let make = || policy::builtin("visual-servo", &cell).unwrap();
        let relabelled = relabel_rollouts(
            &cell,
            options,
            DEFAULT_DEMONSTRATOR,
            &make,
            2,
            8,
            Recording::default(),
        );
        let plain = record(&cell, options, DEFAULT_DEMONSTRATOR, 2, 8);
        for (index, episode) in relabelled.iter().enumerate() {
            let seed = episode_seed(8, index);
            // The states are the driver's own episode: those it sees running alone.
            let mut driver = policy::builtin("visual-servo", &cell).unwrap();
            driver.reset(seed);
            let mut env = AssemblyEnv::new(&cell, options);
            let mut observation = env.reset(seed).unwrap();
            let mut alone = Vec::new();
            loop {
                if observation.measurement_fresh {
                    alone.push(observation.state);
                }
                let result = env.step(&driver.act(&observation).action).unwrap();
                observation = result.observation;
                if let Some(outcome) = result.outcome {
                    assert_eq!(episode.succeeded, outcome == Outcome::Success);
                    break;
                }
            }
            let visited: Vec<_> = episode.steps.iter().map(|s| s.state).collect();
            assert_eq!(visited, alone);
            let demonstrated: Vec<_> = plain[index].steps.iter().map(|s| s.state).collect();
            assert_ne!(visited, demonstrated);
            // Every label is the demonstrator's decision on the state the driver was in.
            let labels: Vec<_> = episode.steps.iter().map(|s| s.action).collect();
            assert_eq!(labels, replayed_labels(&cell, seed, episode));
        }
    }
}
