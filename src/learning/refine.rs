//! TD3 refinement of the hierarchy in the twin (paper §3.3, Algorithm 3): the LSTM selector is
//! fixed; each actor is one TD3 agent that starts from its BC weights and learns from the steps
//! it took, with its local reward (position agent: λg·R_g + λP·r_P + λerr·r_err + step penalty;
//! orientation agent: the same with λO·r_O).
//!
//! The moves are the policy file's forward pass with Gaussian exploration noise on the acting
//! actor's tanh output. Training episodes run [`RefineConfig::parallel_episodes`] at a time on
//! all cores; updates run after each episode, one per step the agent took (TD3's one update
//! per environment step). By default each agent stays within a trust region around its
//! BC actor ([`TRUST_REGION`]): plain TD3 undoes behaviour cloning here within 20 episodes. The
//! policy is evaluated every `eval_every` episodes on [`VALIDATION_EPISODES`] validation
//! episodes (seeds disjoint from the report's), as it runs once deployed (steered against the
//! learned drift), and the best one is kept (decision 0029).

mod episode;
pub mod step_size;

use super::bc::init_actor;
use super::pipeline::actor_prefix;
use super::td3::{ReplayBuffer, Td3, Td3Config, clone_varmap};
use crate::config::cell::CellConfig;
use crate::policy::Actor;
use crate::policy::eval::{self, EvalSummary, episode_seed};
use crate::policy::hierarchical::{HierarchicalPolicy, PolicyConfig};
use crate::policy::inputs::PolicyInputs;
use crate::policy::learned::LearnedPolicy;
use crate::policy::record::DEFAULT_DEMONSTRATOR;
use crate::sim::randomise::{CellRanges, cell_for};
use crate::sim::{AssemblyEnv, EnvOptions, RewardTerms};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use episode::{Driver, Gathered};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::collections::VecDeque;
use step_size::StepSizeConfig;

/// The default trust region around the BC actors (tanh units, 6 µm of a full 3 mm step). Plain
/// TD3 wrecks the BC policy within 20 episodes; regions of 0.001 to 0.01 keep it over 500
/// episodes, and none of them raised its success measurably (docs/learning-reference.md).
pub const TRUST_REGION: f64 = 0.002;

/// Episodes of each validation by default. The refinement keeps its best validation, and
/// TD3's gain over BC is about half a step per episode. Steps per episode vary with σ ≈ 2.4,
/// so a 200-episode mean varies by about 0.17 from the episodes drawn alone: enough to keep
/// a worse policy. With kept robots, 200 episodes are also many on robots whose drift the
/// cell is still learning. 2000 bring the variation to about 0.05 for about 15 s of a
/// 500-episode run (decision 0029).
pub const VALIDATION_EPISODES: usize = 2000;

/// Refinement settings. TD3's own defaults are Table 1's; the exploration noise (not in Table
/// 1) is 0.002, since the BC policy fails one training episode in three at 0.01.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineConfig {
    pub episodes: usize,
    pub td3: Td3Config,
    /// Episodes at the start during which only the critics learn (the actors are frozen), so
    /// that the first actor updates follow a critic that knows the BC policy's values.
    pub critic_warmup_episodes: usize,
    /// Evaluate (and keep the best policy) every this many episodes; 0: only at the end.
    pub eval_every: usize,
    /// Episodes of each validation ([`VALIDATION_EPISODES`] by default).
    pub eval_episodes: usize,
    /// Seed of the validation episodes.
    pub eval_seed: u64,
    /// What the policy reads (`policy::inputs`): the BC stage's choice, kept.
    pub inputs: PolicyInputs,
    /// Each training episode on a cell of its own, drawn around the given one (domain
    /// randomisation); validation stays on the given cell.
    pub randomise: Option<CellRanges>,
    /// The critics also read the true pose, as the policy's inputs of a perfect camera
    /// (asymmetric actor-critic: only the twin knows it, and only training needs it).
    pub asymmetric: bool,
    /// Episodes of `demonstrator` recorded into each agent's demonstration buffer before
    /// training (sampled beside the online data, [`Td3Config::demo_fraction`]); 0: none.
    pub demonstrations: usize,
    /// The scripted expert that records them (one of `policy::record::DEMONSTRATORS`).
    pub demonstrator: &'static str,
    /// Critic updates on the demonstrations alone, with the actors frozen, before the first
    /// training episode.
    pub critic_pretraining_updates: usize,
    /// Training episodes run at once, each on its own twin, with the policy as it stood before
    /// the first of them; the agents then learn from them one by one, as from episodes run in
    /// turn. 1: every episode with the policy updated after the one before.
    pub parallel_episodes: usize,
    /// A third agent refines the selector's step size ([`step_size`]); `None`: the paper's
    /// refinement of the two actors only.
    pub step_size: Option<StepSizeConfig>,
}

impl Default for RefineConfig {
    fn default() -> Self {
        RefineConfig {
            episodes: 500,
            td3: Td3Config {
                hidden: 128,
                exploration_noise: 0.002,
                trust_region: Some(TRUST_REGION),
                ..Td3Config::default()
            },
            critic_warmup_episodes: 20,
            eval_every: 50,
            eval_episodes: VALIDATION_EPISODES,
            eval_seed: 0x7A11_DA7E,
            inputs: PolicyInputs::Absolute,
            randomise: None,
            asymmetric: false,
            demonstrations: 0,
            demonstrator: DEFAULT_DEMONSTRATOR,
            critic_pretraining_updates: 0,
            parallel_episodes: PARALLEL_EPISODES,
            step_size: None,
        }
    }
}

/// Training episodes run at once by default ([`RefineConfig::parallel_episodes`]).
pub const PARALLEL_EPISODES: usize = 8;

impl RefineConfig {
    /// TD3 that learns beside its demonstrator (docs/learning-reference.md): asymmetric critics,
    /// `demonstrations` episodes of `demonstrator` in the replay, critics pre-trained on them,
    /// and Q-filtered TD3+BC actor updates (within the trust region, if there is one).
    pub fn beside_demonstrator(self, demonstrator: &'static str, demonstrations: usize) -> Self {
        RefineConfig {
            td3: Td3Config {
                demo_regularisation: Some(DEMO_REGULARISATION),
                ..self.td3
            },
            asymmetric: true,
            demonstrations,
            demonstrator,
            critic_pretraining_updates: CRITIC_PRETRAINING_UPDATES,
            ..self
        }
    }
}

/// α of TD3+BC (Fujimoto & Gu 2021's value).
pub const DEMO_REGULARISATION: f64 = 2.5;

/// Critic updates on the demonstrations before the actors move.
pub const CRITIC_PRETRAINING_UPDATES: usize = 2000;

/// One training episode, as the learning curve records it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    pub episode: usize,
    #[serde(rename = "return")]
    pub return_: f64,
    pub success: bool,
    pub steps: u32,
}

/// One validation of the policy during refinement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ValidationRecord {
    /// Training episodes done before it.
    pub episode: usize,
    pub success_rate: f64,
    pub avg_steps: Option<f64>,
}

impl ValidationRecord {
    /// Higher is better: success first, then fewer steps.
    fn score(&self) -> (f64, f64) {
        (self.success_rate, -self.avg_steps.unwrap_or(f64::INFINITY))
    }
}

/// The local reward of an actor's agent.
pub fn local_reward(actor: Actor, terms: &RewardTerms) -> f64 {
    let own = match actor {
        Actor::Position => terms.position,
        Actor::Orientation => terms.orientation,
    };
    terms.global + own + terms.error + terms.step
}

/// A refinement in progress.
pub struct Refinement {
    cell: CellConfig,
    options: EnvOptions,
    config: RefineConfig,
    /// The whole policy; the actors' weights are copied in from the agents before each use.
    policy_vars: VarMap,
    policy_config: PolicyConfig,
    agents: [Td3; 2],
    buffers: [ReplayBuffer; 2],
    /// The step-size agent ([`RefineConfig::step_size`]) and its replay.
    step_agent: Option<Td3>,
    step_buffer: ReplayBuffer,
    /// The demonstrator's transitions, per agent ([`RefineConfig::demonstrations`]).
    demo_buffers: [ReplayBuffer; 2],
    /// Episodes run at once and not yet learnt from, in order.
    ahead: VecDeque<Gathered>,
    /// The kept robots (`EnvOptions::kept_robots` ≥ 1), each a twin that remembers its drift
    /// from one episode to the next: episode i runs on robot i mod their number. Empty: every
    /// episode on a twin of its own with a robot new to the cell.
    robots: Vec<AssemblyEnv>,
    episode: usize,
    curve: Vec<EpisodeRecord>,
    validations: Vec<ValidationRecord>,
    best: Option<(ValidationRecord, VarMap)>,
    seed: u64,
}

/// The twins of the kept robots of a refinement seeded with `seed`; when randomising, each on
/// a cell of its own.
fn kept_robots(
    cell: &CellConfig,
    options: EnvOptions,
    randomise: Option<&CellRanges>,
    seed: u64,
) -> Vec<AssemblyEnv> {
    (0..options.kept_robots as usize)
        .map(|robot| {
            let kept = EnvOptions {
                robot_seed: eval::robot_seed(seed ^ 0x0DE7_AB07, robot),
                ..options
            };
            let (cell, kept) = cell_for(cell, &kept, randomise, kept.robot_seed);
            AssemblyEnv::new(&cell, kept)
        })
        .collect()
}

fn agent_index(actor: Actor) -> usize {
    match actor {
        Actor::Position => 0,
        Actor::Orientation => 1,
    }
}

const ACTORS: [Actor; 2] = [Actor::Position, Actor::Orientation];

impl Refinement {
    /// Starts from a policy's weights (`policy_vars`: every tensor of a policy file). With
    /// `from_bc` false the actors are re-initialised (TD3 without behaviour cloning).
    pub fn new(
        cell: &CellConfig,
        options: EnvOptions,
        policy_vars: VarMap,
        config: RefineConfig,
        from_bc: bool,
        seed: u64,
    ) -> candle_core::Result<Self> {
        let policy_config = {
            let data = policy_vars.data().lock().expect("var map lock");
            let dim = |name: &str, axis: usize| -> candle_core::Result<usize> {
                data.get(name)
                    .ok_or_else(|| candle_core::Error::Msg(format!("policy has no `{name}`")))?
                    .as_tensor()
                    .dim(axis)
            };
            PolicyConfig {
                hidden_size: dim("high.lstm.weight_hh_l0", 1)?,
                actor_width: dim("pos.0.weight", 0)?,
                step_limit_mm: cell.steps.position_mm,
                step_limit_deg: cell.steps.orientation_deg,
                inputs: config.inputs,
            }
        };
        let mut agents = Vec::with_capacity(2);
        for (k, actor) in ACTORS.into_iter().enumerate() {
            let td3 = Td3Config {
                seed: seed.wrapping_add(k as u64 + 1),
                // A region around freshly initialised actors would only stop them learning.
                trust_region: config.td3.trust_region.filter(|_| from_bc),
                privileged_dim: if config.asymmetric { 12 } else { 0 },
                ..config.td3
            };
            let init = if from_bc {
                rename(&policy_vars, actor_prefix(actor), "actor")?
            } else {
                // Fresh weights of the policy's width (PyTorch's initialisation, seeded).
                let vars = VarMap::new();
                let mut rng = ChaCha8Rng::seed_from_u64(td3.seed ^ 0xA11CE);
                init_actor(&vars, "actor", policy_config.actor_width, &mut rng)?;
                vars
            };
            let mut agent = Td3::new(12, 3, td3, Some(init))?;
            agent.freeze_actor(config.critic_warmup_episodes > 0);
            agents.push(agent);
        }
        let agents: [Td3; 2] = agents.try_into().map_err(|_| unreachable_agents())?;
        let step_agent = match config.step_size {
            Some(step) => {
                let td3 = Td3Config {
                    seed: seed.wrapping_add(3),
                    ..config.td3
                };
                let privileged = if config.asymmetric { 24 } else { 12 };
                let mut agent = step_size::agent(&policy_vars, td3, step, privileged)?;
                agent.freeze_actor(config.critic_warmup_episodes > 0);
                Some(agent)
            }
            None => None,
        };
        let mut refinement = Refinement {
            cell: cell.clone(),
            options,
            config,
            policy_config,
            buffers: [
                ReplayBuffer::new(config.td3.replay_capacity),
                ReplayBuffer::new(config.td3.replay_capacity),
            ],
            demo_buffers: [
                ReplayBuffer::new(config.td3.replay_capacity),
                ReplayBuffer::new(config.td3.replay_capacity),
            ],
            step_agent,
            step_buffer: ReplayBuffer::new(config.td3.replay_capacity),
            ahead: VecDeque::new(),
            robots: kept_robots(cell, options, config.randomise.as_ref(), seed),
            episode: 0,
            curve: Vec::new(),
            validations: Vec::new(),
            best: None,
            seed,
            agents,
            policy_vars,
        };
        refinement.sync_actors()?;
        refinement.learn_from_demonstrations()?;
        Ok(refinement)
    }

    pub fn config(&self) -> &RefineConfig {
        &self.config
    }

    /// Training episodes done.
    pub fn episode(&self) -> usize {
        self.episode
    }

    pub fn curve(&self) -> &[EpisodeRecord] {
        &self.curve
    }

    pub fn validations(&self) -> &[ValidationRecord] {
        &self.validations
    }

    /// The best validated policy so far (and its validation), else the current one.
    pub fn best(&self) -> (Option<ValidationRecord>, &VarMap) {
        match &self.best {
            Some((record, vars)) => (Some(*record), vars),
            None => (None, &self.policy_vars),
        }
    }

    /// Copies each agent's actor into the policy's weights.
    fn sync_actors(&self) -> candle_core::Result<()> {
        {
            let policy = self.policy_vars.data().lock().expect("var map lock");
            for actor in ACTORS {
                let agent = self.agents[agent_index(actor)].actor_vars();
                let data = agent.data().lock().expect("var map lock");
                for (name, var) in data.iter() {
                    let target = name.replacen("actor", actor_prefix(actor), 1);
                    policy[&target].set(var.as_tensor())?;
                }
            }
        }
        match &self.step_agent {
            Some(agent) => step_size::sync(agent, &self.policy_vars),
            None => Ok(()),
        }
    }

    fn policy(&self) -> candle_core::Result<HierarchicalPolicy> {
        policy_from_vars(&self.policy_vars, &self.policy_config)
    }

    /// Records [`RefineConfig::demonstrations`] episodes of the demonstrator into the
    /// demonstration buffers, then pre-trains the critics on them with the actors frozen.
    fn learn_from_demonstrations(&mut self) -> candle_core::Result<()> {
        if self.config.demonstrations == 0 {
            return Ok(());
        }
        let episodes = self.with_robots(|refinement, robots| {
            refinement.gather_on(robots, 0..refinement.config.demonstrations, &|index| {
                let seed = episode_seed(refinement.seed ^ 0xDE_3057, index);
                Ok((Driver::Demonstrator, seed))
            })
        })?;
        for episode in episodes {
            for (buffer, transitions) in self.demo_buffers.iter_mut().zip(episode.transitions) {
                transitions.into_iter().for_each(|t| buffer.push(t));
            }
        }
        let no_online_data = ReplayBuffer::new(1);
        for (agent, demos) in self.agents.iter_mut().zip(&self.demo_buffers) {
            agent.freeze_actor(true);
            for _ in 0..self.config.critic_pretraining_updates {
                agent.update_with(&no_online_data, demos)?;
            }
        }
        Ok(())
    }

    /// Calls `f` with the refinement and its kept robots, lent apart so that episodes can run
    /// on the robots while reading the rest.
    fn with_robots<T>(&mut self, f: impl FnOnce(&Self, &mut [AssemblyEnv]) -> T) -> T {
        let mut robots = std::mem::take(&mut self.robots);
        let out = f(self, &mut robots);
        self.robots = robots;
        out
    }

    /// Runs one training episode with exploration, then the agents' updates.
    pub fn train_episode(&mut self) -> candle_core::Result<EpisodeRecord> {
        let warm = self.episode >= self.config.critic_warmup_episodes;
        for agent in self.agents.iter_mut().chain(self.step_agent.as_mut()) {
            agent.freeze_actor(!warm);
        }
        if self.ahead.is_empty() {
            let left = self.config.episodes.saturating_sub(self.episode).max(1);
            let count = self.config.parallel_episodes.clamp(1, left);
            let first = self.episode;
            self.ahead = self
                .with_robots(|refinement, robots| {
                    refinement.gather_policy_episodes(robots, first, count)
                })?
                .into();
        }
        let gathered = self
            .ahead
            .pop_front()
            .ok_or_else(|| candle_core::Error::Msg("no training episode was gathered".into()))?;
        for (k, transitions) in gathered.transitions.into_iter().enumerate() {
            let taken = transitions.len();
            transitions
                .into_iter()
                .for_each(|t| self.buffers[k].push(t));
            for _ in 0..taken {
                self.agents[k].update_with(&self.buffers[k], &self.demo_buffers[k])?;
            }
        }
        if let Some(agent) = self.step_agent.as_mut() {
            let taken = gathered.step_transitions.len();
            gathered
                .step_transitions
                .into_iter()
                .for_each(|t| self.step_buffer.push(t));
            for _ in 0..taken {
                agent.update(&self.step_buffer)?;
            }
        }
        self.sync_actors()?;
        let record = EpisodeRecord {
            episode: self.episode,
            return_: gathered.return_,
            success: gathered.success,
            steps: gathered.steps,
        };
        self.curve.push(record);
        self.episode += 1;
        Ok(record)
    }

    /// Evaluates the current policy on the validation episodes and keeps it if it is the best.
    pub fn validate(&mut self) -> candle_core::Result<ValidationRecord> {
        let summary = evaluate_vars(
            &self.cell,
            self.options,
            &self.policy_vars,
            &self.policy_config,
            self.config.eval_episodes,
            self.config.eval_seed,
        )?;
        let record = ValidationRecord {
            episode: self.episode,
            success_rate: summary.success_rate,
            avg_steps: summary.avg_steps,
        };
        self.validations.push(record);
        let better = match &self.best {
            None => true,
            Some((best, _)) => record.score() > best.score(),
        };
        if better {
            self.best = Some((record, clone_varmap(&self.policy_vars)?));
        }
        Ok(record)
    }

    /// Everything needed to resume: the policy, the best policy, both agents' networks.
    pub fn checkpoint(&self) -> candle_core::Result<(HashMap<String, Tensor>, RefineProgress)> {
        let mut tensors = HashMap::new();
        for (prefix, vars) in [("policy.", &self.policy_vars), ("best.", self.best().1)] {
            let data = vars.data().lock().expect("var map lock");
            for (name, var) in data.iter() {
                tensors.insert(format!("{prefix}{name}"), var.as_tensor().clone());
            }
        }
        for (k, agent) in self.agents.iter().chain(&self.step_agent).enumerate() {
            for (name, tensor) in agent.checkpoint() {
                tensors.insert(format!("agent{k}.{name}"), tensor);
            }
        }
        let progress = RefineProgress {
            episode: self.episode,
            curve: self.curve.clone(),
            validations: self.validations.clone(),
            best: self.best.as_ref().map(|(r, _)| *r),
        };
        Ok((tensors, progress))
    }

    /// Continues from a [`Refinement::checkpoint`]. The replay buffers start empty (they are
    /// not saved), and episodes gathered ahead of the checkpoint are gathered again with its
    /// policy; each episode's exploration noise is seeded from its index.
    pub fn restore(
        &mut self,
        tensors: &HashMap<String, Tensor>,
        progress: RefineProgress,
    ) -> candle_core::Result<()> {
        let take = |prefix: &str| -> HashMap<String, Tensor> {
            tensors
                .iter()
                .filter_map(|(k, v)| k.strip_prefix(prefix).map(|n| (n.to_string(), v.clone())))
                .collect()
        };
        set_vars(&self.policy_vars, &take("policy."))?;
        for (k, agent) in self
            .agents
            .iter_mut()
            .chain(self.step_agent.as_mut())
            .enumerate()
        {
            agent.restore(&take(&format!("agent{k}.")))?;
        }
        self.best = match progress.best {
            Some(record) => {
                let vars = clone_varmap(&self.policy_vars)?;
                set_vars(&vars, &take("best."))?;
                Some((record, vars))
            }
            None => None,
        };
        self.episode = progress.episode;
        self.curve = progress.curve;
        self.validations = progress.validations;
        self.ahead.clear();
        self.sync_actors()
    }
}

/// The bookkeeping half of a refinement checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineProgress {
    pub episode: usize,
    pub curve: Vec<EpisodeRecord>,
    pub validations: Vec<ValidationRecord>,
    pub best: Option<ValidationRecord>,
}

fn unreachable_agents() -> candle_core::Error {
    candle_core::Error::Msg("two agents expected".into())
}

/// The tensors `{from}.*` of `vars`, renamed `{to}.*`, in a new map.
fn rename(vars: &VarMap, from: &str, to: &str) -> candle_core::Result<VarMap> {
    let out = VarMap::new();
    {
        let source = vars.data().lock().expect("var map lock");
        let mut target = out.data().lock().expect("var map lock");
        for (name, var) in source.iter() {
            if let Some(rest) = name.strip_prefix(&format!("{from}.")) {
                target.insert(
                    format!("{to}.{rest}"),
                    Var::from_tensor(&var.as_tensor().copy()?)?,
                );
            }
        }
    }
    Ok(out)
}

fn set_vars(vars: &VarMap, tensors: &HashMap<String, Tensor>) -> candle_core::Result<()> {
    let data = vars.data().lock().expect("var map lock");
    for (name, var) in data.iter() {
        let Some(value) = tensors.get(name) else {
            candle_core::bail!("checkpoint has no `{name}`");
        };
        var.set(value)?;
    }
    Ok(())
}

/// A runnable policy from a `VarMap` of policy-file tensors.
pub fn policy_from_vars(
    vars: &VarMap,
    config: &PolicyConfig,
) -> candle_core::Result<HierarchicalPolicy> {
    HierarchicalPolicy::load(
        VarBuilder::from_varmap(vars, DType::F32, &Device::Cpu),
        config,
    )
}

/// Evaluates a policy held in a `VarMap` (all cores).
pub fn evaluate_vars(
    cell: &CellConfig,
    options: EnvOptions,
    vars: &VarMap,
    config: &PolicyConfig,
    episodes: usize,
    seed: u64,
) -> candle_core::Result<EvalSummary> {
    // As the policy runs once deployed, with every rule of the cell's (docs/policy-rules.md).
    let policy =
        LearnedPolicy::hierarchical(policy_from_vars(vars, config)?).with_rules(&cell.rules);
    let factory: crate::policy::ControllerFactory = Box::new(move || Box::new(policy.clone()));
    Ok(eval::evaluate(cell, options, episodes, seed, &factory, &|_| {}).0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learning::bc::BcConfig;
    use crate::learning::demos::record_expert;
    use crate::learning::pipeline::{behaviour_clone, step_limits, train_lstm};
    use crate::learning::selector::SelectorConfig;

    #[test]
    fn each_agent_gets_the_global_terms_and_its_own_local_term() {
        let terms = RewardTerms {
            global: 50.0,
            position: 0.3,
            orientation: 0.2,
            error: -2.0,
            step: -0.01,
            total: 48.49,
        };
        assert!((local_reward(Actor::Position, &terms) - 48.29).abs() < 1e-12);
        assert!((local_reward(Actor::Orientation, &terms) - 48.19).abs() < 1e-12);
    }

    fn tiny_refinement(from_bc: bool) -> Refinement {
        tiny_refinement_with(from_bc, |config| config)
    }

    fn tiny_refinement_with(
        from_bc: bool,
        adjust: impl Fn(RefineConfig) -> RefineConfig,
    ) -> Refinement {
        tiny_refinement_on(0, from_bc, adjust)
    }

    /// A tiny refinement whose episodes are shared among `robots` kept robots (0: none).
    fn tiny_refinement_on(
        robots: u32,
        from_bc: bool,
        adjust: impl Fn(RefineConfig) -> RefineConfig,
    ) -> Refinement {
        let cell = CellConfig::reference();
        let options = EnvOptions::from_cell(&cell);
        let demos = record_expert(&cell, options, 4, 1);
        let limits = step_limits(&cell, PolicyInputs::Absolute);
        let bc = BcConfig {
            epochs: 1,
            ..BcConfig::default()
        };
        let vars = behaviour_clone(&demos, &limits, 8, &bc, None, &mut |_, _, _| {}).unwrap();
        let selector = SelectorConfig {
            hidden_size: 4,
            epochs: 1,
            ..SelectorConfig::default()
        };
        train_lstm(
            &vars,
            &demos,
            &demos,
            &limits,
            &selector,
            None,
            &mut |_, _| {},
        )
        .unwrap();
        let config = RefineConfig {
            episodes: 2,
            td3: Td3Config {
                hidden: 16,
                batch_size: 4,
                ..Td3Config::default()
            },
            critic_warmup_episodes: 0,
            eval_episodes: 2,
            ..RefineConfig::default()
        };
        let options = EnvOptions {
            kept_robots: robots,
            ..options
        };
        Refinement::new(&cell, options, vars, adjust(config), from_bc, 3).unwrap()
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

    /// A validation scores the policy as `celld eval` runs it from its file: steered against
    /// the drift the cell learns of each kept robot, not the bare network.
    #[test]
    fn a_validation_scores_the_policy_as_it_is_deployed() {
        use crate::learning::pipeline::vars_of;
        use crate::policy::ControllerFactory;
        use crate::policy::file::PolicyFile;
        let cell = CellConfig::reference();
        let bytes = crate::policy::bundled_policy("hierarchical-swift-reference").unwrap();
        let file = PolicyFile::from_bytes(bytes).unwrap();
        let options = EnvOptions {
            kept_robots: 2,
            ..EnvOptions::from_cell(&cell)
        };
        let (episodes, seed) = (16, 7);
        let vars = vars_of(&file).unwrap();
        let validated = evaluate_vars(
            &cell,
            options,
            &vars,
            &PolicyConfig::from_file(&file),
            episodes,
            seed,
        )
        .unwrap();
        let score = |factory: ControllerFactory| {
            let summary = eval::evaluate(&cell, options, episodes, seed, &factory, &|_| {}).0;
            (summary.success_rate, summary.avg_steps)
        };
        let deployed = LearnedPolicy::from_bytes(bytes).unwrap();
        let as_deployed = score(Box::new(move || Box::new(deployed.clone())));
        let bare = LearnedPolicy::hierarchical(HierarchicalPolicy::from_file(&file).unwrap())
            .with_rules(&cell.rules.in_training());
        let as_bare = score(Box::new(move || Box::new(bare.clone())));
        assert_eq!((validated.success_rate, validated.avg_steps), as_deployed);
        // The steering changes the episodes, so the check can tell the two apart.
        assert_ne!(as_deployed, as_bare);
    }

    #[test]
    fn a_restored_checkpoint_continues_where_it_stopped() {
        let mut run = tiny_refinement(true);
        run.train_episode().unwrap();
        run.validate().unwrap();
        let (tensors, progress) = run.checkpoint().unwrap();
        assert_eq!(progress.episode, 1);
        let mut resumed = tiny_refinement(true);
        resumed.restore(&tensors, progress.clone()).unwrap();
        assert_eq!(resumed.episode(), 1);
        assert_eq!(resumed.curve(), run.curve());
        assert_eq!(snapshot(&resumed.policy_vars), snapshot(&run.policy_vars));
        assert_eq!(snapshot(resumed.best().1), snapshot(run.best().1));
        // The agents' networks came back too: a checkpoint of the resumed run is the same.
        let (again, _) = resumed.checkpoint().unwrap();
        for (name, tensor) in &tensors {
            let a = tensor.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let b = again[name].flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert_eq!(a, b, "{name}");
        }
    }

    /// With demonstrations, the demonstrator's episodes fill each agent's demonstration buffer
    /// with the labels behaviour cloning learnt from, every transition carries the true pose
    /// for the critics, and the run is the same under the same seed.
    #[test]
    fn demonstrations_fill_the_buffers_with_bc_labels_and_the_true_pose() {
        let beside = |config: RefineConfig| RefineConfig {
            critic_pretraining_updates: 4,
            ..config.beside_demonstrator("expert", 2)
        };
        let mut run = tiny_refinement_with(true, beside);
        let position = &run.demo_buffers[agent_index(Actor::Position)];
        assert!(position.len() >= 20, "{} position steps", position.len());
        let mut moves = 0;
        for buffer in &run.demo_buffers {
            for t in buffer.items() {
                assert_eq!(t.privileged.len(), 12);
                assert_eq!(t.next_privileged.len(), 12);
                // A label's largest component is 0.9 (or 0 for a hold), as BC's are.
                let largest = t.action.iter().fold(0f32, |m, a| m.max(a.abs()));
                assert!(
                    largest == 0.0 || (0.0..=0.95).contains(&largest),
                    "{largest}"
                );
                moves += usize::from(largest > 0.0);
            }
        }
        assert!(moves > 0);
        // The true pose differs from what the camera saw, but not by much.
        let t = &position.items()[0];
        let gap = t
            .state
            .iter()
            .zip(&t.privileged)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(gap > 0.0 && gap < 1.0, "normalised gap {gap}");
        run.train_episode().unwrap();
        let mut again = tiny_refinement_with(true, beside);
        again.train_episode().unwrap();
        assert_eq!(snapshot(&run.policy_vars), snapshot(&again.policy_vars));
        assert_eq!(run.curve(), again.curve());
    }

    /// A run's curve, its policy's weights by name and its replay buffers' sizes.
    type RunSummary = (Vec<EpisodeRecord>, Vec<(String, Vec<f32>)>, [usize; 2]);

    /// Runs 3 training episodes of a tiny refinement, `parallel` at a time, on `threads`
    /// threads, the actors frozen for the first `warmup`.
    fn run_at_once(parallel: usize, threads: usize, warmup: usize) -> RunSummary {
        run_at_once_on(0, parallel, threads, warmup)
    }

    fn run_at_once_on(robots: u32, parallel: usize, threads: usize, warmup: usize) -> RunSummary {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut run = tiny_refinement_on(robots, true, |config| RefineConfig {
                episodes: 3,
                parallel_episodes: parallel,
                critic_warmup_episodes: warmup,
                ..config
            });
            for _ in 0..3 {
                run.train_episode().unwrap();
            }
            let sizes = [run.buffers[0].len(), run.buffers[1].len()];
            (run.curve().to_vec(), snapshot(&run.policy_vars), sizes)
        })
    }

    #[test]
    fn episodes_run_at_once_give_the_same_run_on_any_number_of_threads() {
        let one = run_at_once(3, 1, 0);
        assert_eq!(one, run_at_once(3, 2, 0));
        assert_eq!(one.0.len(), 3);
        // Transitions were gathered. A one-epoch policy may never level the shaft to within
        // the tolerance the position actor acts within in these episodes, so it may not act
        // at all (`hierarchical::actor_with_work`).
        assert!(one.2[0] + one.2[1] > 0, "buffers {:?}", one.2);
    }

    #[test]
    fn episodes_run_at_once_are_the_episodes_run_in_turn_while_the_actors_are_frozen() {
        // While only the critics learn, the policy is the same for every episode: the episodes
        // and the transitions they gather cannot depend on how many ran at once.
        let at_once = run_at_once(3, 2, 10);
        let in_turn = run_at_once(1, 2, 10);
        assert_eq!(at_once, in_turn);
        // And the actors did learn once unfrozen, or the comparison above would say nothing
        // about episodes run with a stale policy.
        let learning = run_at_once(3, 2, 0);
        assert_ne!(learning.1, at_once.1);
    }

    #[test]
    fn episodes_on_kept_robots_are_the_same_on_any_number_of_threads_and_at_once_or_in_turn() {
        // Two robots, three episodes at once: robot 0 runs episodes 0 and 2 in turn.
        let one = run_at_once_on(2, 3, 1, 10);
        assert_eq!(one, run_at_once_on(2, 3, 2, 10));
        assert_eq!(one, run_at_once_on(2, 1, 2, 10));
        // On kept robots the episodes are not those on robots new to the cell.
        assert_ne!(one.0, run_at_once(3, 2, 10).0);
    }

    #[test]
    fn a_kept_robot_remembers_its_drift_from_one_episode_to_the_next() {
        // Six demonstrations on two robots: each robot ran three episodes, and the cell takes
        // in what an episode taught it when the next starts. An episode teaches only if the
        // shaft went far enough in for the drift to show (`DriftKnowledge::is_usable`): with
        // three, at least one of a robot's first two did.
        let run = tiny_refinement_on(2, true, |config| RefineConfig {
            demonstrations: 6,
            demonstrator: "expert",
            ..config
        });
        assert_eq!(run.robots.len(), 2);
        assert!(run.robots.iter().all(|env| env.drift_memory().is_some()));
        let fresh = tiny_refinement_on(0, true, |config| RefineConfig {
            demonstrations: 6,
            demonstrator: "expert",
            ..config
        });
        assert!(fresh.robots.is_empty());
        // The demonstrator's episodes on remembered robots are not those on new ones.
        assert_ne!(
            run.demo_buffers[0].len() + run.demo_buffers[1].len(),
            fresh.demo_buffers[0].len() + fresh.demo_buffers[1].len()
        );
    }

    /// With the step-size agent: a transition of it for every decision of the policy, the
    /// first ones (50 mm above the seat) coarse; only ω3's row of the head moves; its
    /// networks go into the checkpoint and come back from it.
    #[test]
    fn the_step_size_agent_learns_the_heads_scale_row_and_is_checkpointed() {
        let with_step = |config: RefineConfig| RefineConfig {
            step_size: Some(StepSizeConfig::default()),
            ..config
        };
        let mut run = tiny_refinement_with(true, with_step);
        let head = |r: &Refinement| {
            let data = r.policy_vars.data().lock().unwrap();
            let w = data["high.head.weight"]
                .as_tensor()
                .to_vec2::<f32>()
                .unwrap();
            let b = data["high.head.bias"].as_tensor().to_vec1::<f32>().unwrap();
            (w, b)
        };
        let before = head(&run);
        run.train_episode().unwrap();
        run.train_episode().unwrap();
        let decisions = run.buffers[0].len() + run.buffers[1].len();
        assert_eq!(run.step_buffer.len(), decisions);
        assert!(run.step_buffer.items()[0].coarse);
        let after = head(&run);
        assert_eq!(after.0[..2], before.0[..2]);
        assert_eq!(after.1[..2], before.1[..2]);
        assert_ne!((&after.0[2], after.1[2]), (&before.0[2], before.1[2]));
        let (tensors, progress) = run.checkpoint().unwrap();
        assert!(tensors.keys().any(|k| k.starts_with("agent2.")));
        let mut resumed = tiny_refinement_with(true, with_step);
        resumed.restore(&tensors, progress).unwrap();
        assert_eq!(snapshot(&resumed.policy_vars), snapshot(&run.policy_vars));
        assert_eq!(head(&resumed), after);
    }

    #[test]
    fn without_bc_the_actors_start_afresh_at_the_policys_width() {
        let bc = tiny_refinement(true);
        let fresh = tiny_refinement(false);
        let pos = |r: &Refinement| {
            snapshot(&r.policy_vars)
                .into_iter()
                .find(|(k, _)| k == "pos.0.weight")
                .unwrap()
                .1
        };
        assert_eq!(pos(&bc).len(), pos(&fresh).len());
        assert_ne!(pos(&bc), pos(&fresh));
    }
}
