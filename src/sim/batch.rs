//! Many episodes stepped at once, on all cores: for evaluation and training.

use super::env::{AssemblyEnv, EnvError, EnvOptions, Observation, StepResult};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use rayon::prelude::*;

/// A batch of independent twins of the same cell.
#[derive(Debug, Clone)]
pub struct BatchEnv {
    envs: Vec<AssemblyEnv>,
}

impl BatchEnv {
    pub fn new(cell: &CellConfig, options: EnvOptions, size: usize) -> Self {
        let env = AssemblyEnv::new(cell, options);
        BatchEnv {
            envs: vec![env; size],
        }
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// Resets every episode, episode `i` with `seeds[i]`.
    pub fn reset(&mut self, seeds: &[u64]) -> Result<Vec<Observation>, EnvError> {
        assert_eq!(seeds.len(), self.envs.len(), "one seed per episode");
        self.envs
            .par_iter_mut()
            .zip(seeds.par_iter())
            .map(|(env, seed)| env.reset(*seed))
            .collect()
    }

    /// Steps every episode that is still running with its action; finished episodes are left
    /// alone and answer `None`.
    pub fn step(&mut self, actions: &[Move]) -> Vec<Option<StepResult>> {
        assert_eq!(actions.len(), self.envs.len(), "one action per episode");
        self.envs
            .par_iter_mut()
            .zip(actions.par_iter())
            .map(|(env, action)| env.step(action).ok())
            .collect()
    }

    /// The episodes, for inspection (outcomes, observations).
    pub fn envs(&self) -> &[AssemblyEnv] {
        &self.envs
    }
}
