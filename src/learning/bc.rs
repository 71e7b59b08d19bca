//! Behaviour cloning of the two actors (paper §3.2, Algorithm 2; Table 1: SGD, lr 1e-3,
//! batch 32): each actor learns, by least squares, the direction labels of the expert's moves
//! that used it (`dataset::StepLabels`), from the normalised state.
//!
//! Weights are created here, seeded, with PyTorch's default initialisation (uniform within
//! ±1/√fan_in), because candle's CPU random generator cannot be seeded; training is then
//! deterministic under the seed.

use super::dataset::{GoalScales, Normaliser, StepLabels, StepLimits};
use super::demos::{DemoEpisode, DemoStep};
use crate::policy::Actor;
use crate::policy::hierarchical::actor_config;
use crate::policy::inputs::PolicyInputs;
use crate::policy::mlp::{Mlp, MlpConfig};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Module, Optimizer, SGD, VarBuilder, VarMap};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Behaviour-cloning settings; defaults from Table 1 of the paper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BcConfig {
    /// Epochs of the position actor.
    pub epochs: usize,
    /// Epochs of the orientation actor. Its samples are a hundredth of the position actor's
    /// (which are repeated), so its epochs are cheap, and it needs many: its loss falls from
    /// 0.008 at 200 epochs to 0.0006 at 3000 (docs/learning-reference.md).
    pub orientation_epochs: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    /// The last `anneal_fraction` of each actor's epochs (rounded up) run at `learning_rate ×
    /// anneal_factor`. At a constant rate the weights end anywhere in SGD's noise around the
    /// optimum, and this policy is sensitive at the micrometre level: 3 epochs at 0.02 from the
    /// bundled policy gave success 0.701, 3 at 0.002 gave 0.982 (docs/learning-reference.md).
    pub anneal_fraction: f64,
    pub anneal_factor: f64,
    pub seed: u64,
    /// Weight of the x and y components in the position actor's loss (z weighs 1). Lateral
    /// moves during insertion are a few µm beside a millimetre-long z step: unweighted, the
    /// loss lets their errors through.
    pub lateral_weight: f64,
    /// A further weight of the x and y components (the sideways move; the tilt about x and y)
    /// in both actors' losses for samples with the tip in the bore (P_z ≥ `bore_from_pz_mm`).
    /// There the sideways corrections are hundredths of a millimetre, and unweighted the
    /// actor gets about half of each one wrong; at 30 its error there is a third as large
    /// (docs/learning-reference.md).
    pub bore_lateral_weight: f64,
    /// P_z (mm) at the entrance of the bore: the tip is in the bore at or above it.
    pub bore_from_pz_mm: f64,
    /// Each position step at or past the standoff (P_z ≥ `insertion_from_pz_mm`) appears this
    /// many times in the position actor's samples: insertion needs micrometre precision that
    /// an unweighted loss spends on the approach (docs/learning-reference.md: success 0.050
    /// with 1, 0.326 with 20).
    pub insertion_repeat: usize,
    /// P_z (mm) from which a position step counts as insertion: 1.5 mm above the entrance.
    pub insertion_from_pz_mm: f64,
    /// The fixed σ of the goal-centred input normaliser ([`Normaliser::goal_centred`]).
    pub goal_scales: GoalScales,
    /// What the policy reads (`policy::inputs`).
    pub inputs: PolicyInputs,
    /// The orientation actor's errors relative to its labels' size, down to this label
    /// ([`RelativeToLabel`]); `None` weighs every sample alike.
    pub orientation_label_floor: Option<f64>,
    /// The same for the position actor. Its last step to the seat is a few hundredths of a
    /// millimetre, a hundredth of an insertion step: unweighted, the actor answered it with no
    /// move and held just short of the depth tolerance (docs/learning-reference.md).
    pub position_label_floor: Option<f64>,
}

impl BcConfig {
    /// The learning rate of epoch `epoch` (0-based) of an actor trained `epochs` epochs.
    pub fn learning_rate_at(&self, epoch: usize, epochs: usize) -> f64 {
        let annealed = (epochs as f64 * self.anneal_fraction).ceil() as usize;
        if epoch + annealed >= epochs {
            self.learning_rate * self.anneal_factor
        } else {
            self.learning_rate
        }
    }
}

impl Default for BcConfig {
    fn default() -> Self {
        BcConfig {
            epochs: 200,
            orientation_epochs: 3000,
            batch_size: 32,
            learning_rate: 1e-3,
            anneal_fraction: 0.1,
            anneal_factor: 0.1,
            seed: 0,
            lateral_weight: 1.0,
            bore_lateral_weight: 1.0,
            bore_from_pz_mm: -60.0,
            insertion_repeat: 20,
            insertion_from_pz_mm: -61.5,
            goal_scales: GoalScales::default(),
            inputs: PolicyInputs::Absolute,
            orientation_label_floor: None,
            position_label_floor: None,
        }
    }
}

/// Adds a `Linear(inputs → outputs)` named `{prefix}.weight` [out, in] and `{prefix}.bias`, with
/// PyTorch's default initialisation, to `varmap`.
pub fn init_linear(
    varmap: &VarMap,
    prefix: &str,
    inputs: usize,
    outputs: usize,
    rng: &mut impl Rng,
) -> candle_core::Result<()> {
    let bound = 1.0 / (inputs as f64).sqrt();
    let mut uniform = |n: usize| -> Vec<f32> {
        (0..n)
            .map(|_| rng.random_range(-bound..bound) as f32)
            .collect()
    };
    let weight = Tensor::from_vec(uniform(inputs * outputs), (outputs, inputs), &Device::Cpu)?;
    let bias = Tensor::from_vec(uniform(outputs), outputs, &Device::Cpu)?;
    let mut data = varmap.data().lock().expect("var map lock");
    data.insert(format!("{prefix}.weight"), Var::from_tensor(&weight)?);
    data.insert(format!("{prefix}.bias"), Var::from_tensor(&bias)?);
    Ok(())
}

/// Adds the weights of an MLP (`{prefix}.0`, `.2`, `.4`), layer by layer in order, each with
/// [`init_linear`].
pub fn init_mlp(
    varmap: &VarMap,
    prefix: &str,
    config: &MlpConfig,
    rng: &mut impl Rng,
) -> candle_core::Result<()> {
    for (name, inputs, outputs) in config.layers() {
        init_linear(varmap, &format!("{prefix}.{name}"), inputs, outputs, rng)?;
    }
    Ok(())
}

/// Adds the weights of one actor (`{prefix}.0`, `.2`, `.4`, docs/design.md §6) of width `width`.
pub fn init_actor(
    varmap: &VarMap,
    prefix: &str,
    width: usize,
    rng: &mut impl Rng,
) -> candle_core::Result<()> {
    init_mlp(varmap, prefix, &actor_config(width), rng)
}

/// The variables of `varmap` whose names start with `prefix`, in name order.
pub fn vars_under(varmap: &VarMap, prefix: &str) -> Vec<Var> {
    let data = varmap.data().lock().expect("var map lock");
    let mut named: Vec<(&String, &Var)> =
        data.iter().filter(|(k, _)| k.starts_with(prefix)).collect();
    named.sort_by(|a, b| a.0.cmp(b.0));
    named.into_iter().map(|(_, v)| v.clone()).collect()
}

/// The (normalised state, direction label) pairs of the steps that used `actor`; holds have
/// no direction and are left out.
pub fn actor_samples(
    episodes: &[DemoEpisode],
    actor: Actor,
    normaliser: &Normaliser,
    limits: &StepLimits,
) -> Vec<([f32; 12], [f32; 3])> {
    samples_where(episodes, actor, normaliser, limits, |_| true)
}

/// The position actor's samples, with those at or past `config.insertion_from_pz_mm` repeated
/// `config.insertion_repeat` times in all.
pub fn position_samples(
    episodes: &[DemoEpisode],
    normaliser: &Normaliser,
    limits: &StepLimits,
    config: &BcConfig,
) -> Vec<([f32; 12], [f32; 3])> {
    let mut samples = actor_samples(episodes, Actor::Position, normaliser, limits);
    let inserting = samples_where(episodes, Actor::Position, normaliser, limits, |s| {
        s.state[8] >= config.insertion_from_pz_mm
    });
    for _ in 1..config.insertion_repeat {
        samples.extend_from_slice(&inserting);
    }
    samples
}

fn samples_where(
    episodes: &[DemoEpisode],
    actor: Actor,
    normaliser: &Normaliser,
    limits: &StepLimits,
    keep: impl Fn(&DemoStep) -> bool,
) -> Vec<([f32; 12], [f32; 3])> {
    episodes
        .iter()
        .flat_map(|e| &e.steps)
        .filter(|s| s.actor == actor && keep(s))
        .map(|s| (s, StepLabels::of(s, limits)))
        .filter(|(_, labels)| !labels.is_hold())
        .map(|(s, labels)| {
            (
                normaliser.apply(&s.state),
                labels.direction.map(|v| v as f32),
            )
        })
        .collect()
}

/// How much each output component's error counts in an actor's BC loss.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossWeights {
    /// Per component (x, y, z), for every sample.
    pub components: [f32; 3],
    /// A further factor on x and y for the samples in the bore.
    pub bore_lateral: f32,
    /// The normalised P_z input (column 8) at the entrance: samples at or above it are in the
    /// bore.
    pub bore_from_input: f32,
    /// Each sample's error relative to its label's size, if set ([`RelativeToLabel`]).
    pub relative_to_label: Option<RelativeToLabel>,
}

/// The orientation label floor of the recipe for any cell (`celld train policy`, and the
/// service's training `for_any_cell`): it lifted the cross-cell policy on the cells it was not
/// trained on (docs/learning-reference.md § Why the defaults are what they are).
pub const ACROSS_CELLS_ORIENTATION_LABEL_FLOOR: f64 = 0.2;

/// Weights each sample's squared error by 1 / max(|label|∞, `floor`)², over the mean of that
/// weight across the samples (so the loss keeps its scale): a small correction's error counts
/// as much, relative to it, as a large one's. Unweighted, an actor that must size moves from
/// its full step down to a hundredth of it fits the small ones to within its overall error and
/// answers a small tilt with no move at all.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativeToLabel {
    /// The label size (tanh units) below which errors count no more.
    pub floor: f32,
    /// The mean of the raw weights over the samples ([`RelativeToLabel::over`]).
    pub mean_weight: f32,
}

impl RelativeToLabel {
    /// The weighting with `floor` for `samples`.
    pub fn over(samples: &[([f32; 12], [f32; 3])], floor: f32) -> Self {
        let raw = |label: &[f32; 3]| Self::raw_weight(label, floor) as f64;
        let sum: f64 = samples.iter().map(|(_, label)| raw(label)).sum();
        RelativeToLabel {
            floor,
            mean_weight: (sum / samples.len().max(1) as f64) as f32,
        }
    }

    fn raw_weight(label: &[f32; 3], floor: f32) -> f32 {
        let largest = label.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        largest.max(floor).powi(-2)
    }

    /// A sample's weight in the loss.
    pub fn weight(&self, label: &[f32; 3]) -> f32 {
        Self::raw_weight(label, self.floor) / self.mean_weight
    }

    /// The rows' weights, (N, 1), for labels `y` (N, 3).
    fn of(&self, y: &Tensor) -> candle_core::Result<Tensor> {
        y.abs()?
            .max_keepdim(1)?
            .maximum(f64::from(self.floor))?
            .powf(-2.0)?
            / f64::from(self.mean_weight)
    }
}

impl LossWeights {
    /// The same weights for every sample.
    pub fn uniform(components: [f32; 3]) -> Self {
        LossWeights {
            components,
            bore_lateral: 1.0,
            bore_from_input: f32::INFINITY,
            relative_to_label: None,
        }
    }
}

/// The paper's BC loss, (1/2N) Σ ‖a − aᵉ‖², of an actor over samples.
pub fn bc_loss(actor: &Mlp, samples: &[([f32; 12], [f32; 3])]) -> candle_core::Result<f64> {
    weighted_loss(actor, samples, LossWeights::uniform([1.0; 3]))
}

/// The BC loss with weights per output component.
pub fn weighted_loss(
    actor: &Mlp,
    samples: &[([f32; 12], [f32; 3])],
    weights: LossWeights,
) -> candle_core::Result<f64> {
    let (x, y) = batch(samples, &(0..samples.len()).collect::<Vec<_>>())?;
    loss(actor, &x, &y, &weights, &component_tensor(weights)?)?
        .to_scalar::<f32>()
        .map(f64::from)
}

fn component_tensor(weights: LossWeights) -> candle_core::Result<Tensor> {
    Tensor::from_slice(&weights.components, (1, 3), &Device::Cpu)
}

fn batch(
    samples: &[([f32; 12], [f32; 3])],
    rows: &[usize],
) -> candle_core::Result<(Tensor, Tensor)> {
    let mut x = Vec::with_capacity(rows.len() * 12);
    let mut y = Vec::with_capacity(rows.len() * 3);
    for &row in rows {
        x.extend_from_slice(&samples[row].0);
        y.extend_from_slice(&samples[row].1);
    }
    Ok((
        Tensor::from_vec(x, (rows.len(), 12), &Device::Cpu)?,
        Tensor::from_vec(y, (rows.len(), 3), &Device::Cpu)?,
    ))
}

/// The weighted loss of a minibatch; `components` is `weights.components` as a (1, 3) tensor.
fn loss(
    actor: &Mlp,
    x: &Tensor,
    y: &Tensor,
    weights: &LossWeights,
    components: &Tensor,
) -> candle_core::Result<Tensor> {
    let n = x.dim(0)? as f64;
    let mut squared = (actor.forward(x)? - y)?.sqr()?.broadcast_mul(components)?;
    if weights.bore_lateral != 1.0 {
        let in_bore = x
            .narrow(1, 8, 1)?
            .ge(f64::from(weights.bore_from_input))?
            .to_dtype(DType::F32)?;
        let lateral = ((in_bore * (f64::from(weights.bore_lateral) - 1.0))? + 1.0)?;
        let per_row = Tensor::cat(&[&lateral, &lateral, &Tensor::ones_like(&lateral)?], 1)?;
        squared = (squared * per_row)?;
    }
    if let Some(relative) = weights.relative_to_label {
        squared = squared.broadcast_mul(&relative.of(y)?)?;
    }
    squared.sum_all()? / (2.0 * n)
}

/// Trains the actor `{prefix}` (already in `varmap`) on `samples` with SGD, each output
/// component's error weighted by `weights`; `on_epoch(epoch, loss)` is called after each epoch
/// with the mean of its minibatches' weighted losses (a second pass over every sample each
/// epoch would cost a fifth of the training). Returns the losses.
#[allow(clippy::too_many_arguments)]
pub fn train_actor(
    varmap: &VarMap,
    prefix: &str,
    width: usize,
    weights: LossWeights,
    samples: &[([f32; 12], [f32; 3])],
    config: &BcConfig,
    on_epoch: &mut dyn FnMut(usize, f64),
) -> candle_core::Result<Vec<f64>> {
    if samples.is_empty() {
        candle_core::bail!("no demonstrated steps for actor `{prefix}`");
    }
    let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
    let actor = Mlp::load(vb.pp(prefix), &actor_config(width))?;
    let mut optimizer = SGD::new(
        vars_under(varmap, &format!("{prefix}.")),
        config.learning_rate,
    )?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let components = component_tensor(weights)?;
    let mut order: Vec<usize> = (0..samples.len()).collect();
    let mut losses = Vec::with_capacity(config.epochs);
    for epoch in 0..config.epochs {
        optimizer.set_learning_rate(config.learning_rate_at(epoch, config.epochs));
        order.shuffle(&mut rng);
        let mut total = 0.0;
        for rows in order.chunks(config.batch_size.max(1)) {
            let (x, y) = batch(samples, rows)?;
            let loss = loss(&actor, &x, &y, &weights, &components)?;
            total += f64::from(loss.to_scalar::<f32>()?) * rows.len() as f64;
            optimizer.backward_step(&loss)?;
        }
        let epoch_loss = total / samples.len() as f64;
        if !epoch_loss.is_finite() {
            candle_core::bail!(
                "behaviour cloning of `{prefix}` diverged at epoch {epoch} (loss {epoch_loss})"
            );
        }
        on_epoch(epoch, epoch_loss);
        losses.push(epoch_loss);
    }
    Ok(losses)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::learning::demos::record_expert;
    use crate::sim::EnvOptions;

    #[test]
    fn insertion_steps_are_repeated_and_holds_left_out() {
        let step = |pz: f64, dz: f64| DemoStep {
            episode: 0,
            step: 0,
            state: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, pz, 0.0, 0.0, 0.0],
            action: [0.0, 0.0, dz, 0.0, 0.0, 0.0],
            actor: Actor::Position,
            scale: 0.5,
        };
        // Two approach steps, one hold at the standoff, two insertion steps.
        let demos = [DemoEpisode {
            steps: vec![
                step(-100.0, 4.0),
                step(-80.0, 4.0),
                step(-61.0, 0.0),
                step(-61.0, 3.0),
                step(-58.0, 3.0),
            ],
            succeeded: true,
        }];
        let limits = StepLimits {
            position_mm: 5.0,
            orientation_deg: 1.0,
            inputs: PolicyInputs::Absolute,
        };
        let normaliser = Normaliser::fit(&demos);
        let config = BcConfig {
            insertion_repeat: 5,
            insertion_from_pz_mm: -61.5,
            ..BcConfig::default()
        };
        let plain = actor_samples(&demos, Actor::Position, &normaliser, &limits);
        assert_eq!(plain.len(), 4, "the hold has no direction to learn");
        let samples = position_samples(&demos, &normaliser, &limits, &config);
        assert_eq!(samples.len(), 2 + 2 * 5);
        let deep = normaliser.apply(&step(-58.0, 3.0).state);
        assert_eq!(samples.iter().filter(|(x, _)| *x == deep).count(), 5);
    }

    #[test]
    fn the_last_fraction_of_the_epochs_runs_at_the_annealed_rate() {
        let config = BcConfig {
            learning_rate: 0.02,
            anneal_fraction: 0.1,
            anneal_factor: 0.25,
            ..BcConfig::default()
        };
        let rates: Vec<f64> = (0..25).map(|e| config.learning_rate_at(e, 25)).collect();
        // ⌈2.5⌉ = 3 annealed epochs out of 25.
        assert_eq!(rates.iter().filter(|&&r| r == 0.02).count(), 22);
        assert!(
            rates[22..].iter().all(|&r| (r - 0.005).abs() < 1e-15),
            "{rates:?}"
        );
        let off = BcConfig {
            anneal_fraction: 0.0,
            ..config
        };
        assert!((0..25).all(|e| off.learning_rate_at(e, 25) == 0.02));
        let all = BcConfig {
            anneal_fraction: 1.0,
            ..config
        };
        assert!((0..25).all(|e| (all.learning_rate_at(e, 25) - 0.005).abs() < 1e-15));
    }

    #[test]
    fn the_bore_weight_scales_the_sideways_errors_of_samples_in_the_bore_only() {
        let varmap = VarMap::new();
        init_actor(&varmap, "pos", 8, &mut ChaCha8Rng::seed_from_u64(4)).unwrap();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let actor = Mlp::load(vb.pp("pos"), &actor_config(8)).unwrap();
        // Normalised P_z (column 8) against the entrance at -12: three samples in the bore
        // (one exactly at the entrance), two above it.
        let sample = |pz: f32, i: f32| {
            let mut x = [0.1 * i; 12];
            x[8] = pz;
            (x, [0.3 - 0.1 * i, -0.2 * i, 0.5])
        };
        let inside = [sample(-12.0, 1.0), sample(-3.0, 2.0), sample(0.0, 3.0)];
        let outside = [sample(-12.5, 4.0), sample(-40.0, 5.0)];
        let with = |components: [f32; 3], bore_lateral: f32| LossWeights {
            components,
            bore_lateral,
            bore_from_input: -12.0,
            relative_to_label: None,
        };
        let loss =
            |samples: &[([f32; 12], [f32; 3])], w| weighted_loss(&actor, samples, w).unwrap();
        let sideways = loss(&inside, with([1.0, 1.0, 0.0], 1.0));
        let axial = loss(&inside, with([0.0, 0.0, 1.0], 1.0));
        let weighted = loss(&inside, with([1.0, 1.0, 1.0], 30.0));
        assert!(
            (weighted - (30.0 * sideways + axial)).abs() < 1e-5 * weighted,
            "{weighted} against 30 · {sideways} + {axial}"
        );
        assert_eq!(
            loss(&outside, with([1.0, 1.0, 1.0], 30.0)),
            loss(&outside, LossWeights::uniform([1.0; 3]))
        );
    }

    /// Weights 1 / max(|label|∞, floor)² over their mean, checked by hand; the loss is the
    /// per-sample losses so weighted.
    #[test]
    fn relative_weights_count_each_error_against_its_label() {
        let varmap = VarMap::new();
        init_actor(&varmap, "ori", 8, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let actor = Mlp::load(vb.pp("ori"), &actor_config(8)).unwrap();
        // Largest components 0.5, 0.05 (below the floor: counts as 0.1) and 0.2: raw weights
        // 4, 100 and 25, mean 43.
        let samples = [
            ([0.1; 12], [0.5, -0.2, 0.0]),
            ([-0.3; 12], [0.01, -0.05, 0.02]),
            ([0.7; 12], [0.0, 0.0, -0.2]),
        ];
        let relative = RelativeToLabel::over(&samples, 0.1);
        assert!((relative.mean_weight - 43.0).abs() < 1e-4);
        let expected = [4.0 / 43.0, 100.0 / 43.0, 25.0 / 43.0];
        for ((_, label), expected) in samples.iter().zip(expected) {
            assert!((relative.weight(label) - expected).abs() < 1e-6);
        }
        let weights = LossWeights {
            relative_to_label: Some(relative),
            ..LossWeights::uniform([1.0; 3])
        };
        let each = |sample| weighted_loss(&actor, &[sample], LossWeights::uniform([1.0; 3]));
        let by_hand: f64 = samples
            .iter()
            .zip(expected)
            .map(|(sample, w)| f64::from(w) * each(*sample).unwrap())
            .sum::<f64>()
            / 3.0;
        let weighted = weighted_loss(&actor, &samples, weights).unwrap();
        assert!(
            (weighted - by_hand).abs() < 1e-5 * by_hand,
            "{weighted} against {by_hand}"
        );
    }

    #[test]
    fn bc_lowers_its_loss_on_expert_data_deterministically() {
        let cell = CellConfig::reference();
        let demos = record_expert(&cell, EnvOptions::from_cell(&cell), 8, 3);
        let normaliser = Normaliser::fit(&demos);
        let limits = StepLimits {
            position_mm: 5.0,
            orientation_deg: 1.0,
            inputs: PolicyInputs::Absolute,
        };
        let samples = actor_samples(&demos, Actor::Position, &normaliser, &limits);
        assert!(samples.len() > 100);
        // The paper's loss over every sample, before and after training (the epochs report
        // the mean over their minibatches, measured while the weights moved).
        let full_loss = |varmap: &VarMap| {
            let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
            bc_loss(
                &Mlp::load(vb.pp("pos"), &actor_config(32)).unwrap(),
                &samples,
            )
            .unwrap()
        };
        let run = || {
            let varmap = VarMap::new();
            let mut rng = ChaCha8Rng::seed_from_u64(1);
            init_actor(&varmap, "pos", 32, &mut rng).unwrap();
            let before = full_loss(&varmap);
            let config = BcConfig {
                epochs: 20,
                learning_rate: 0.05,
                ..BcConfig::default()
            };
            let losses = train_actor(
                &varmap,
                "pos",
                32,
                LossWeights::uniform([1.0; 3]),
                &samples,
                &config,
                &mut |_, _| {},
            )
            .unwrap();
            (before, full_loss(&varmap), losses)
        };
        let (before, after, losses) = run();
        assert!(after < 0.5 * before, "loss {before} → {after}");
        assert!(losses[losses.len() - 1] < losses[0], "{losses:?}");
        assert_eq!((before, after, losses), run(), "same seed, same training");
    }
}
