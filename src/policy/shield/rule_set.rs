//! The rules' names, in pipeline order, and a set of them (what fired at a step).

use serde::{Serialize, Serializer};

/// A rule of the shield. The order is the pipeline's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum RuleId {
    ActorWithWork,
    FullStep,
    CentredAsDemonstrated,
    TurnedAsDemonstrated,
    DeepestMove,
    NotPastTheAxis,
    NotPastLevel,
    PivotInBore,
    CarefulStepUnderNoise,
    NoisyCameraDescent,
    CentresAfterARefusal,
    SteeredAgainstDrift,
    FullStepAfterUncertainty,
    StandoffWhileUnsure,
}

impl RuleId {
    /// Every rule, in pipeline order.
    pub const ALL: [RuleId; 14] = [
        RuleId::ActorWithWork,
        RuleId::FullStep,
        RuleId::CentredAsDemonstrated,
        RuleId::TurnedAsDemonstrated,
        RuleId::DeepestMove,
        RuleId::NotPastTheAxis,
        RuleId::NotPastLevel,
        RuleId::PivotInBore,
        RuleId::CarefulStepUnderNoise,
        RuleId::NoisyCameraDescent,
        RuleId::CentresAfterARefusal,
        RuleId::SteeredAgainstDrift,
        RuleId::FullStepAfterUncertainty,
        RuleId::StandoffWhileUnsure,
    ];

    /// The name in the cell file's `[rules]`, `--rules` and the stored steps.
    pub fn name(self) -> &'static str {
        match self {
            RuleId::ActorWithWork => "actor_with_work",
            RuleId::FullStep => "full_step",
            RuleId::CentredAsDemonstrated => "centred_as_demonstrated",
            RuleId::TurnedAsDemonstrated => "turned_as_demonstrated",
            RuleId::DeepestMove => "deepest_move",
            RuleId::NotPastTheAxis => "not_past_the_axis",
            RuleId::NotPastLevel => "not_past_level",
            RuleId::PivotInBore => "pivot_in_bore",
            RuleId::CarefulStepUnderNoise => "careful_step_under_noise",
            RuleId::NoisyCameraDescent => "noisy_camera_descent",
            RuleId::CentresAfterARefusal => "centres_after_a_refusal",
            RuleId::SteeredAgainstDrift => "steered_against_drift",
            RuleId::FullStepAfterUncertainty => "full_step_after_uncertainty",
            RuleId::StandoffWhileUnsure => "standoff_while_unsure",
        }
    }

    /// The rule of a name.
    pub fn from_name(name: &str) -> Option<RuleId> {
        RuleId::ALL.into_iter().find(|id| id.name() == name)
    }

    /// Whether the rule limits an actor's move (5–8), rather than reading the network's output
    /// as its demonstrators' move (1–4) or making it as the cell runs it (9–14).
    pub fn is_limit(self) -> bool {
        matches!(
            self,
            RuleId::DeepestMove
                | RuleId::NotPastTheAxis
                | RuleId::NotPastLevel
                | RuleId::PivotInBore
        )
    }

    /// Whether the rule makes the move as the cell runs the policy (9–14): these read what the
    /// cell has learned as it runs (the camera's noise, the robot's drift, the refusals), and the
    /// demonstrators a policy learns from decide on the state alone, so training's rollouts run
    /// without them (decision 0026).
    pub fn is_where_it_runs(self) -> bool {
        self >= RuleId::CarefulStepUnderNoise
    }

    fn bit(self) -> u16 {
        1 << (self as u16)
    }
}

impl std::fmt::Display for RuleId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A set of rules, iterated in pipeline order; serialised as a list of names.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct RuleSet(u16);

impl RuleSet {
    /// Every rule.
    pub fn all() -> Self {
        RuleId::ALL.into_iter().collect()
    }

    pub fn insert(&mut self, id: RuleId) {
        self.0 |= id.bit();
    }

    pub fn contains(&self, id: RuleId) -> bool {
        self.0 & id.bit() != 0
    }

    pub fn is_empty(&self) -> bool {
        self.0 == 0
    }

    pub fn len(&self) -> usize {
        self.0.count_ones() as usize
    }

    /// The rules in pipeline order.
    pub fn iter(self) -> impl Iterator<Item = RuleId> {
        RuleId::ALL.into_iter().filter(move |id| self.contains(*id))
    }

    /// The names in pipeline order.
    pub fn names(self) -> Vec<&'static str> {
        self.iter().map(RuleId::name).collect()
    }

    /// The set of `names`; the first unknown name is the error.
    pub fn from_names<'a>(names: impl IntoIterator<Item = &'a str>) -> Result<Self, String> {
        names
            .into_iter()
            .map(|name| RuleId::from_name(name).ok_or_else(|| name.to_string()))
            .collect()
    }
}

impl FromIterator<RuleId> for RuleSet {
    fn from_iter<I: IntoIterator<Item = RuleId>>(iter: I) -> Self {
        let mut set = RuleSet::default();
        iter.into_iter().for_each(|id| set.insert(id));
        set
    }
}

impl Serialize for RuleSet {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_seq(self.iter().map(RuleId::name))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_are_distinct() {
        for id in RuleId::ALL {
            assert_eq!(RuleId::from_name(id.name()), Some(id));
        }
        let names: std::collections::BTreeSet<_> = RuleId::ALL.iter().map(|id| id.name()).collect();
        assert_eq!(names.len(), RuleId::ALL.len());
        assert_eq!(RuleId::from_name("no_such_rule"), None);
    }

    #[test]
    fn a_set_iterates_in_pipeline_order_whatever_the_insertion_order() {
        let set: RuleSet = [
            RuleId::StandoffWhileUnsure,
            RuleId::ActorWithWork,
            RuleId::FullStep,
        ]
        .into_iter()
        .collect();
        assert_eq!(
            set.names(),
            ["actor_with_work", "full_step", "standoff_while_unsure"]
        );
        assert_eq!(set.len(), 3);
        assert_eq!(
            serde_json::to_string(&set).unwrap(),
            r#"["actor_with_work","full_step","standoff_while_unsure"]"#
        );
        assert_eq!(RuleSet::all().len(), 14);
        assert_eq!(
            RuleSet::from_names(["full_step", "bogus"]),
            Err("bogus".to_string())
        );
    }
}
