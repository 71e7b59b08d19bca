//! The reinforcement stages of `celld train`: TD3 from the BC actors inside the hierarchy
//! (`train td3`), and the flat TD3 baseline (`train flat`), with their learning curves.

use super::{
    FLAT_CHECKPOINT, FLAT_POLICY, FLAT_PROGRESS, LSTM, POLICY, Run, TD3_CHECKPOINT, TD3_PROGRESS,
    bar,
};
use anyhow::{Context, Result, bail};
use assembly_cell::files::write_atomically;
use assembly_cell::learning::dataset::Normaliser;
use assembly_cell::learning::flat::{FlatConfig, FlatProgress, FlatTraining};
use assembly_cell::learning::pipeline::{self, step_limits};
use assembly_cell::learning::refine::step_size::StepSizeConfig;
use assembly_cell::learning::refine::{EpisodeRecord, RefineConfig, RefineProgress, Refinement};
use assembly_cell::learning::td3::Td3Config;
use assembly_cell::policy::record::DEMONSTRATORS;
use candle_core::Tensor;
use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

impl Run {
    /// Whether a TD3 stage resumes from its checkpoint (--resume, with the checkpoint there);
    /// `None` when it need not run (its `output` is there and kept). Refuses to start afresh
    /// over a checkpoint.
    fn resumes(&self, checkpoint: &Path, output: &str) -> Result<Option<bool>> {
        let resuming = self.args.resume && checkpoint.is_file();
        if !resuming && !self.should_run(output)? {
            return Ok(None);
        }
        if !resuming && checkpoint.exists() {
            bail!(
                "{} exists; pass --resume to continue it, or choose another --out",
                checkpoint.display()
            );
        }
        Ok(Some(resuming))
    }

    pub(super) fn td3(&self) -> Result<()> {
        let checkpoint = self.path(TD3_CHECKPOINT);
        let progress_path = self.path(TD3_PROGRESS);
        let Some(resuming) = self.resumes(&checkpoint, POLICY)? else {
            return Ok(());
        };
        let varmap = pipeline::load_vars(&self.needs(LSTM, "lstm")?)?;
        let defaults = RefineConfig::default();
        let mut config = RefineConfig {
            episodes: self.args.td3_episodes,
            eval_every: self.args.eval_every,
            eval_episodes: self.args.eval_episodes,
            td3: Td3Config {
                actor_learning_rate: self.args.td3_actor_lr,
                exploration_noise: self.args.td3_noise.unwrap_or(if self.args.no_bc_init {
                    Td3Config::default().exploration_noise
                } else {
                    defaults.td3.exploration_noise
                }),
                trust_region: Some(self.args.td3_trust_region).filter(|&r| r > 0.0),
                ..defaults.td3.with_target_noise(self.args.td3_target_noise)
            },
            critic_warmup_episodes: self.args.td3_critic_warmup,
            parallel_episodes: self.args.td3_parallel_episodes,
            step_size: self.args.td3_step_size.then_some(StepSizeConfig {
                coarse_noise: self.args.td3_step_noise,
                coarse_trust_region: self.args.td3_step_trust_region,
                fine_trust_region: self.args.td3_step_fine_trust_region,
                learning_rate: self.args.td3_step_lr,
                progress_reward_per_mm: self.args.td3_step_progress_reward,
            }),
            inputs: self.inputs,
            randomise: self.recording().randomise,
            ..defaults
        };
        if self.args.td3_demonstrations > 0 {
            let demonstrator = DEMONSTRATORS
                .into_iter()
                .find(|&name| name == self.args.demonstrator)
                .context("the demonstrator was checked when the run started")?;
            config = config.beside_demonstrator(demonstrator, self.args.td3_demonstrations);
            config.td3.demo_regularisation = Some(self.args.td3_demo_alpha);
        }
        let mut refinement = Refinement::new(
            &self.cell,
            self.options,
            varmap,
            config,
            !self.args.no_bc_init,
            self.args.seed,
        )?;
        if resuming {
            let (tensors, progress) =
                load_checkpoint::<RefineProgress>(&checkpoint, &progress_path)?;
            refinement.restore(&tensors, progress)?;
            eprintln!("resuming TD3 at episode {}", refinement.episode());
        }
        let started = Instant::now();
        let bar = bar(config.episodes as u64, "td3");
        bar.set_position(refinement.episode() as u64);
        if refinement.validations().is_empty() {
            refinement.validate()?;
        }
        while refinement.episode() < config.episodes {
            let record = match refinement.train_episode() {
                Ok(record) => record,
                Err(error) => bail!(
                    "TD3 diverged at episode {}: {error}; the last good checkpoint is {}",
                    refinement.episode(),
                    checkpoint.display()
                ),
            };
            let done = refinement.episode();
            if config.eval_every > 0 && done % config.eval_every == 0 {
                let v = refinement.validate()?;
                bar.set_message(format!(
                    "validation success {:.3}, steps {:.1}",
                    v.success_rate,
                    v.avg_steps.unwrap_or(f64::NAN)
                ));
            } else if done % 10 == 0 {
                bar.set_message(format!(
                    "episode return {:.1}, steps {}",
                    record.return_, record.steps
                ));
            }
            bar.inc(1);
            if done % self.args.checkpoint_every == 0 || done == config.episodes {
                let (tensors, progress) = refinement.checkpoint()?;
                save_checkpoint(&tensors, &progress, &checkpoint, &progress_path)?;
            }
        }
        if refinement.validations().last().map(|v| v.episode) != Some(config.episodes) {
            refinement.validate()?;
        }
        bar.finish_and_clear();
        self.write_curve(&refinement)?;
        let (best, vars) = refinement.best();
        let limits = step_limits(&self.cell, self.inputs);
        pipeline::policy_file(vars, &limits, self.inputs, &self.provenance("hierarchical"))?
            .save(self.path(POLICY))?;
        if let Some(best) = best {
            eprintln!(
                "TD3: best validation at episode {}: success {:.3}, avg steps {:.2}",
                best.episode,
                best.success_rate,
                best.avg_steps.unwrap_or(f64::NAN)
            );
        }
        self.note(
            "td3",
            started.elapsed().as_secs_f64(),
            json!({
                "best": best,
                "validations": refinement.validations(),
                "step_size": config.step_size.is_some(),
                "kept_robots": self.options.kept_robots,
            }),
        )
    }

    fn write_curve(&self, refinement: &Refinement) -> Result<()> {
        self.write_curve_files(
            "td3_curve",
            refinement.curve(),
            json!(refinement.validations()),
        )
    }

    /// `{stem}.csv` (episode, return, success, steps) and `{stem}.json` (episodes and
    /// validations; what `celld report --curve` reads).
    fn write_curve_files(
        &self,
        stem: &str,
        curve: &[EpisodeRecord],
        validations: Value,
    ) -> Result<()> {
        let mut csv = String::from("episode,return,success,steps\n");
        for r in curve {
            csv.push_str(&format!(
                "{},{},{},{}\n",
                r.episode,
                r.return_,
                u8::from(r.success),
                r.steps
            ));
        }
        write_atomically(&self.path(&format!("{stem}.csv")), csv.as_bytes())?;
        write_atomically(
            &self.path(&format!("{stem}.json")),
            &serde_json::to_vec_pretty(&json!({
                "episodes": curve,
                "validations": validations,
            }))?,
        )?;
        Ok(())
    }

    /// The flat TD3 baseline: fresh weights, no BC, no hierarchy; the demonstrations are read
    /// (or recorded) for their states only, to fit the input normaliser.
    pub(super) fn flat(&self) -> Result<()> {
        let checkpoint = self.path(FLAT_CHECKPOINT);
        let progress_path = self.path(FLAT_PROGRESS);
        let Some(resuming) = self.resumes(&checkpoint, FLAT_POLICY)? else {
            return Ok(());
        };
        if self.args.td3_episodes == 0 {
            bail!("--td3-episodes must be at least 1");
        }
        let (mut demos, held_out) = self.demos()?;
        demos.extend(held_out);
        let config = FlatConfig {
            episodes: self.args.td3_episodes,
            eval_every: self.args.eval_every,
            eval_episodes: self.args.eval_episodes,
            td3: Td3Config {
                hidden: self.args.flat_hidden,
                actor_learning_rate: self.args.td3_actor_lr,
                exploration_noise: self
                    .args
                    .td3_noise
                    .unwrap_or(Td3Config::default().exploration_noise),
                ..Td3Config::default()
            },
            critic_warmup_episodes: self.args.td3_critic_warmup,
            ..FlatConfig::default()
        };
        let mut training = FlatTraining::new(
            &self.cell,
            self.options,
            &Normaliser::fit(&demos),
            config,
            self.args.seed,
        )?;
        if resuming {
            let (tensors, progress) = load_checkpoint::<FlatProgress>(&checkpoint, &progress_path)?;
            training.restore(&tensors, progress)?;
            eprintln!("resuming flat TD3 at episode {}", training.episode());
        }
        let started = Instant::now();
        let bar = bar(config.episodes as u64, "flat");
        bar.set_position(training.episode() as u64);
        let checkpoint_every = self.args.checkpoint_every;
        let result = training.run(&mut |training, record, validation| {
            let done = training.episode();
            if let Some(v) = validation {
                bar.set_message(format!(
                    "validation success {:.3}, return {:.1}",
                    v.success_rate, v.avg_reward
                ));
            } else if done % 10 == 0 {
                bar.set_message(format!(
                    "episode return {:.1}, steps {}",
                    record.return_, record.steps
                ));
            }
            bar.inc(1);
            if done % checkpoint_every == 0 || done == config.episodes {
                let (tensors, progress) = training.checkpoint();
                save_checkpoint(&tensors, &progress, &checkpoint, &progress_path)
                    .map_err(candle_core::Error::wrap)?;
            }
            Ok(())
        });
        if let Err(error) = result {
            bar.abandon();
            bail!(
                "flat TD3 stopped at episode {} (no policy written): {error}; the last good checkpoint is {}",
                training.episode(),
                checkpoint.display()
            );
        }
        bar.finish_and_clear();
        self.write_curve_files(
            "td3-flat_curve",
            training.curve(),
            json!(training.validations()),
        )?;
        let (best, vars) = training.best();
        training
            .policy_file(vars, &self.provenance("td3"))?
            .save(self.path(FLAT_POLICY))?;
        if let Some(best) = best {
            eprintln!(
                "flat TD3: best validation at episode {}: success {:.3}, avg steps {:.2}, avg return {:.1}",
                best.episode,
                best.success_rate,
                best.avg_steps.unwrap_or(f64::NAN),
                best.avg_reward
            );
        }
        self.note(
            "td3-flat",
            started.elapsed().as_secs_f64(),
            json!({
                "best": best,
                "validations": training.validations(),
                "config": format!("{config:?}"),
            }),
        )
    }
}

/// The key of a checkpoint's metadata that holds its progress.
const PROGRESS_KEY: &str = "progress";

/// Writes a TD3 stage's checkpoint: the tensors, with the progress in the file's metadata, so
/// that one rename replaces both (a crash leaves the previous checkpoint whole, never the
/// weights of one episode with the progress of another). The progress is also written beside
/// it as JSON, to read.
fn save_checkpoint<P: Serialize>(
    tensors: &HashMap<String, Tensor>,
    progress: &P,
    checkpoint: &Path,
    progress_path: &Path,
) -> Result<()> {
    let progress = serde_json::to_string(progress)?;
    let metadata = HashMap::from([(PROGRESS_KEY.to_string(), progress.clone())]);
    let bytes = safetensors::serialize(tensors.iter(), Some(metadata))?;
    write_atomically(checkpoint, &bytes)?;
    write_atomically(progress_path, progress.as_bytes())?;
    Ok(())
}

/// A TD3 stage's checkpoint: its tensors and its progress (from the checkpoint's metadata; a
/// checkpoint written before it held its progress is read with its progress file).
fn load_checkpoint<P: DeserializeOwned>(
    checkpoint: &Path,
    progress_path: &Path,
) -> Result<(HashMap<String, Tensor>, P)> {
    let bytes = std::fs::read(checkpoint).with_context(|| format!("{}", checkpoint.display()))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
        .with_context(|| format!("{}", checkpoint.display()))?;
    let progress = match header.metadata().as_ref().and_then(|m| m.get(PROGRESS_KEY)) {
        Some(progress) => serde_json::from_str(progress)
            .with_context(|| format!("the progress in {}", checkpoint.display()))?,
        None => serde_json::from_slice(&std::fs::read(progress_path)?)
            .with_context(|| format!("{}", progress_path.display()))?,
    };
    let tensors = candle_core::safetensors::load_buffer(&bytes, &candle_core::Device::Cpu)?;
    Ok((tensors, progress))
}
