//! The imitation stages of `celld train`: the demonstrations (recorded, read, or relabelled
//! DAgger rollouts), behaviour cloning of both actors and the LSTM selector on the expert's
//! choices.

use super::{BC, BC_POLICY, DEMOS, Fitted, LSTM, Run, bar};
use anyhow::{Context, Result};
use assembly_cell::files::write_atomically;
use assembly_cell::learning::bc::BcConfig;
use assembly_cell::learning::dagger;
use assembly_cell::learning::dataset::GoalScales;
use assembly_cell::learning::demos::{self, DemoEpisode};
use assembly_cell::learning::pipeline::{self, step_limits};
use assembly_cell::learning::run;
use assembly_cell::learning::selector::SelectorConfig;
use assembly_cell::policy::hierarchical::HierarchicalPolicy;
use assembly_cell::policy::learned::LearnedPolicy;
use assembly_cell::policy::{Actor, Controller};
use candle_nn::VarMap;
use indicatif::MultiProgress;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::time::Instant;

impl Run {
    /// The demonstrations, recorded (and saved) on first use; a tenth held out.
    pub(super) fn demos(&self) -> Result<(Vec<DemoEpisode>, Vec<DemoEpisode>)> {
        self.demos_for_the_selector()
            .map(|(train, held_out, _)| (train, held_out))
    }

    /// [`Run::demos`], with the episodes the selector trains on: all of them, or with
    /// `--dagger-actors-only` the demonstrator's own (the DAgger episodes come first in the
    /// file, the held-out tenth last).
    fn demos_for_the_selector(
        &self,
    ) -> Result<(Vec<DemoEpisode>, Vec<DemoEpisode>, Vec<DemoEpisode>)> {
        let path = self.path(DEMOS);
        if !path.exists() {
            match &self.args.demos_file {
                Some(from) => {
                    std::fs::copy(from, &path).with_context(|| {
                        format!("copying --demos-file {} into the run", from.display())
                    })?;
                }
                None => {
                    let started = Instant::now();
                    eprintln!(
                        "recording {} demonstrations of {}…",
                        self.args.demos, self.args.demonstrator
                    );
                    let recorded = demos::record_with(
                        &self.cell,
                        self.demonstration_options(),
                        &self.args.demonstrator,
                        self.args.demos,
                        self.args.seed,
                        self.recording(),
                    );
                    let succeeded = |e: &[DemoEpisode]| e.iter().filter(|e| e.succeeded).count();
                    let mut figures =
                        json!({"episodes": recorded.len(), "succeeded": succeeded(&recorded)});
                    let mut episodes = Vec::new();
                    let mut rounds = Vec::new();
                    for (round, driver) in self.dagger_drivers.iter().enumerate() {
                        let dagger = self.relabel_rollouts(round, driver);
                        rounds.push(json!({
                            "policy": self.args.dagger_policy[round],
                            "episodes": dagger.len(),
                            "policy_succeeded": succeeded(&dagger),
                        }));
                        episodes.extend(dagger);
                    }
                    if !rounds.is_empty() {
                        figures["dagger"] = Value::Array(rounds);
                    }
                    // The policies' episodes first, so that the held-out tenth stays the
                    // demonstrator's own.
                    episodes.extend(recorded);
                    let episodes = dagger::renumbered(episodes);
                    let mut jsonl = Vec::new();
                    demos::write_jsonl(&episodes, &mut jsonl)?;
                    write_atomically(&path, &jsonl)?;
                    let wall_s = started.elapsed().as_secs_f64();
                    self.note("demos", wall_s, figures)?;
                }
            }
        }
        let file = std::fs::File::open(&path)?;
        let episodes = demos::read_jsonl(std::io::BufReader::new(file))
            .with_context(|| format!("{}", path.display()))?;
        run::check_demonstrations(&episodes).with_context(|| format!("{}", path.display()))?;
        let dagger = if self.args.demos_file.is_none() {
            self.args.dagger_policy.len() * self.args.dagger_episodes
        } else {
            0
        };
        let split = dagger::split(episodes, dagger, self.args.dagger_actors_only);
        Ok((split.train, split.held_out, split.selector))
    }

    /// DAgger round `round`'s episodes: `driver` drives, the demonstrator labels (seeds apart
    /// from the demonstrations' and the other rounds').
    fn relabel_rollouts(&self, round: usize, driver: &HierarchicalPolicy) -> Vec<DemoEpisode> {
        eprintln!(
            "recording {} episodes of {} labelled by {}…",
            self.args.dagger_episodes,
            driver.name(),
            self.args.demonstrator
        );
        // The rules as training runs them (docs/policy-rules.md).
        let driver =
            LearnedPolicy::hierarchical(driver.clone()).with_rules(&self.cell.rules.in_training());
        let make = || Box::new(driver.clone()) as Box<dyn Controller>;
        dagger::rollouts(
            &self.cell,
            self.options,
            &self.args.demonstrator,
            &make,
            self.args.dagger_episodes,
            self.args.seed,
            round,
            self.recording(),
        )
    }

    fn bc_config(&self) -> BcConfig {
        BcConfig {
            epochs: self.args.bc_epochs,
            orientation_epochs: self.args.bc_orientation_epochs,
            batch_size: self.args.bc_batch,
            learning_rate: self.args.bc_lr,
            anneal_fraction: self.args.bc_anneal_fraction,
            anneal_factor: self.args.bc_anneal_factor,
            seed: self.args.seed,
            lateral_weight: self.args.bc_lateral_weight,
            bore_lateral_weight: self.args.bc_bore_lateral_weight,
            bore_from_pz_mm: self.inputs.entrance_input_mm(&self.cell),
            insertion_repeat: self.args.bc_insertion_repeat,
            insertion_from_pz_mm: pipeline::insertion_from_input_mm(&self.cell, self.inputs),
            goal_scales: GoalScales {
                lateral_mm: self.args.norm_lateral_std_mm,
                depth_mm: self.args.norm_depth_std_mm,
                tilt_deg: self.args.norm_tilt_std_deg,
            },
            inputs: self.inputs,
            orientation_label_floor: self.args.bc_orientation_label_floor,
            position_label_floor: self.args.bc_position_label_floor,
        }
    }

    pub(super) fn bc(&self) -> Result<()> {
        if !self.should_run(BC)? {
            return Ok(());
        }
        let (train, _) = self.demos()?;
        let bc = self.fit_bc(&train, &MultiProgress::new())?;
        self.save_bc(&bc)
    }

    pub(super) fn lstm(&self) -> Result<()> {
        if !self.should_run(LSTM)? {
            return Ok(());
        }
        let varmap = pipeline::load_vars(&self.needs(BC, "bc")?)?;
        let (_, held_out, selector) = self.demos_for_the_selector()?;
        let lstm = self.fit_selector(&selector, &held_out, varmap, &MultiProgress::new())?;
        self.save_lstm(&lstm)
    }

    /// `train all`'s first stages. The selector needs only the normaliser from behaviour
    /// cloning, so on a fresh run both train at once (the two actors and the selector on three
    /// threads) and give the files `train bc` then `train lstm` would, byte for byte. A run that
    /// has either output already goes stage by stage.
    pub(super) fn bc_and_lstm(&self) -> Result<()> {
        if self.path(BC).exists() || self.path(LSTM).exists() {
            self.bc()?;
            return self.lstm();
        }
        let (train, held_out, selector) = self.demos_for_the_selector()?;
        let normaliser =
            pipeline::training_normaliser(&train, &self.bc_config(), self.init.as_ref())?;
        let selector_vars = pipeline::normaliser_vars(&normaliser)?;
        let progress = MultiProgress::new();
        let (bc, lstm) = std::thread::scope(|scope| {
            let lstm =
                scope.spawn(|| self.fit_selector(&selector, &held_out, selector_vars, &progress));
            let bc = self.fit_bc(&train, &progress);
            (bc, lstm.join().expect("the selector's thread panicked"))
        });
        // BC's output is kept even if the selector failed: `--resume` then trains only the
        // selector.
        let bc = bc?;
        self.save_bc(&bc)?;
        let lstm = lstm?;
        for actor in [Actor::Position, Actor::Orientation] {
            let prefix = format!("{}.", pipeline::actor_prefix(actor));
            pipeline::merge_vars(&lstm.varmap, &bc.varmap, &prefix);
        }
        self.save_lstm(&lstm)
    }

    /// Behaviour cloning of both actors; writes bc_curve.csv.
    fn fit_bc(&self, train: &[DemoEpisode], progress: &MultiProgress) -> Result<Fitted> {
        let started = Instant::now();
        let config = self.bc_config();
        let total = config.epochs + config.orientation_epochs;
        let bar = bar(total as u64, "bc").within(progress);
        let mut curve = String::from("actor,epoch,loss\n");
        let mut last = BTreeMap::new();
        let varmap = pipeline::behaviour_clone(
            train,
            &step_limits(&self.cell, self.inputs),
            self.args.actor_width,
            &config,
            self.init.as_ref(),
            &mut |actor, epoch, loss| {
                let name = actor_name(actor);
                curve.push_str(&format!("{name},{epoch},{loss}\n"));
                last.insert(name, loss);
                bar.set_message(format!("{name} loss {loss:.4}"));
                bar.inc(1);
            },
        )
        .context("behaviour cloning (no checkpoint written)")?;
        bar.finish_and_clear();
        write_atomically(&self.path("bc_curve.csv"), curve.as_bytes())?;
        Ok(Fitted {
            varmap,
            wall_s: started.elapsed().as_secs_f64(),
            figures: json!({
                "final_loss": last,
                "config": format!("{config:?}"),
                "init_policy": self.args.init_policy,
            }),
        })
    }

    fn save_bc(&self, bc: &Fitted) -> Result<()> {
        pipeline::save_vars(&bc.varmap, &self.path(BC))?;
        self.note("bc", bc.wall_s, bc.figures.clone())
    }

    /// The LSTM selector, trained into `varmap` (which holds the normaliser); writes
    /// lstm_curve.csv.
    fn fit_selector(
        &self,
        train: &[DemoEpisode],
        held_out: &[DemoEpisode],
        varmap: VarMap,
        progress: &MultiProgress,
    ) -> Result<Fitted> {
        let started = Instant::now();
        let config = SelectorConfig {
            hidden_size: self.args.lstm_hidden,
            epochs: self.args.lstm_epochs,
            batch_size: self.args.lstm_batch,
            learning_rate: self.args.lstm_lr,
            seed: self.args.seed,
        };
        let bar = bar(config.epochs as u64, "lstm").within(progress);
        let mut curve = String::from("epoch,loss\n");
        let report = pipeline::train_lstm(
            &varmap,
            train,
            held_out,
            &step_limits(&self.cell, self.inputs),
            &config,
            self.init.as_ref(),
            &mut |epoch, loss| {
                curve.push_str(&format!("{epoch},{loss}\n"));
                bar.set_message(format!("loss {loss:.4}"));
                bar.inc(1);
            },
        )
        .context("LSTM selector training (no checkpoint written)")?;
        bar.finish_and_clear();
        write_atomically(&self.path("lstm_curve.csv"), curve.as_bytes())?;
        eprintln!(
            "selector: held-out agreement with the expert's actor choice {:.4}",
            report.held_out_agreement
        );
        Ok(Fitted {
            varmap,
            wall_s: started.elapsed().as_secs_f64(),
            figures: json!({
                "held_out_agreement": report.held_out_agreement,
                "final_loss": report.losses.last(),
                "config": format!("{config:?}"),
            }),
        })
    }

    /// Writes the selector stage's checkpoint (actors, normaliser, selector) and the BC policy.
    fn save_lstm(&self, lstm: &Fitted) -> Result<()> {
        pipeline::save_vars(&lstm.varmap, &self.path(LSTM))?;
        let limits = step_limits(&self.cell, self.inputs);
        let file =
            pipeline::policy_file(&lstm.varmap, &limits, self.inputs, &self.provenance("bc"))?;
        file.save(self.path(BC_POLICY))?;
        self.note("lstm", lstm.wall_s, lstm.figures.clone())
    }
}

fn actor_name(actor: Actor) -> &'static str {
    match actor {
        Actor::Position => "position",
        Actor::Orientation => "orientation",
    }
}
