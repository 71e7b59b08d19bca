//! The supervised half of the training pipeline (paper §3.1–§3.2): demonstrations → BC actors →
//! LSTM selector → a policy file (DESIGN.md §6). `refine` does the TD3 half.
//!
//! Every stage works on one `VarMap` holding tensors by the policy file's names, so a stage's
//! output is a checkpoint (`save_vars`) and the last stage's output is the policy file.

use super::bc::{BcConfig, actor_samples, init_actor, position_samples, train_actor};
use super::dataset::{Normaliser, StepLimits};
use super::demos::DemoEpisode;
use super::selector::{SelectorConfig, agreement, init_selector, sequences, train_selector};
use crate::config::cell::CellConfig;
use crate::policy::Actor;
use crate::policy::file::{PolicyFile, PolicyFileError, PolicyKind, TENSOR_NAMES};
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// The step limits of a cell, as the policy composes its moves with them.
pub fn step_limits(cell: &CellConfig) -> StepLimits {
    StepLimits {
        position_mm: cell.steps.position_mm,
        orientation_deg: cell.steps.orientation_deg,
    }
}

/// The actor prefix of each actor in a policy file.
/// P_z (mm) from which a position step counts as insertion in behaviour cloning
/// ([`BcConfig::insertion_from_pz_mm`]): the tip 1.5 mm above the entrance.
pub fn insertion_from_pz_mm(cell: &CellConfig) -> f64 {
    -(cell.shaft.engaged_length_mm + 1.5)
}

pub fn actor_prefix(actor: Actor) -> &'static str {
    match actor {
        Actor::Position => "pos",
        Actor::Orientation => "ori",
    }
}

/// Behaviour cloning of both actors: a new `VarMap` with `pos.*`, `ori.*`, `obs_mean`, `obs_std`.
/// `on_epoch(actor, epoch, loss)` reports progress.
pub fn behaviour_clone(
    demos: &[DemoEpisode],
    limits: &StepLimits,
    width: usize,
    config: &BcConfig,
    on_epoch: &mut dyn FnMut(Actor, usize, f64),
) -> candle_core::Result<VarMap> {
    let normaliser = Normaliser::fit(demos).goal_centred(config.goal_scales);
    let varmap = VarMap::new();
    insert(&varmap, "obs_mean", &normaliser.mean.map(|v| v as f32))?;
    insert(&varmap, "obs_std", &normaliser.std.map(|v| v as f32))?;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    for actor in [Actor::Position, Actor::Orientation] {
        let prefix = actor_prefix(actor);
        init_actor(&varmap, prefix, width, &mut rng)?;
        let samples = match actor {
            Actor::Position => position_samples(demos, &normaliser, limits, config),
            Actor::Orientation => actor_samples(demos, actor, &normaliser, limits),
        };
        let weights = match actor {
            Actor::Position => {
                let lateral = config.lateral_weight as f32;
                [lateral, lateral, 1.0]
            }
            Actor::Orientation => [1.0; 3],
        };
        let config = match actor {
            Actor::Position => *config,
            Actor::Orientation => BcConfig {
                epochs: config.orientation_epochs,
                ..*config
            },
        };
        train_actor(
            &varmap,
            prefix,
            width,
            weights,
            &samples,
            &config,
            &mut |epoch, loss| on_epoch(actor, epoch, loss),
        )?;
    }
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
/// on `train`, and measures it on `held_out`.
pub fn train_lstm(
    varmap: &VarMap,
    train: &[DemoEpisode],
    held_out: &[DemoEpisode],
    limits: &StepLimits,
    config: &SelectorConfig,
    on_epoch: &mut dyn FnMut(usize, f64),
) -> candle_core::Result<SelectorReport> {
    let normaliser = normaliser_of(varmap)?;
    init_selector(
        varmap,
        config.hidden_size,
        &mut ChaCha8Rng::seed_from_u64(config.seed),
    )?;
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
/// is. `provenance` adds metadata keys (command, seed, …).
pub fn policy_file(
    varmap: &VarMap,
    limits: &StepLimits,
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
    let partial = path.with_extension("safetensors.partial");
    candle_core::safetensors::save(&tensors, &partial)?;
    std::fs::rename(&partial, path)?;
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
        let limits = step_limits(&cell);
        let bc = BcConfig {
            epochs: 2,
            orientation_epochs: 3,
            ..BcConfig::default()
        };
        let mut epochs = Vec::new();
        let varmap = behaviour_clone(&demos, &limits, 16, &bc, &mut |actor, epoch, _| {
            epochs.push((actor, epoch))
        })
        .unwrap();
        let (pos, ori) = (Actor::Position, Actor::Orientation);
        assert_eq!(
            epochs,
            [(pos, 0), (pos, 1), (ori, 0), (ori, 1), (ori, 2)],
            "each actor its own epochs"
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
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(report.losses.len(), 2);
        let provenance = BTreeMap::from([("seed".to_string(), "5".to_string())]);
        let file = policy_file(&varmap, &limits, &provenance).unwrap();
        assert_eq!((file.hidden_size(), file.actor_width()), (8, 16));
        assert_eq!(file.raw_metadata()["seed"], "5");
        // The normaliser is stored in f32.
        let stored = normaliser_of(&varmap).unwrap();
        let fitted = Normaliser::fit(&demos).goal_centred(bc.goal_scales);
        assert_eq!(stored.mean, fitted.mean.map(|v| f64::from(v as f32)));
        assert_eq!(stored.std, fitted.std.map(|v| f64::from(v as f32)));
        // File → bytes → file → vars → file gives the same bytes.
        let reread = PolicyFile::from_bytes(&file.to_bytes()).unwrap();
        let again = policy_file(&vars_of(&reread).unwrap(), &limits, &provenance).unwrap();
        assert_eq!(again.to_bytes(), file.to_bytes());
        // Checkpoint round trip.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("stage.safetensors");
        save_vars(&varmap, &path).unwrap();
        let loaded = policy_file(&load_vars(&path).unwrap(), &limits, &provenance).unwrap();
        assert_eq!(loaded.to_bytes(), file.to_bytes());
        HierarchicalPolicy::from_file(&file).unwrap();
    }

    #[test]
    fn a_policy_without_a_selector_is_refused_by_name() {
        let varmap = VarMap::new();
        insert(&varmap, "obs_mean", &[0.0; 12]).unwrap();
        let limits = StepLimits {
            position_mm: 5.0,
            orientation_deg: 1.0,
        };
        let error = policy_file(&varmap, &limits, &BTreeMap::new()).unwrap_err();
        assert!(error.to_string().contains("high.lstm"), "{error}");
    }
}
