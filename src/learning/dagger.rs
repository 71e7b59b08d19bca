//! DAgger (Ross, Gordon & Bagnell 2011) as the training runs use it: a policy drives episodes in
//! the twin and the demonstrator labels every state it visits; those episodes go before the
//! demonstrator's own, and the last tenth, the demonstrator's own, is held out to check the
//! selector. `celld train` and `POST /api/training` split their episodes here alike.

use super::demos::{self, DemoEpisode, DriverFactory, Recording};
use crate::config::cell::CellConfig;
use crate::policy::eval::episode_seed;
use crate::sim::EnvOptions;

/// Sets DAgger's episode seeds apart from the demonstrations' (both derive from the run's seed).
const DAGGER_SEED_SALT: u64 = 0xDA66_E500;

/// Driver `index`'s DAgger episodes: it drives `episodes` episodes, the demonstrator labels
/// them (seeds apart from the demonstrations' and from the other drivers').
#[allow(clippy::too_many_arguments)]
pub fn rollouts(
    cell: &CellConfig,
    options: EnvOptions,
    demonstrator: &str,
    driver: DriverFactory,
    episodes: usize,
    run_seed: u64,
    index: usize,
    recording: Recording,
) -> Vec<DemoEpisode> {
    demos::relabel_rollouts(
        cell,
        options,
        demonstrator,
        driver,
        episodes,
        episode_seed(run_seed ^ DAGGER_SEED_SALT, index),
        recording,
    )
}

/// Numbers the episodes 0, 1, … in order (one file's numbering, whatever their sources).
pub fn renumbered(episodes: Vec<DemoEpisode>) -> Vec<DemoEpisode> {
    episodes
        .into_iter()
        .enumerate()
        .map(|(index, mut episode)| {
            for step in &mut episode.steps {
                step.episode = index as u32;
            }
            episode
        })
        .collect()
}

/// A run's episodes as its stages learn from them.
#[derive(Debug, Clone, PartialEq)]
pub struct Split {
    /// What behaviour cloning learns from (the normaliser too).
    pub train: Vec<DemoEpisode>,
    /// The last tenth, which checks the selector.
    pub held_out: Vec<DemoEpisode>,
    /// What the selector learns from.
    pub selector: Vec<DemoEpisode>,
}

/// Splits `episodes`, whose first `dagger` are DAgger episodes and the rest the demonstrator's
/// own: episodes without steps are dropped, the last tenth is held out, and the selector
/// learns from all the others or, with `actors_only`, from the demonstrator's own among them
/// (the demonstrator's holds on a struggling policy's states would teach a selector to hold
/// where the demonstrator itself moves on).
pub fn split(mut episodes: Vec<DemoEpisode>, dagger: usize, actors_only: bool) -> Split {
    let own_from = dagger.min(episodes.len());
    let own_with_steps = episodes[own_from..]
        .iter()
        .filter(|e| !e.steps.is_empty())
        .count();
    episodes.retain(|e| !e.steps.is_empty());
    let held_out = episodes.split_off(episodes.len() - episodes.len() / 10);
    let selector = if actors_only {
        let own = own_with_steps.saturating_sub(held_out.len());
        episodes[episodes.len() - own..].to_vec()
    } else {
        episodes.clone()
    };
    Split {
        train: episodes,
        held_out,
        selector,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learning::demos::DemoStep;
    use crate::policy::Actor;

    /// An episode of `steps` steps whose states all read `tag`.
    fn episode(tag: f64, steps: usize) -> DemoEpisode {
        DemoEpisode {
            steps: (0..steps)
                .map(|step| DemoStep {
                    episode: 99,
                    step: step as u32,
                    state: [tag; 12],
                    action: [0.0; 6],
                    actor: Actor::Position,
                    scale: 0.5,
                })
                .collect(),
            succeeded: true,
        }
    }

    fn tags(episodes: &[DemoEpisode]) -> Vec<f64> {
        episodes.iter().map(|e| e.steps[0].state[0]).collect()
    }

    #[test]
    fn the_held_out_tenth_and_the_selectors_episodes_are_the_demonstrators_own() {
        // 12 DAgger episodes (tags 0..12, the third empty), then 10 own (tags 100..110, the
        // first empty): 20 with steps, 2 held out.
        let mut episodes: Vec<DemoEpisode> = (0..12)
            .map(|i| episode(i as f64, if i == 2 { 0 } else { 3 }))
            .collect();
        episodes.extend((0..10).map(|i| episode(100.0 + i as f64, if i == 0 { 0 } else { 2 })));
        let split_all = split(episodes.clone(), 12, false);
        assert_eq!(tags(&split_all.held_out), [108.0, 109.0]);
        assert_eq!(split_all.train.len(), 18);
        assert_eq!(split_all.selector, split_all.train);
        let actors_only = split(episodes, 12, true);
        assert_eq!(actors_only.train, split_all.train);
        assert_eq!(actors_only.held_out, split_all.held_out);
        assert_eq!(
            tags(&actors_only.selector),
            (101..108).map(f64::from).collect::<Vec<_>>()
        );
    }

    #[test]
    fn without_dagger_episodes_the_selector_learns_from_all() {
        let episodes: Vec<DemoEpisode> = (0..20).map(|i| episode(i as f64, 1)).collect();
        for actors_only in [false, true] {
            let split = split(episodes.clone(), 0, actors_only);
            assert_eq!(tags(&split.held_out), [18.0, 19.0]);
            assert_eq!(split.selector, split.train);
        }
    }

    #[test]
    fn renumbering_numbers_episodes_in_order() {
        let numbered = renumbered(vec![episode(1.0, 2), episode(2.0, 3)]);
        let numbers: Vec<Vec<u32>> = numbered
            .iter()
            .map(|e| e.steps.iter().map(|s| s.episode).collect())
            .collect();
        assert_eq!(numbers, [vec![0, 0], vec![1, 1, 1]]);
    }
}
