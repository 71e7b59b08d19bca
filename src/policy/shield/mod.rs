//! The shield: the rules between a learned controller's proposal and the collision supervisor,
//! as one ordered pipeline (docs/policy-rules.md, decision 0053).
//!
//! The networks propose a move: the hierarchical policy's selector picks an actor and a step
//! size and the actor a direction; a flat policy gives the whole move. Each rule then reads
//! the observation and the move so far, and may change the move; the rules run in the order
//! of [`RuleId::ALL`], one file each, each naming the failure it prevents and the decision that
//! introduced it. After the last rule every component of the translation is clamped to the
//! step limit (a bound, not a rule). The supervisor checks what comes out.
//!
//! The shield is built in one place, [`Shield::new`], from the cell file's `[rules]`
//! ([`RulesConfig`]): every rule can be switched off there, or for one evaluation with
//! `celld eval --rules`. Every learned controller runs through it ([`super::learned`]), and
//! TD3's episodes make their moves through it too. Each decision carries a [`ShieldTrace`]: the
//! proposal and the rules that changed it, in order, which every stored step keeps.
//!
//! Rules 1–8 shape the move of the actor the proposal names, so they apply to the
//! hierarchical policies only; rules 9–14 apply to every learned policy (9–11 to a position
//! move only).

mod actor_with_work;
mod careful_step_under_noise;
mod centred_as_demonstrated;
mod centres_after_a_refusal;
mod config;
mod deepest_move;
mod full_step;
mod full_step_after_uncertainty;
mod noisy_camera_descent;
mod not_past_level;
mod not_past_the_axis;
mod pivot_in_bore;
mod rule_set;
mod standoff_while_unsure;
mod steered_against_drift;
mod turned_as_demonstrated;

pub use actor_with_work::{ActorWithWork, BEING_SEATED_WITHIN_MM};
pub use careful_step_under_noise::CarefulStepUnderNoise;
pub use centred_as_demonstrated::{CentredAsDemonstrated, demonstrators_centring_mm};
pub use config::{RuleSelection, RuleSelectionError, RulesConfig};
pub use deepest_move::{deepest_move_mm, holds_depth_after};
pub use full_step::{FULL_STEP_LABEL_SHARE, FullStep};
pub use full_step_after_uncertainty::FullStepAfterUncertainty;
pub use noisy_camera_descent::NoisyCameraDescent;
pub use not_past_level::not_past_level;
pub use not_past_the_axis::{not_past_the_axis, past_the_axis_mm};
pub use pivot_in_bore::pivot_in_bore;
pub use rule_set::{RuleId, RuleSet};
pub use standoff_while_unsure::no_nearer_than_the_standoff_mm;
pub use turned_as_demonstrated::TurnedAsDemonstrated;

use super::Actor;
use crate::geometry::Move;
use crate::sim::Observation;

/// What a rule reads besides the move: the observation and the policy's step limits.
#[derive(Debug, Clone, Copy)]
pub struct RuleContext<'a> {
    pub observation: &'a Observation,
    /// The position actor's full step (mm).
    pub step_limit_mm: f64,
    /// The orientation actor's full step (deg).
    pub step_limit_deg: f64,
}

/// The move as the rules shape it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shaped {
    /// The actor that acts (None for a flat policy, or a hold).
    pub actor: Option<Actor>,
    pub action: Move,
    /// The sideways part is the demonstrators' exact centring, which the robot's learned drift
    /// does not steer (set by rules 10 and 11, `noisy_camera_descent` and
    /// `centres_after_a_refusal`; rule 12 then leaves it alone).
    pub exact_sideways: bool,
}

impl Shaped {
    /// Whether this is a position move (rules on the position actor's move apply).
    pub fn is_position(&self) -> bool {
        self.actor == Some(Actor::Position)
    }

    pub fn is_orientation(&self) -> bool {
        self.actor == Some(Actor::Orientation)
    }
}

/// What the shield did to one decision: the controller's own proposal, the actor it named,
/// and the rules that changed the move, in pipeline order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShieldTrace {
    pub proposed: Move,
    pub proposed_actor: Option<Actor>,
    pub fired: RuleSet,
}

/// One stage of the pipeline: a rule and its parameters (and state, for the one rule that
/// remembers the refusals since the last move).
#[derive(Debug, Clone)]
enum Stage {
    FullStep(FullStep),
    CentredAsDemonstrated(CentredAsDemonstrated),
    TurnedAsDemonstrated(TurnedAsDemonstrated),
    DeepestMove,
    NotPastTheAxis,
    NotPastLevel,
    PivotInBore,
    CarefulStepUnderNoise(CarefulStepUnderNoise),
    NoisyCameraDescent(NoisyCameraDescent),
    CentresAfterARefusal,
    SteeredAgainstDrift,
    FullStepAfterUncertainty(FullStepAfterUncertainty),
    StandoffWhileUnsure,
}

impl Stage {
    fn id(&self) -> RuleId {
        match self {
            Stage::FullStep(_) => RuleId::FullStep,
            Stage::CentredAsDemonstrated(_) => RuleId::CentredAsDemonstrated,
            Stage::TurnedAsDemonstrated(_) => RuleId::TurnedAsDemonstrated,
            Stage::DeepestMove => RuleId::DeepestMove,
            Stage::NotPastTheAxis => RuleId::NotPastTheAxis,
            Stage::NotPastLevel => RuleId::NotPastLevel,
            Stage::PivotInBore => RuleId::PivotInBore,
            Stage::CarefulStepUnderNoise(_) => RuleId::CarefulStepUnderNoise,
            Stage::NoisyCameraDescent(_) => RuleId::NoisyCameraDescent,
            Stage::CentresAfterARefusal => RuleId::CentresAfterARefusal,
            Stage::SteeredAgainstDrift => RuleId::SteeredAgainstDrift,
            Stage::FullStepAfterUncertainty(_) => RuleId::FullStepAfterUncertainty,
            Stage::StandoffWhileUnsure => RuleId::StandoffWhileUnsure,
        }
    }

    fn apply(&mut self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        match self {
            Stage::FullStep(rule) => rule.apply(context, shaped),
            Stage::CentredAsDemonstrated(rule) => rule.apply(context, shaped),
            Stage::TurnedAsDemonstrated(rule) => rule.apply(context, shaped),
            Stage::DeepestMove => deepest_move::apply(context, shaped),
            Stage::NotPastTheAxis => not_past_the_axis::apply(context, shaped),
            Stage::NotPastLevel => not_past_level::apply(context, shaped),
            Stage::PivotInBore => pivot_in_bore::apply(context, shaped),
            Stage::CarefulStepUnderNoise(rule) => rule.apply(context, shaped),
            Stage::NoisyCameraDescent(rule) => rule.apply(context, shaped),
            Stage::CentresAfterARefusal => centres_after_a_refusal::apply(context, shaped),
            Stage::SteeredAgainstDrift => steered_against_drift::apply(context, shaped),
            Stage::FullStepAfterUncertainty(rule) => rule.apply(context, shaped),
            Stage::StandoffWhileUnsure => standoff_while_unsure::apply(context, shaped),
        }
    }
}

/// The rules in pipeline order, as the cell file's `[rules]` switches them.
#[derive(Debug, Clone)]
pub struct Shield {
    config: RulesConfig,
    actor_with_work: Option<ActorWithWork>,
    stages: Vec<Stage>,
}

impl Default for Shield {
    /// Every rule, with today's parameters.
    fn default() -> Self {
        Shield::new(&RulesConfig::default())
    }
}

impl Shield {
    /// The pipeline of the rules `config` switches on, with its parameters.
    pub fn new(config: &RulesConfig) -> Self {
        let on = |id| config.is_on(id);
        let mut stages = Vec::with_capacity(RuleId::ALL.len());
        let mut push = |id: RuleId, stage: Stage| {
            if on(id) {
                stages.push(stage);
            }
        };
        push(RuleId::FullStep, Stage::FullStep(config.full_step));
        push(
            RuleId::CentredAsDemonstrated,
            Stage::CentredAsDemonstrated(config.centred_as_demonstrated),
        );
        push(
            RuleId::TurnedAsDemonstrated,
            Stage::TurnedAsDemonstrated(config.turned_as_demonstrated),
        );
        push(RuleId::DeepestMove, Stage::DeepestMove);
        push(RuleId::NotPastTheAxis, Stage::NotPastTheAxis);
        push(RuleId::NotPastLevel, Stage::NotPastLevel);
        push(RuleId::PivotInBore, Stage::PivotInBore);
        push(
            RuleId::CarefulStepUnderNoise,
            Stage::CarefulStepUnderNoise(config.careful_step_under_noise),
        );
        push(
            RuleId::NoisyCameraDescent,
            Stage::NoisyCameraDescent(config.noisy_camera_descent),
        );
        push(RuleId::CentresAfterARefusal, Stage::CentresAfterARefusal);
        push(RuleId::SteeredAgainstDrift, Stage::SteeredAgainstDrift);
        push(
            RuleId::FullStepAfterUncertainty,
            Stage::FullStepAfterUncertainty(config.full_step_after_uncertainty),
        );
        push(RuleId::StandoffWhileUnsure, Stage::StandoffWhileUnsure);
        Shield {
            config: *config,
            actor_with_work: on(RuleId::ActorWithWork).then_some(config.actor_with_work),
            stages,
        }
    }

    /// The rules and parameters the pipeline was built from.
    pub fn config(&self) -> &RulesConfig {
        &self.config
    }

    /// Starts a new episode (forgets the refusals since the last move).
    pub fn reset(&mut self) {
        for stage in &mut self.stages {
            if let Stage::FullStepAfterUncertainty(rule) = stage {
                *rule = FullStepAfterUncertainty {
                    refused_near_the_wall: false,
                    ..*rule
                };
            }
        }
    }

    /// The actor that acts for the selector's choice `selected`: the choice, or where rule 1
    /// ([`ActorWithWork`]) is on, the actor with work to do. The caller notes the rule where
    /// the two differ.
    pub fn choose_actor(&self, observation: &Observation, selected: Actor) -> Actor {
        match &self.actor_with_work {
            Some(rule) => rule.actor(selected, observation),
            None => selected,
        }
    }

    /// Rules 2–14 on `shaped`, in order, each noted in `fired` where it changed the move;
    /// then the translation clamped to the step limit.
    pub fn shape(&mut self, context: &RuleContext<'_>, shaped: &mut Shaped, fired: &mut RuleSet) {
        for stage in &mut self.stages {
            let before = shaped.action;
            stage.apply(context, shaped);
            if shaped.action != before {
                fired.insert(stage.id());
            }
        }
        shaped.action.translation_mm = shaped
            .action
            .translation_mm
            .map(|v| v.clamp(-context.step_limit_mm, context.step_limit_mm));
    }

    /// Only the rules that limit an actor's move (5–8: [`RuleId::is_limit`]), as TD3 reads the
    /// actor's output back from the move it made.
    pub fn limit(&self, context: &RuleContext<'_>, shaped: &mut Shaped) {
        for stage in &self.stages {
            if stage.id().is_limit() {
                // The limits hold no state: a clone changes nothing that lasts.
                stage.clone().apply(context, shaped);
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests;
