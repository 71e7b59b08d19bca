//! The supervised half of the training pipeline (paper §3.1–§3.2): demonstrations → BC actors →
//! LSTM selector → a policy file (docs/design.md §6). `refine` does the TD3 half.
//!
//! Every stage works on one `VarMap` holding tensors by the policy file's names, so a stage's
//! output is a checkpoint (`save_vars`) and the last stage's output is the policy file.

use super::bc::{
    BcConfig, LossWeights, RelativeToLabel, actor_samples, init_actor, position_samples,
    train_actor,
};
use super::dataset::{Normaliser, StepLimits};
use super::demos::DemoEpisode;
use super::selector::{SelectorConfig, agreement, init_selector, sequences, train_selector};
use crate::config::cell::CellConfig;
use crate::policy::Actor;
use crate::policy::file::{PolicyFile, PolicyFileError, PolicyKind, TENSOR_NAMES};
use crate::policy::inputs::PolicyInputs;
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// The step limits of a cell, as a policy that reads `inputs` composes its moves with them.
pub fn step_limits(cell: &CellConfig, inputs: PolicyInputs) -> StepLimits {
    StepLimits {
        position_mm: cell.steps.position_mm,
        orientation_deg: cell.steps.orientation_deg,
        inputs,
    }
}

/// The input's slot 8 (mm) from which a position step counts as insertion in behaviour
/// cloning ([`BcConfig::insertion_from_pz_mm`]): the tip 1.5 mm above the entrance.
pub fn insertion_from_input_mm(cell: &CellConfig, inputs: PolicyInputs) -> f64 {
    inputs.entrance_input_mm(cell) - 1.5
}

/// The actor prefix of each actor in a policy file.
pub fn actor_prefix(actor: Actor) -> &'static str {
    match actor {
        Actor::Position => "pos",
        Actor::Orientation => "ori",
    }
}

/// The input normaliser of a policy trained on `demos`.
pub fn fit_normaliser(demos: &[DemoEpisode], config: &BcConfig) -> Normaliser {
    Normaliser::fit(demos).goal_centred(config.goal_scales, config.inputs)
}

/// The normaliser training uses: `start`'s when fine-tuning a policy (its weights were trained
/// on those inputs), else the one fitted to `demos`.
pub fn training_normaliser(
    demos: &[DemoEpisode],
    config: &BcConfig,
    start: Option<&PolicyFile>,
) -> candle_core::Result<Normaliser> {
    match start {
        Some(file) => normaliser_of(&vars_of(file)?),
        None => Ok(fit_normaliser(demos, config)),
    }
}

/// Copies `start`'s tensors whose names start with `prefix` into `varmap`, as new variables.
fn start_from(varmap: &VarMap, start: &PolicyFile, prefix: &str) -> candle_core::Result<()> {
    merge_vars(varmap, &vars_of(start)?, prefix);
    Ok(())
}

/// A new `VarMap` holding `normaliser` (`obs_mean`, `obs_std`), which every stage starts from:
/// the selector needs nothing else from behaviour cloning, so the two can train at once.
pub fn normaliser_vars(normaliser: &Normaliser) -> candle_core::Result<VarMap> {
    let varmap = VarMap::new();
    insert(&varmap, "obs_mean", &normaliser.mean.map(|v| v as f32))?;
    insert(&varmap, "obs_std", &normaliser.std.map(|v| v as f32))?;
    Ok(varmap)
}

/// Copies the variables of `from` whose names start with `prefix` into `into`.
pub fn merge_vars(into: &VarMap, from: &VarMap, prefix: &str) {
    let from = from.data().lock().expect("var map lock");
    let mut into = into.data().lock().expect("var map lock");
    for (name, var) in from.iter().filter(|(name, _)| name.starts_with(prefix)) {
        into.insert(name.clone(), var.clone());
    }
}

/// Behaviour cloning of both actors: a new `VarMap` with `pos.*`, `ori.*`, `obs_mean`, `obs_std`.
/// The actors start from fresh seeded weights, or from `start`'s actors and normaliser
/// (fine-tuning a policy, whose actors must be `width` wide). `on_epoch(actor, epoch, loss)`
/// reports progress.
pub fn behaviour_clone(
    demos: &[DemoEpisode],
    limits: &StepLimits,
    width: usize,
    config: &BcConfig,
    start: Option<&PolicyFile>,
    on_epoch: &mut dyn FnMut(Actor, usize, f64),
) -> candle_core::Result<VarMap> {
    let normaliser = training_normaliser(demos, config, start)?;
    let varmap = normaliser_vars(&normaliser)?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut jobs = Vec::with_capacity(2);
    for actor in [Actor::Position, Actor::Orientation] {
        match start {
            Some(file) => start_from(&varmap, file, &format!("{}.", actor_prefix(actor)))?,
            None => init_actor(&varmap, actor_prefix(actor), width, &mut rng)?,
        }
        let samples = match actor {
            Actor::Position => position_samples(demos, &normaliser, limits, config),
            Actor::Orientation => actor_samples(demos, actor, &normaliser, limits),
        };
        let components = match actor {
            Actor::Position => {
                let lateral = config.lateral_weight as f32;
                [lateral, lateral, 1.0]
            }
            Actor::Orientation => [1.0; 3],
        };
        let label_floor = match actor {
            Actor::Position => config.position_label_floor,
            Actor::Orientation => config.orientation_label_floor,
        };
        let relative_to_label =
            label_floor.map(|floor| RelativeToLabel::over(&samples, floor as f32));
        let weights = LossWeights {
            components,
            bore_lateral: config.bore_lateral_weight as f32,
            bore_from_input: ((config.bore_from_pz_mm - normaliser.mean[8]) / normaliser.std[8])
                as f32,
            relative_to_label,
        };
        let config = match actor {
            Actor::Position => *config,
            Actor::Orientation => BcConfig {
                epochs: config.orientation_epochs,
                ..*config
            },
        };
        jobs.push((actor, samples, weights, config));
    }
    // The actors' training does not depend on each other (each has its own weights, samples
    // and seeded shuffle), so they train at once, one thread each: the same weights as one
    // after the other, in the time of the longer.
    let (progress, reports) = std::sync::mpsc::channel();
    std::thread::scope(|scope| {
        let workers: Vec<_> = jobs
            .iter()
            .map(|(actor, samples, weights, config)| {
                let (progress, varmap) = (progress.clone(), &varmap);
                scope.spawn(move || {
                    train_actor(
                        varmap,
                        actor_prefix(*actor),
                        width,
                        *weights,
                        samples,
                        config,
                        &mut |epoch, loss| {
                            let _ = progress.send((*actor, epoch, loss));
                        },
                    )
                })
            })
            .collect();
        drop(progress);
        for (actor, epoch, loss) in reports {
            on_epoch(actor, epoch, loss);
        }
        workers
            .into_iter()
            .map(|worker| worker.join().expect("a behaviour cloning thread panicked"))
            .collect::<candle_core::Result<Vec<_>>>()
    })?;
    Ok(varmap)
}

/// The normaliser stored in a stage's `VarMap`.
pub fn normaliser_of(varmap: &VarMap) -> candle_core::Result<Normaliser> {
    let get = |name: &str| -> candle_core::Result<[f64; 12]> {
        let data = varmap.data().lock().expect("var map lock");
        let var = data
            .get(name)
            .ok_or_else(|| candle_core::Error::Msg(format!("checkpoint has no `{name}`")))?;
        let values = var.as_tensor().to_vec1::<f32>()?;
        if values.len() != 12 {
            candle_core::bail!("`{name}` has {} values, expected 12", values.len());
        }
        Ok(std::array::from_fn(|i| f64::from(values[i])))
    };
    Ok(Normaliser {
        mean: get("obs_mean")?,
        std: get("obs_std")?,
    })
}

/// What the selector stage reports: its losses and its agreement with the expert's actor
/// choices on held-out demonstrations.
#[derive(Debug, Clone, PartialEq)]
pub struct SelectorReport {
    pub losses: Vec<f64>,
    pub held_out_agreement: f64,
}

/// Trains the LSTM selector into `varmap` (which holds the normaliser from `behaviour_clone`),
/// on `train`, and measures it on `held_out`. It starts from fresh seeded weights, or from
/// `start`'s selector (fine-tuning; its hidden size must be `config.hidden_size`).
pub fn train_lstm(
    varmap: &VarMap,
    train: &[DemoEpisode],
    held_out: &[DemoEpisode],
    limits: &StepLimits,
    config: &SelectorConfig,
    start: Option<&PolicyFile>,
    on_epoch: &mut dyn FnMut(usize, f64),
) -> candle_core::Result<SelectorReport> {
    let normaliser = normaliser_of(varmap)?;
    match start {
        Some(file) => start_from(varmap, file, "high.")?,
        None => init_selector(
            varmap,
            config.hidden_size,
            &mut ChaCha8Rng::seed_from_u64(config.seed),
        )?,
    }
    let losses = train_selector(
        varmap,
        &sequences(train, &normaliser, limits),
        config,
        on_epoch,
    )?;
    let held_out_agreement = agreement(
        varmap,
        config.hidden_size,
        &sequences(held_out, &normaliser, limits),
    )?;
    Ok(SelectorReport {
        losses,
        held_out_agreement,
    })
}

/// The policy file made of `varmap`'s tensors (all of [`TENSOR_NAMES`]), checked as an upload
/// is, for a network that reads `inputs`. `provenance` adds metadata keys (command, seed, …).
pub fn policy_file(
    varmap: &VarMap,
    limits: &StepLimits,
    inputs: PolicyInputs,
    provenance: &BTreeMap<String, String>,
) -> Result<PolicyFile, PolicyFileError> {
    let data = varmap.data().lock().expect("var map lock");
    let mut tensors = Vec::with_capacity(TENSOR_NAMES.len());
    for name in TENSOR_NAMES {
        let Some(var) = data.get(name) else {
            return Err(PolicyFileError::MissingTensor {
                name: name.to_string(),
                kind: PolicyKind::Hierarchical,
            });
        };
        let tensor = var.as_tensor();
        let values = tensor
            .flatten_all()
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| PolicyFileError::UnexpectedTensor {
                name: name.to_string(),
                reason: e.to_string(),
            })?;
        tensors.push((name.to_string(), tensor.dims().to_vec(), values));
    }
    let mut metadata = PolicyFile::standard_metadata(limits.position_mm, limits.orientation_deg);
    metadata.extend(provenance.clone());
    inputs.mark(&mut metadata);
    PolicyFile::new(tensors, metadata)
}

/// A `VarMap` holding a policy file's tensors (to refine it further).
pub fn vars_of(file: &PolicyFile) -> candle_core::Result<VarMap> {
    let varmap = VarMap::new();
    {
        let mut data = varmap.data().lock().expect("var map lock");
        for (name, tensor) in file.to_candle(&Device::Cpu)? {
            data.insert(name, Var::from_tensor(&tensor)?);
        }
    }
    Ok(varmap)
}

/// Writes every tensor of `varmap` to a safetensors checkpoint, atomically (a crash leaves the
/// previous checkpoint whole).
pub fn save_vars(varmap: &VarMap, path: &Path) -> candle_core::Result<()> {
    let tensors: HashMap<String, Tensor> = {
        let data = varmap.data().lock().expect("var map lock");
        data.iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect()
    };
    let bytes = safetensors::serialize(&tensors, None).map_err(candle_core::Error::wrap)?;
    crate::files::write_atomically(path, &bytes)?;
    Ok(())
}

/// Reads a checkpoint written by [`save_vars`].
pub fn load_vars(path: &Path) -> candle_core::Result<VarMap> {
    let varmap = VarMap::new();
    {
        let mut data = varmap.data().lock().expect("var map lock");
        for (name, tensor) in candle_core::safetensors::load(path, &Device::Cpu)? {
            data.insert(name, Var::from_tensor(&tensor)?);
        }
    }
    Ok(varmap)
}

fn insert(varmap: &VarMap, name: &str, values: &[f32]) -> candle_core::Result<()> {
    let tensor = Tensor::from_slice(values, values.len(), &Device::Cpu)?;
    varmap
        .data()
        .lock()
        .expect("var map lock")
        .insert(name.to_string(), Var::from_tensor(&tensor)?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learning::demos::record_expert;
    use crate::policy::hierarchical::HierarchicalPolicy;
    use crate::sim::EnvOptions;

    #[test]
    fn stages_make_a_policy_file_that_round_trips() {
        let cell = CellConfig::reference();
        let demos = record_expert(&cell, EnvOptions::from_cell(&cell), 6, 5);
        let limits = step_limits(&cell, PolicyInputs::Absolute);
        let bc = BcConfig {
            epochs: 2,
            orientation_epochs: 3,
            ..BcConfig::default()
        };
        let mut epochs = Vec::new();
        let varmap = behaviour_clone(&demos, &limits, 16, &bc, None, &mut |actor, epoch, _| {
            epochs.push((actor, epoch))
        })
        .unwrap();
        // The actors train at once: each reports its own epochs, in order.
        let of = |actor| -> Vec<usize> {
            epochs
                .iter()
                .filter(|(a, _)| *a == actor)
                .map(|(_, epoch)| *epoch)
                .collect()
        };
        assert_eq!(of(Actor::Position), [0, 1], "the position actor's epochs");
        assert_eq!(
            of(Actor::Orientation),
            [0, 1, 2],
            "the orientation actor's own"
        );
        let selector = SelectorConfig {
            hidden_size: 8,
            epochs: 2,
            ..SelectorConfig::default()
        };
        let report = train_lstm(
            &varmap,
            &demos[..4],
            &demos[4..],
            &limits,
            &selector,
            None,
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(report.losses.len(), 2);
        let provenance = BTreeMap::from([("seed".to_string(), "5".to_string())]);
        let file = policy_file(&varmap, &limits, PolicyInputs::Absolute, &provenance).unwrap();
        assert_eq!((file.hidden_size(), file.actor_width()), (8, 16));
        assert_eq!(file.raw_metadata()["seed"], "5");
        // The normaliser is stored in f32.
        let stored = normaliser_of(&varmap).unwrap();
        let fitted = Normaliser::fit(&demos).goal_centred(bc.goal_scales, bc.inputs);
        assert_eq!(stored.mean, fitted.mean.map(|v| f64::from(v as f32)));
        assert_eq!(stored.std, fitted.std.map(|v| f64::from(v as f32)));
        // File → bytes → file → vars → file gives the same bytes.
        let reread = PolicyFile::from_bytes(&file.to_bytes()).unwrap();
        let again = policy_file(
            &vars_of(&reread).unwrap(),
            &limits,
            PolicyInputs::Absolute,
            &provenance,
        )
        .unwrap();
        assert_eq!(again.to_bytes(), file.to_bytes());
        // Checkpoint round trip.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("stage.safetensors");
        save_vars(&varmap, &path).unwrap();
        let loaded = policy_file(
            &load_vars(&path).unwrap(),
            &limits,
            PolicyInputs::Absolute,
            &provenance,
        )
        .unwrap();
        assert_eq!(loaded.to_bytes(), file.to_bytes());
        HierarchicalPolicy::from_file(&file).unwrap();
    }

    #[test]
    fn both_actors_at_once_train_as_one_after_the_other() {
        let cell = CellConfig::reference();
        let demos = record_expert(&cell, EnvOptions::from_cell(&cell), 6, 5);
        let limits = step_limits(&cell, PolicyInputs::Absolute);
        let bc = BcConfig {
            epochs: 3,
            orientation_epochs: 5,
            lateral_weight: 2.0,
            seed: 9,
            ..BcConfig::default()
        };
        let together = behaviour_clone(&demos, &limits, 16, &bc, None, &mut |_, _, _| {}).unwrap();
        // The reference: the same initialisation, then each actor alone, in turn.
        let normaliser = fit_normaliser(&demos, &bc);
        let alone = normaliser_vars(&normaliser).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(bc.seed);
        init_actor(&alone, "pos", 16, &mut rng).unwrap();
        init_actor(&alone, "ori", 16, &mut rng).unwrap();
        let position = position_samples(&demos, &normaliser, &limits, &bc);
        train_actor(
            &alone,
            "pos",
            16,
            LossWeights::uniform([2.0, 2.0, 1.0]),
            &position,
            &bc,
            &mut |_, _| {},
        )
        .unwrap();
        let orientation = actor_samples(&demos, Actor::Orientation, &normaliser, &limits);
        let ori_config = BcConfig {
            epochs: bc.orientation_epochs,
            ..bc
        };
        train_actor(
            &alone,
            "ori",
            16,
            LossWeights::uniform([1.0; 3]),
            &orientation,
            &ori_config,
            &mut |_, _| {},
        )
        .unwrap();
        let values = |vars: &VarMap| -> BTreeMap<String, Vec<f32>> {
            let data = vars.data().lock().unwrap();
            data.iter()
                .map(|(name, var)| {
                    let flat = var.as_tensor().flatten_all().unwrap();
                    (name.clone(), flat.to_vec1::<f32>().unwrap())
                })
                .collect()
        };
        let (together, alone) = (values(&together), values(&alone));
        assert_eq!(together.len(), 14, "6 tensors per actor and the normaliser");
        assert_eq!(together, alone);
    }

    #[test]
    fn a_policy_without_a_selector_is_refused_by_name() {
        let varmap = VarMap::new();
        insert(&varmap, "obs_mean", &[0.0; 12]).unwrap();
        let limits = StepLimits {
            position_mm: 5.0,
            orientation_deg: 1.0,
            inputs: PolicyInputs::Absolute,
        };
        let error =
            policy_file(&varmap, &limits, PolicyInputs::Absolute, &BTreeMap::new()).unwrap_err();
        assert!(error.to_string().contains("high.lstm"), "{error}");
    }
}
