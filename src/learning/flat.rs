//! The flat TD3 baseline's training: TD3 (`super::td3`, Table 1's defaults) on
//! one actor that gives the whole 6-DoF move (`policy::flat`), from freshly initialised weights
//! (no behaviour cloning) and without the hierarchy, in the twin.
//!
//! - **Reward**: the twin's total reward per step (the paper's reward: global, both local terms,
//!   the error term and the step penalty, with their weights).
//! - **Observation normaliser**: fitted on the expert demonstrations' *states* only
//!   ([`Normaliser::fit`]), so that the actor's input is scaled as the hierarchical policy's is.
//!   No expert action is used anywhere.
//! - **Episodes** run as the hierarchical refinement's (`super::refine`) do: the same episode
//!   seeds, Gaussian exploration noise (σ = `exploration_noise`) on the actor's tanh outputs,
//!   holding still without a fresh frame (a hold is not a transition; its reward goes to the
//!   previous one), one TD3 update per transition after each episode, the critics learning
//!   alone for the first `critic_warmup_episodes`.
//! - **Keeping the best**: every `eval_every` episodes (and at the end) the policy runs the
//!   validation episodes (seeds disjoint from the report's); the best one — success, then fewer
//!   steps, then a higher average return — is kept. The untrained network is not a candidate.
//!
//! Deterministic under its seed: the weights come from seeded code and every random draw from
//! seeded generators.

use super::dataset::{Normaliser, StepLimits};
use super::demos::DemoEpisode;
use super::pipeline::step_limits;
use super::refine::{EpisodeRecord, RefineConfig};
use super::td3::{ReplayBuffer, Td3, Td3Config, Transition, clone_varmap};
use crate::config::cell::CellConfig;
use crate::geometry::Move;
use crate::policy::ControllerFactory;
use crate::policy::eval::{self, episode_seed};
use crate::policy::file::{PolicyFileError, PolicyKind};
use crate::policy::flat::{ACTION_DIM, FlatPolicy, FlatPolicyFile};
use crate::policy::inputs::PolicyInputs;
use crate::policy::learned::LearnedPolicy;
use crate::policy::mlp::LAYER_NAMES;
use crate::sim::{AssemblyEnv, EnvOptions, Outcome};
use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

/// Settings of the flat baseline's training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlatConfig {
    pub episodes: usize,
    /// TD3's settings; the actor and both critics are `td3.hidden` wide.
    pub td3: Td3Config,
    /// Episodes at the start during which only the critics learn.
    pub critic_warmup_episodes: usize,
    /// Validate (and keep the best policy) every this many episodes; 0: only at the end.
    pub eval_every: usize,
    pub eval_episodes: usize,
    /// Seed of the validation episodes (the hierarchical refinement's).
    pub eval_seed: u64,
}

impl Default for FlatConfig {
    fn default() -> Self {
        let refine = RefineConfig::default();
        FlatConfig {
            episodes: refine.episodes,
            td3: Td3Config::default(),
            critic_warmup_episodes: refine.critic_warmup_episodes,
            eval_every: refine.eval_every,
            eval_episodes: refine.eval_episodes,
            eval_seed: refine.eval_seed,
        }
    }
}

/// One validation of the flat policy.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FlatValidation {
    /// Training episodes done before it.
    pub episode: usize,
    pub success_rate: f64,
    /// Average steps of the successful validation episodes.
    pub avg_steps: Option<f64>,
    /// Average return of the validation episodes.
    pub avg_reward: f64,
}

impl FlatValidation {
    /// Higher is better: success first, then fewer steps, then a higher return.
    fn score(&self) -> (f64, f64, f64) {
        (
            self.success_rate,
            -self.avg_steps.unwrap_or(f64::INFINITY),
            self.avg_reward,
        )
    }
}

/// What [`FlatTraining::run`] calls after each episode: the training, the episode, and the
/// validation that followed it, if any. An error stops the training.
pub type OnEpisode<'a> = dyn FnMut(&FlatTraining, &EpisodeRecord, Option<&FlatValidation>) -> candle_core::Result<()>
    + 'a;

/// The bookkeeping half of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FlatProgress {
    pub episode: usize,
    pub curve: Vec<EpisodeRecord>,
    pub validations: Vec<FlatValidation>,
    pub best: Option<FlatValidation>,
}

/// A training of the flat baseline in progress.
pub struct FlatTraining {
    cell: CellConfig,
    options: EnvOptions,
    config: FlatConfig,
    limits: StepLimits,
    /// As stored in the policy file (f32).
    normaliser: Normaliser,
    agent: Td3,
    buffer: ReplayBuffer,
    env: AssemblyEnv,
    rng: ChaCha8Rng,
    episode: usize,
    curve: Vec<EpisodeRecord>,
    validations: Vec<FlatValidation>,
    best: Option<(FlatValidation, VarMap)>,
    seed: u64,
}

/// The normaliser's values as a policy file stores them (f32).
fn stored(normaliser: &Normaliser) -> Normaliser {
    Normaliser {
        mean: normaliser.mean.map(|v| f64::from(v as f32)),
        std: normaliser.std.map(|v| f64::from(v as f32)),
    }
}

impl FlatTraining {
    /// A training from fresh weights. `normaliser` scales the actor's input (fit it on the
    /// demonstrations' states, [`Normaliser::fit`]).
    pub fn new(
        cell: &CellConfig,
        options: EnvOptions,
        normaliser: &Normaliser,
        config: FlatConfig,
        seed: u64,
    ) -> candle_core::Result<Self> {
        let td3 = Td3Config {
            seed: seed.wrapping_add(1),
            ..config.td3
        };
        let mut agent = Td3::new(12, ACTION_DIM, td3, None)?;
        agent.freeze_actor(config.critic_warmup_episodes > 0);
        Ok(FlatTraining {
            cell: cell.clone(),
            options,
            config,
            limits: step_limits(cell, PolicyInputs::Absolute),
            normaliser: stored(normaliser),
            agent,
            buffer: ReplayBuffer::new(config.td3.replay_capacity),
            env: AssemblyEnv::new(cell, options),
            rng: ChaCha8Rng::seed_from_u64(seed),
            episode: 0,
            curve: Vec::new(),
            validations: Vec::new(),
            best: None,
            seed,
        })
    }

    pub fn config(&self) -> &FlatConfig {
        &self.config
    }

    /// Training episodes done.
    pub fn episode(&self) -> usize {
        self.episode
    }

    pub fn curve(&self) -> &[EpisodeRecord] {
        &self.curve
    }

    pub fn validations(&self) -> &[FlatValidation] {
        &self.validations
    }

    pub fn normaliser(&self) -> &Normaliser {
        &self.normaliser
    }

    /// The actor's weights now (`actor.0.weight` …).
    pub fn actor_vars(&self) -> &VarMap {
        self.agent.actor_vars()
    }

    /// The best validated actor so far (and its validation), else the current one.
    pub fn best(&self) -> (Option<FlatValidation>, &VarMap) {
        match &self.best {
            Some((record, vars)) => (Some(*record), vars),
            None => (None, self.agent.actor_vars()),
        }
    }

    /// The flat policy file of an actor's weights with this training's normaliser and step
    /// limits; `provenance` adds metadata keys.
    pub fn policy_file(
        &self,
        actor: &VarMap,
        provenance: &BTreeMap<String, String>,
    ) -> Result<FlatPolicyFile, PolicyFileError> {
        let mut tensors = Vec::with_capacity(8);
        {
            let data = actor.data().lock().expect("var map lock");
            for layer in LAYER_NAMES {
                for part in ["weight", "bias"] {
                    let name = format!("actor.{layer}.{part}");
                    let Some(var) = data.get(&name) else {
                        return Err(PolicyFileError::MissingTensor {
                            name,
                            kind: PolicyKind::Flat,
                        });
                    };
                    let tensor = var.as_tensor();
                    let values = tensor
                        .flatten_all()
                        .and_then(|t| t.to_vec1::<f32>())
                        .map_err(|e| PolicyFileError::UnexpectedTensor {
                            name: name.clone(),
                            reason: e.to_string(),
                        })?;
                    tensors.push((name, tensor.dims().to_vec(), values));
                }
            }
        }
        let n = &self.normaliser;
        tensors.push((
            "obs_mean".into(),
            vec![12],
            n.mean.map(|v| v as f32).to_vec(),
        ));
        tensors.push(("obs_std".into(), vec![12], n.std.map(|v| v as f32).to_vec()));
        let mut metadata =
            FlatPolicyFile::standard_metadata(self.limits.position_mm, self.limits.orientation_deg);
        metadata.extend(provenance.clone());
        FlatPolicyFile::new(tensors, metadata)
    }

    /// The current actor as a runnable policy; refused (an error) when its weights are not
    /// finite.
    fn policy(&self) -> candle_core::Result<FlatPolicy> {
        let file = self
            .policy_file(self.agent.actor_vars(), &BTreeMap::new())
            .map_err(|e| {
                candle_core::Error::Msg(format!(
                    "the actor is not a valid policy after episode {}: {e}",
                    self.episode
                ))
            })?;
        Ok(FlatPolicy::from_file(&file))
    }

    /// Runs one training episode with exploration, then the agent's updates.
    pub fn train_episode(&mut self) -> candle_core::Result<EpisodeRecord> {
        self.agent
            .freeze_actor(self.episode < self.config.critic_warmup_episodes);
        let mut policy = self.policy()?;
        // The hierarchical refinement's episode seeds: both see the same initial conditions.
        let seed = episode_seed(self.seed ^ 0x7D3, self.episode);
        let mut observation = self
            .env
            .reset(seed)
            .map_err(|e| candle_core::Error::Msg(format!("twin reset failed: {e}")))?;
        let sigma = self.config.td3.exploration_noise;
        // The last transition's state, action and reward so far (its next state is not known
        // until the next fresh frame).
        let mut pending: Option<([f32; 12], [f32; 6], f64)> = None;
        let mut taken = 0usize;
        let mut return_ = 0.0;
        let (success, steps) = loop {
            let mut action = [0.0f64; 6];
            if observation.measurement_fresh {
                let x = policy.normalise(&observation.state);
                if let Some((s, a, r)) = pending.take() {
                    self.buffer.push(transition(s, a, r, x, false));
                }
                let clean = policy.actor(&x);
                if !x.iter().chain(&clean).all(|v| v.is_finite()) {
                    candle_core::bail!(
                        "the actor's input or output is not finite at episode {}",
                        self.episode
                    );
                }
                let mut a = [0f32; 6];
                for (ai, ci) in a.iter_mut().zip(clean) {
                    let noise: f64 = self.rng.sample(StandardNormal);
                    *ai = (f64::from(ci) + sigma * noise).clamp(-1.0, 1.0) as f32;
                }
                action = policy.to_move(&a);
                taken += 1;
                pending = Some((x, a, 0.0));
            }
            let result = self
                .env
                .step(&Move::from_array(action))
                .map_err(|e| candle_core::Error::Msg(format!("twin step failed: {e}")))?;
            return_ += result.reward.total;
            if let Some((_, _, r)) = pending.as_mut() {
                *r += result.reward.total;
            }
            if let Some(outcome) = result.outcome {
                if let Some((s, a, r)) = pending.take() {
                    let x = policy.normalise(&result.observation.state);
                    self.buffer.push(transition(s, a, r, x, true));
                }
                break (outcome == Outcome::Success, self.env.steps());
            }
            observation = result.observation;
        };
        for _ in 0..taken {
            self.agent.update(&self.buffer)?;
        }
        let record = EpisodeRecord {
            episode: self.episode,
            return_,
            success,
            steps,
        };
        self.curve.push(record);
        self.episode += 1;
        Ok(record)
    }

    /// Evaluates the current policy on the validation episodes (all cores) and keeps it if it
    /// is the best so far.
    pub fn validate(&mut self) -> candle_core::Result<FlatValidation> {
        // As the policy runs once deployed, with every rule of the cell's (docs/policy-rules.md).
        let policy = LearnedPolicy::flat(self.policy()?).with_rules(&self.cell.rules);
        let factory: ControllerFactory = Box::new(move || Box::new(policy.clone()));
        let (summary, _) = eval::evaluate(
            &self.cell,
            self.options,
            self.config.eval_episodes,
            self.config.eval_seed,
            &factory,
            &|_| {},
        );
        let record = FlatValidation {
            episode: self.episode,
            success_rate: summary.success_rate,
            avg_steps: summary.avg_steps,
            avg_reward: summary.avg_reward,
        };
        self.validations.push(record);
        let better = match &self.best {
            None => true,
            Some((best, _)) => record.score() > best.score(),
        };
        if better {
            self.best = Some((record, clone_varmap(self.agent.actor_vars())?));
        }
        Ok(record)
    }

    /// Trains up to `config.episodes`, validating every `eval_every` episodes and at the end.
    /// `on_episode` sees the training after each episode, with the episode and the validation
    /// that followed it, if any; an error it returns stops the training.
    pub fn run(&mut self, on_episode: &mut OnEpisode<'_>) -> candle_core::Result<()> {
        while self.episode < self.config.episodes {
            let record = self.train_episode()?;
            let every = self.config.eval_every;
            let validation = if every > 0 && self.episode.is_multiple_of(every) {
                Some(self.validate()?)
            } else {
                None
            };
            on_episode(self, &record, validation.as_ref())?;
        }
        if self.validations.last().map(|v| v.episode) != Some(self.episode) {
            self.validate()?;
        }
        Ok(())
    }

    /// Everything needed to resume: the agent's networks, the best actor, the normaliser.
    pub fn checkpoint(&self) -> (HashMap<String, Tensor>, FlatProgress) {
        let mut tensors = HashMap::new();
        for (name, tensor) in self.agent.checkpoint() {
            tensors.insert(format!("agent.{name}"), tensor);
        }
        {
            let data = self.best().1.data().lock().expect("var map lock");
            for (name, var) in data.iter() {
                tensors.insert(format!("best.{name}"), var.as_tensor().clone());
            }
        }
        for (name, values) in [
            ("obs_mean", self.normaliser.mean),
            ("obs_std", self.normaliser.std),
        ] {
            let values = values.map(|v| v as f32);
            let tensor = Tensor::from_slice(&values, 12, &Device::Cpu).expect("12 values");
            tensors.insert(format!("normaliser.{name}"), tensor);
        }
        let progress = FlatProgress {
            episode: self.episode,
            curve: self.curve.clone(),
            validations: self.validations.clone(),
            best: self.best.as_ref().map(|(r, _)| *r),
        };
        (tensors, progress)
    }

    /// Continues from a [`FlatTraining::checkpoint`]. The replay buffer starts empty (it is not
    /// saved) and the exploration noise is re-seeded from the episode reached.
    pub fn restore(
        &mut self,
        tensors: &HashMap<String, Tensor>,
        progress: FlatProgress,
    ) -> candle_core::Result<()> {
        let take = |prefix: &str| -> HashMap<String, Tensor> {
            tensors
                .iter()
                .filter_map(|(k, v)| k.strip_prefix(prefix).map(|n| (n.to_string(), v.clone())))
                .collect()
        };
        self.agent.restore(&take("agent."))?;
        self.best = match progress.best {
            Some(record) => {
                let vars = clone_varmap(self.agent.actor_vars())?;
                let best = take("best.");
                for (name, var) in vars.data().lock().expect("var map lock").iter() {
                    let Some(value) = best.get(name) else {
                        candle_core::bail!("checkpoint has no `best.{name}`");
                    };
                    var.set(value)?;
                }
                Some((record, vars))
            }
            None => None,
        };
        let normaliser = take("normaliser.");
        let array = |name: &str| -> candle_core::Result<[f64; 12]> {
            let Some(t) = normaliser.get(name) else {
                candle_core::bail!("checkpoint has no `normaliser.{name}`");
            };
            let v = t.to_vec1::<f32>()?;
            if v.len() != 12 {
                candle_core::bail!("`normaliser.{name}` has {} values, expected 12", v.len());
            }
            Ok(std::array::from_fn(|i| f64::from(v[i])))
        };
        self.normaliser = Normaliser {
            mean: array("obs_mean")?,
            std: array("obs_std")?,
        };
        self.episode = progress.episode;
        self.curve = progress.curve;
        self.validations = progress.validations;
        self.rng = ChaCha8Rng::seed_from_u64(self.seed ^ self.episode as u64);
        Ok(())
    }
}

/// Trains the flat baseline from the demonstrations' states (for the normaliser) to the end;
/// `on_episode` reports progress after each episode (with the validation that followed it).
pub fn train_flat(
    cell: &CellConfig,
    options: EnvOptions,
    demos: &[DemoEpisode],
    config: FlatConfig,
    seed: u64,
    on_episode: &mut dyn FnMut(&EpisodeRecord, Option<&FlatValidation>),
) -> candle_core::Result<FlatTraining> {
    let mut training = FlatTraining::new(cell, options, &Normaliser::fit(demos), config, seed)?;
    training.run(&mut |_, record, validation| {
        on_episode(record, validation);
        Ok(())
    })?;
    Ok(training)
}

fn transition(s: [f32; 12], a: [f32; 6], r: f64, next: [f32; 12], done: bool) -> Transition {
    Transition {
        state: s.to_vec(),
        action: a.to_vec(),
        reward: r as f32,
        next_state: next.to_vec(),
        done,
        ..Transition::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learning::demos::record_expert;
    use crate::policy::Controller;

    fn tiny_config(episodes: usize) -> FlatConfig {
        FlatConfig {
            episodes,
            td3: Td3Config {
                hidden: 16,
                batch_size: 4,
                ..Td3Config::default()
            },
            critic_warmup_episodes: 1,
            eval_every: 2,
            eval_episodes: 2,
            ..FlatConfig::default()
        }
    }

    fn snapshot(vars: &VarMap) -> Vec<(String, Vec<f32>)> {
        let data = vars.data().lock().unwrap();
        let mut out: Vec<_> = data
            .iter()
            .map(|(k, v)| {
                let values = v.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
                (k.clone(), values)
            })
            .collect();
        out.sort_by(|a, b| a.0.cmp(&b.0));
        out
    }

    fn tiny_run(seed: u64, reported: &mut Vec<usize>) -> FlatTraining {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let demos = record_expert(&cell, options, 3, 1);
        train_flat(
            &cell,
            options,
            &demos,
            tiny_config(3),
            seed,
            &mut |record, _| reported.push(record.episode),
        )
        .unwrap()
    }

    #[test]
    fn a_few_episodes_are_deterministic_under_a_seed() {
        let (mut first, mut second, mut other) = (vec![], vec![], vec![]);
        let a = tiny_run(11, &mut first);
        let b = tiny_run(11, &mut second);
        let c = tiny_run(12, &mut other);
        assert_eq!(first, vec![0, 1, 2]);
        assert_eq!(second, first);
        assert_eq!(a.curve(), b.curve());
        assert_eq!(a.validations(), b.validations());
        // Validated after episode 2 (every 2) and at the end (3).
        assert_eq!(
            a.validations()
                .iter()
                .map(|v| v.episode)
                .collect::<Vec<_>>(),
            vec![2, 3]
        );
        // The actor moved (it learnt after the one warm-up episode) and identically so.
        assert_eq!(snapshot(a.actor_vars()), snapshot(b.actor_vars()));
        assert_ne!(snapshot(a.actor_vars()), snapshot(c.actor_vars()));
        let fresh = FlatTraining::new(
            &CellConfig::reference(),
            EnvOptions::from_cell(&CellConfig::reference()),
            a.normaliser(),
            tiny_config(3),
            11,
        )
        .unwrap();
        assert_ne!(snapshot(a.actor_vars()), snapshot(fresh.actor_vars()));
        // The files written from them are identical, and load as the `td3` controller.
        let provenance = BTreeMap::from([("seed".to_string(), "11".to_string())]);
        let (_, best_a) = a.best();
        let (_, best_b) = b.best();
        let file = a.policy_file(best_a, &provenance).unwrap();
        assert_eq!(
            file.to_bytes(),
            b.policy_file(best_b, &provenance).unwrap().to_bytes()
        );
        assert_eq!(file.width(), 16);
        assert_eq!(file.raw_metadata()["seed"], "11");
        assert_eq!(FlatPolicy::from_file(&file).name(), "td3");
    }

    #[test]
    fn the_normaliser_comes_from_the_demonstrations_states() {
        let mut reported = vec![];
        let run = tiny_run(5, &mut reported);
        let cell = CellConfig::reference();
        let demos = record_expert(&cell, EnvOptions::from_cell(&cell), 3, 1);
        assert_eq!(*run.normaliser(), stored(&Normaliser::fit(&demos)));
    }

    #[test]
    fn a_checkpoint_resumes_and_non_finite_weights_stop_the_training() {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let demos = record_expert(&cell, options, 3, 1);
        let normaliser = Normaliser::fit(&demos);
        let mut run = FlatTraining::new(&cell, options, &normaliser, tiny_config(2), 4).unwrap();
        run.train_episode().unwrap();
        run.validate().unwrap();
        let (tensors, progress) = run.checkpoint();
        let mut resumed = FlatTraining::new(
            &cell,
            options,
            &Normaliser {
                mean: [0.0; 12],
                std: [1.0; 12],
            },
            tiny_config(2),
            4,
        )
        .unwrap();
        resumed.restore(&tensors, progress.clone()).unwrap();
        assert_eq!(resumed.episode(), 1);
        assert_eq!(resumed.curve(), run.curve());
        assert_eq!(resumed.normaliser(), run.normaliser());
        assert_eq!(snapshot(resumed.actor_vars()), snapshot(run.actor_vars()));
        assert_eq!(snapshot(resumed.best().1), snapshot(run.best().1));

        // A diverged actor (NaN weights) stops the next episode with a message naming it.
        let mut broken = tensors.clone();
        let w = &tensors["agent.online.actor.2.weight"];
        let nan = Tensor::full(f32::NAN, w.dims(), &Device::Cpu).unwrap();
        broken.insert("agent.online.actor.2.weight".into(), nan);
        resumed.restore(&broken, progress).unwrap();
        let error = resumed.train_episode().unwrap_err().to_string();
        assert!(
            error.contains("not a valid policy") && error.contains("actor.2.weight"),
            "{error}"
        );
    }
}
