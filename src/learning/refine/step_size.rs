//! TD3 on the selector's step size: a third agent whose actor is the row of the selector's
//! head that gives ω3, the step scale s = sigmoid(ω3).
//!
//! Behaviour cloning leaves the step scale short where the demonstrators take full steps: on
//! the approach above the bore the cloned selector of `hierarchical-swift-reference` answers their 1.0
//! with 0.86–0.90, and the actors' tanh outputs cannot make up for it. There the moves are
//! millimetres and an error of a tenth of one is corrected by the next step, so the agent
//! explores more ([`StepSizeConfig::coarse_noise`]) and may move further
//! ([`StepSizeConfig::coarse_trust_region`]) than elsewhere.
//!
//! The agent reads the LSTM's hidden state h (what the head reads) and acts u = tanh(w·h + b)
//! with w, b half the head's ω3 row: tanh(ω3/2) = 2·sigmoid(ω3) − 1, so s = (1 + u)/2 exactly,
//! and the refined row goes back into the head as 2·w, 2·b. The policy file keeps its format.
//! Its critics read h beside the policy's inputs (and, with asymmetric critics, the true pose).
//!
//! Its reward is the twin's whole reward plus a documented shaping term
//! ([`StepSizeConfig::progress_reward_per_mm`]). The paper's reward alone barely prefers a
//! shorter episode: each step earns its positive r_P and r_O terms, which about make up for
//! the success bonus coming a step later, and without the shaping the agent left the steps as
//! they were (docs/learning-reference.md).

use crate::learning::td3::{Td3, Td3Config};
use crate::sim::Observation;
use candle_core::{Tensor, Var};
use candle_nn::VarMap;

/// The head's weights in a policy file.
const HEAD_WEIGHT: &str = "high.head.weight";
const HEAD_BIAS: &str = "high.head.bias";
/// The row of the head that gives ω3.
const SCALE_ROW: usize = 2;

/// How the step-size agent explores and how far it may move.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepSizeConfig {
    /// σ of the exploration noise on u (s moves by half of it) on coarse states; elsewhere the
    /// refinement's exploration noise.
    pub coarse_noise: f64,
    /// The trust region on u on coarse states.
    pub coarse_trust_region: f64,
    /// The trust region on u on the other states. The head is linear in h, and the LSTM's h
    /// on the approach is not far enough from its h at the entrance for the approach's scale
    /// to move while the entrance's stays within the actors' 0.002.
    pub fine_trust_region: f64,
    /// Adam's rate for the head's row.
    pub learning_rate: f64,
    /// Shaping of the agent's reward (0: the paper's reward alone): this much per mm the
    /// estimated distance to the goal |P| shrank over the step.
    pub progress_reward_per_mm: f64,
}

impl StepSizeConfig {
    /// The shaping term of a step that started `from_mm` from the goal and ended at
    /// `observation`.
    pub fn progress_reward(&self, from_mm: f64, observation: &Observation) -> f32 {
        (self.progress_reward_per_mm * (from_mm - distance_to_goal_mm(observation))) as f32
    }
}

/// |P| in the estimate (mm).
pub fn distance_to_goal_mm(observation: &Observation) -> f64 {
    let s = &observation.state;
    (s[6] * s[6] + s[7] * s[7] + s[8] * s[8]).sqrt()
}

impl Default for StepSizeConfig {
    fn default() -> Self {
        StepSizeConfig {
            coarse_noise: 0.1,
            coarse_trust_region: 0.5,
            fine_trust_region: 0.3,
            learning_rate: 3e-3,
            progress_reward_per_mm: 0.5,
        }
    }
}

/// Height of the tip above the bore's entrance (mm, in the estimate) above which a state is
/// coarse: the demonstrators take full steps down to about here, then align and come to the
/// standoff 1 mm above the entrance in moves of a millimetre or less.
pub const COARSE_ABOVE_ENTRANCE_MM: f64 = 5.0;

/// Whether the state is coarse: the tip more than [`COARSE_ABOVE_ENTRANCE_MM`] above the
/// entrance, as the estimate sees it.
pub fn is_coarse(observation: &Observation) -> bool {
    -observation.insertion_mm() > COARSE_ABOVE_ENTRANCE_MM
}

/// u for a step scale s: 2·s − 1.
pub fn u_of_scale(scale: f32) -> f32 {
    2.0 * scale - 1.0
}

/// The step scale s for u: (1 + u)/2.
pub fn scale_of_u(u: f32) -> f32 {
    (1.0 + u) / 2.0
}

/// The step-size agent, starting from the policy's head. `td3` is the refinement's setting;
/// its critics read `privileged_dim` numbers beside h.
pub fn agent(
    policy_vars: &VarMap,
    td3: Td3Config,
    step: StepSizeConfig,
    privileged_dim: usize,
) -> candle_core::Result<Td3> {
    let (weight, bias) = head(policy_vars)?;
    let hidden = weight.dim(1)?;
    let init = VarMap::new();
    {
        let mut data = init.data().lock().expect("var map lock");
        let row = (weight.narrow(0, SCALE_ROW, 1)? * 0.5)?;
        let b = (bias.narrow(0, SCALE_ROW, 1)? * 0.5)?;
        data.insert("actor.weight".into(), Var::from_tensor(&row)?);
        data.insert("actor.bias".into(), Var::from_tensor(&b)?);
    }
    let config = Td3Config {
        trust_region: Some(step.fine_trust_region),
        coarse_trust_region: Some(step.coarse_trust_region),
        actor_learning_rate: step.learning_rate,
        exploration_noise: step.coarse_noise,
        // Its loss is the zoned one; the demonstrations teach the actors, not the step size.
        demo_regularisation: None,
        privileged_dim,
        ..td3
    };
    Td3::new(hidden, 1, config, Some(init))
}

/// Writes the agent's actor back into the policy's head as its ω3 row (2·w, 2·b).
pub fn sync(agent: &Td3, policy_vars: &VarMap) -> candle_core::Result<()> {
    let (weight, bias) = head(policy_vars)?;
    let actor = agent.actor_vars();
    let w = (tensor(actor, "actor.weight", "step agent")? * 2.0)?;
    let b = (tensor(actor, "actor.bias", "step agent")? * 2.0)?;
    let with_row = |t: &Tensor, row: &Tensor, axis: usize| -> candle_core::Result<Tensor> {
        Tensor::cat(&[&t.narrow(axis, 0, SCALE_ROW)?, row], axis)
    };
    let data = policy_vars.data().lock().expect("var map lock");
    data[HEAD_WEIGHT].set(&with_row(&weight, &w, 0)?)?;
    data[HEAD_BIAS].set(&with_row(&bias, &b, 0)?)?;
    Ok(())
}

/// The head's weight [3, H] and bias [3].
fn head(policy_vars: &VarMap) -> candle_core::Result<(Tensor, Tensor)> {
    let weight = tensor(policy_vars, HEAD_WEIGHT, "policy")?;
    if weight.dims().len() != 2 || weight.dim(0)? != SCALE_ROW + 1 {
        candle_core::bail!("`{HEAD_WEIGHT}` is {:?}, not [3, H]", weight.dims());
    }
    Ok((weight, tensor(policy_vars, HEAD_BIAS, "policy")?))
}

/// A copy of the tensor `name` of `vars` (`whose` names them in the error).
fn tensor(vars: &VarMap, name: &str, whose: &str) -> candle_core::Result<Tensor> {
    let data = vars.data().lock().expect("var map lock");
    data.get(name)
        .ok_or_else(|| candle_core::Error::Msg(format!("{whose} has no `{name}`")))?
        .as_tensor()
        .copy()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learning::pipeline::load_vars;
    use crate::learning::refine::policy_from_vars;
    use crate::policy::hierarchical::{HierarchicalPolicy, PolicyConfig};
    use std::path::Path;

    fn swift() -> (VarMap, PolicyConfig) {
        let vars = load_vars(Path::new("policies/swift.safetensors")).unwrap();
        let config = *HierarchicalPolicy::from_path("policies/swift.safetensors")
            .unwrap()
            .config();
        (vars, config)
    }

    fn head_values(vars: &VarMap) -> (Vec<f32>, Vec<f32>) {
        let (w, b) = head(vars).unwrap();
        (
            w.flatten_all().unwrap().to_vec1().unwrap(),
            b.to_vec1().unwrap(),
        )
    }

    /// The agent's action on the policy's own LSTM state is the policy's step scale, as
    /// u = 2·s − 1; given back unchanged, the head is the same to the bit; a changed bias
    /// comes back doubled in ω3's row alone.
    #[test]
    fn the_agent_acts_the_policys_step_scale_and_gives_its_row_back() {
        let (vars, config) = swift();
        let td3 = Td3Config {
            hidden: 8,
            ..Td3Config::default()
        };
        let agent = agent(&vars, td3, StepSizeConfig::default(), 12).unwrap();
        let mut policy = policy_from_vars(&vars, &config).unwrap();
        let mut state = [0.0f64; 12];
        for k in 0..6 {
            // Coming down the axis from 30 mm above the seat, a little off it.
            state[6] = 0.4 - 0.05 * k as f64;
            state[8] = -30.0 + 5.0 * k as f64;
            let out = policy.step(&state).unwrap();
            let (h, _) = policy.lstm_state();
            let u = agent.act(h).unwrap()[0];
            let scale = scale_of_u(u);
            assert!(
                (scale - out.scale).abs() < 1e-5,
                "step {k}: agent {scale}, policy {}",
                out.scale
            );
        }
        let before = head_values(&vars);
        sync(&agent, &vars).unwrap();
        assert_eq!(head_values(&vars), before);
        {
            let data = agent.actor_vars().data().lock().unwrap();
            let bias = &data["actor.bias"];
            bias.set(&(bias.as_tensor() + 0.125).unwrap()).unwrap();
        }
        sync(&agent, &vars).unwrap();
        let (weights, biases) = head_values(&vars);
        assert_eq!(weights, before.0);
        assert_eq!(biases[..2], before.1[..2]);
        assert!(
            (biases[2] - (before.1[2] + 0.25)).abs() < 1e-6,
            "{biases:?}"
        );
    }

    #[test]
    fn u_and_the_step_scale_are_one_map_and_its_inverse() {
        for s in [0.0f32, 0.002, 0.5, 0.88, 0.98, 1.0] {
            assert!((scale_of_u(u_of_scale(s)) - s).abs() < 1e-7);
        }
        assert_eq!(u_of_scale(0.5), 0.0);
        assert_eq!(scale_of_u(-1.0), 0.0);
    }
}
