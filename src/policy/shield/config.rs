//! The cell file's `[rules]`: each rule switched on or off, with its parameters (today's values
//! by default), and the selection `celld eval --rules` and evaluation requests make.

use super::{
    ActorWithWork, CarefulStepUnderNoise, CentredAsDemonstrated, FullStep,
    FullStepAfterUncertainty, NoisyCameraDescent, RuleId, RuleSet, TurnedAsDemonstrated,
};
use serde::{Deserialize, Deserializer, Serialize};

/// A rule with no parameters: on or off.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Switch {
    pub enabled: bool,
}

impl Default for Switch {
    fn default() -> Self {
        Switch { enabled: true }
    }
}

/// `[rules]` of a cell file: one table per rule (`[rules.full_step]`, `enabled = false`, and
/// its parameters). A missing table is the rule on with today's parameters.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RulesConfig {
    pub actor_with_work: ActorWithWork,
    pub full_step: FullStep,
    pub centred_as_demonstrated: CentredAsDemonstrated,
    pub turned_as_demonstrated: TurnedAsDemonstrated,
    pub deepest_move: Switch,
    pub not_past_the_axis: Switch,
    pub not_past_level: Switch,
    pub pivot_in_bore: Switch,
    pub careful_step_under_noise: CarefulStepUnderNoise,
    pub noisy_camera_descent: NoisyCameraDescent,
    pub centres_after_a_refusal: Switch,
    pub steered_against_drift: Switch,
    pub full_step_after_uncertainty: FullStepAfterUncertainty,
    pub standoff_while_unsure: Switch,
}

impl RulesConfig {
    /// Whether rule `id` is switched on.
    pub fn is_on(&self, id: RuleId) -> bool {
        let mut copy = *self;
        *copy.switch(id)
    }

    fn set(&mut self, id: RuleId, on: bool) {
        *self.switch(id) = on;
    }

    /// Rule `id`'s `enabled`.
    fn switch(&mut self, id: RuleId) -> &mut bool {
        match id {
            RuleId::ActorWithWork => &mut self.actor_with_work.enabled,
            RuleId::FullStep => &mut self.full_step.enabled,
            RuleId::CentredAsDemonstrated => &mut self.centred_as_demonstrated.enabled,
            RuleId::TurnedAsDemonstrated => &mut self.turned_as_demonstrated.enabled,
            RuleId::DeepestMove => &mut self.deepest_move.enabled,
            RuleId::NotPastTheAxis => &mut self.not_past_the_axis.enabled,
            RuleId::NotPastLevel => &mut self.not_past_level.enabled,
            RuleId::PivotInBore => &mut self.pivot_in_bore.enabled,
            RuleId::CarefulStepUnderNoise => &mut self.careful_step_under_noise.enabled,
            RuleId::NoisyCameraDescent => &mut self.noisy_camera_descent.enabled,
            RuleId::CentresAfterARefusal => &mut self.centres_after_a_refusal.enabled,
            RuleId::SteeredAgainstDrift => &mut self.steered_against_drift.enabled,
            RuleId::FullStepAfterUncertainty => &mut self.full_step_after_uncertainty.enabled,
            RuleId::StandoffWhileUnsure => &mut self.standoff_while_unsure.enabled,
        }
    }

    /// The rules switched on.
    pub fn enabled(&self) -> RuleSet {
        RuleId::ALL
            .into_iter()
            .filter(|id| self.is_on(*id))
            .collect()
    }

    /// These parameters with the rules `selection` names switched on and every other off
    /// (`all` keeps them as they are).
    pub fn selected(&self, selection: &RuleSelection) -> Self {
        let mut config = *self;
        if let Some(on) = selection.rules() {
            RuleId::ALL
                .into_iter()
                .for_each(|id| config.set(id, on.contains(id)));
        }
        config
    }

    /// These rules as training's rollouts run them (DAgger's and TD3's episodes): without the
    /// rules that make a move as the cell runs it ([`RuleId::is_where_it_runs`]).
    pub fn in_training(&self) -> Self {
        let mut config = *self;
        RuleId::ALL
            .into_iter()
            .filter(|id| id.is_where_it_runs())
            .for_each(|id| config.set(id, false));
        config
    }

    /// Whether these are today's rules and parameters (a cell file without `[rules]`): such a
    /// cell's config hash is the one it had before rules could be switched.
    pub fn is_default(&self) -> bool {
        *self == RulesConfig::default()
    }

    /// The first parameter out of its range, as (key, value, the range).
    pub fn invalid(&self) -> Option<(&'static str, f64, &'static str)> {
        let shares = [
            (
                "rules.actor_with_work.tolerance_factor_above_bore",
                self.actor_with_work.tolerance_factor_above_bore,
                1.0,
                10.0,
            ),
            (
                "rules.actor_with_work.being_seated_within_mm",
                self.actor_with_work.being_seated_within_mm,
                0.0,
                100.0,
            ),
            (
                "rules.full_step.from_share",
                self.full_step.from_share,
                0.0,
                0.93,
            ),
            (
                "rules.centred_as_demonstrated.shortest_share",
                self.centred_as_demonstrated.shortest_share,
                0.0,
                1.0,
            ),
            (
                "rules.centred_as_demonstrated.approach_standoff_factor",
                self.centred_as_demonstrated.approach_standoff_factor,
                0.0,
                100.0,
            ),
            (
                "rules.turned_as_demonstrated.shortest_share",
                self.turned_as_demonstrated.shortest_share,
                0.0,
                1.0,
            ),
            (
                "rules.careful_step_under_noise.noisy_camera_scale",
                self.careful_step_under_noise.noisy_camera_scale,
                0.0,
                100.0,
            ),
            (
                "rules.careful_step_under_noise.from_mm",
                self.careful_step_under_noise.from_mm,
                0.0,
                1000.0,
            ),
            (
                "rules.careful_step_under_noise.careful_depth_mm",
                self.careful_step_under_noise.careful_depth_mm,
                0.0,
                1000.0,
            ),
            (
                "rules.careful_step_under_noise.careful_step_mm",
                self.careful_step_under_noise.careful_step_mm,
                0.001,
                1000.0,
            ),
            (
                "rules.noisy_camera_descent.noisy_camera_scale",
                self.noisy_camera_descent.noisy_camera_scale,
                0.0,
                100.0,
            ),
            (
                "rules.noisy_camera_descent.from_mm",
                self.noisy_camera_descent.from_mm,
                0.0,
                1000.0,
            ),
            (
                "rules.full_step_after_uncertainty.from_mm",
                self.full_step_after_uncertainty.from_mm,
                0.0,
                1000.0,
            ),
            (
                "rules.full_step_after_uncertainty.ends_short_of_the_seat_mm",
                self.full_step_after_uncertainty.ends_short_of_the_seat_mm,
                0.0,
                1000.0,
            ),
        ];
        shares
            .into_iter()
            .find(|(_, value, low, high)| !(low..=high).contains(&value))
            .map(|(key, value, low, high)| {
                let range = match (low, high) {
                    (0.0, 1.0) => "between 0 and 1",
                    (0.0, 0.93) => "between 0 and 0.93 (the labels' ceiling)",
                    (1.0, 10.0) => "between 1 and 10",
                    (0.001, _) => "between 0.001 and 1000",
                    _ => "between 0 and its upper bound (100 or 1000)",
                };
                (key, value, range)
            })
    }
}

/// Which rules run: every rule the cell switches on, none, or only those named (of those the
/// cell's parameters describe). `all`, `none` or a comma-separated list of rule names.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RuleSelection {
    #[default]
    All,
    None,
    Only(RuleSet),
}

/// A selection that names something that is not a rule.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "`{name}` is not a rule; rules are all, none or a comma-separated list (no spaces) of: {known}"
)]
pub struct RuleSelectionError {
    pub name: String,
    pub known: String,
}

impl RuleSelection {
    /// The rules switched on, or None for `all` (the cell's own switches stand).
    pub fn rules(&self) -> Option<RuleSet> {
        match self {
            RuleSelection::All => None,
            RuleSelection::None => Some(RuleSet::default()),
            RuleSelection::Only(set) => Some(*set),
        }
    }

    /// Parses `all`, `none` or `a,b,c` (rule names, nothing else between the commas).
    pub fn parse(text: &str) -> Result<Self, RuleSelectionError> {
        match text {
            "all" => Ok(RuleSelection::All),
            "none" => Ok(RuleSelection::None),
            list => Self::of_names(list.split(',')),
        }
    }

    /// Only the rules `names` (none for no name).
    pub fn of_names<'a>(
        names: impl IntoIterator<Item = &'a str>,
    ) -> Result<Self, RuleSelectionError> {
        let set = RuleSet::from_names(names).map_err(|name| RuleSelectionError {
            name,
            known: RuleId::ALL.map(RuleId::name).join(", "),
        })?;
        Ok(if set.is_empty() {
            RuleSelection::None
        } else {
            RuleSelection::Only(set)
        })
    }

    /// `all`, `none` or the names, comma-separated (what [`RuleSelection::parse`] reads).
    pub fn label(&self) -> String {
        match self {
            RuleSelection::All => "all".to_string(),
            RuleSelection::None => "none".to_string(),
            RuleSelection::Only(set) => set.names().join(","),
        }
    }
}

impl std::str::FromStr for RuleSelection {
    type Err = RuleSelectionError;
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        RuleSelection::parse(text)
    }
}

impl Serialize for RuleSelection {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(&self.label())
    }
}

/// `"all"`, `"none"`, `"a,b"` or `["a", "b"]`.
impl<'de> Deserialize<'de> for RuleSelection {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Text(String),
            List(Vec<String>),
        }
        let selection = match Raw::deserialize(deserializer)? {
            Raw::Text(text) => RuleSelection::parse(&text),
            Raw::List(names) => RuleSelection::of_names(names.iter().map(String::as_str)),
        };
        selection.map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cell_file_switches_a_rule_and_keeps_the_others_as_they_are() {
        let config: RulesConfig = toml::from_str(
            "[full_step]\nenabled = false\n[turned_as_demonstrated]\nshortest_share = 0.9\n",
        )
        .unwrap();
        assert!(!config.is_on(RuleId::FullStep));
        assert_eq!(config.enabled().len(), 13);
        assert_eq!(config.turned_as_demonstrated.shortest_share, 0.9);
        assert!(config.turned_as_demonstrated.enabled);
        assert!(!config.is_default());
        assert!(toml::from_str::<RulesConfig>("").unwrap().is_default());
        let typo = toml::from_str::<RulesConfig>("[full_stepp]\nenabled = false\n").unwrap_err();
        assert!(typo.to_string().contains("full_stepp"), "{typo}");
    }

    #[test]
    fn a_selection_parses_round_trips_and_names_an_unknown_rule() {
        assert_eq!(RuleSelection::parse("all"), Ok(RuleSelection::All));
        assert_eq!(RuleSelection::parse("none"), Ok(RuleSelection::None));
        let only = RuleSelection::parse("pivot_in_bore,full_step").unwrap();
        assert_eq!(only.label(), "full_step,pivot_in_bore");
        // Nothing but names between the commas: what the request's schema describes.
        for bad in [
            "",
            " full_step",
            "full_step,",
            "full_step,,pivot_in_bore",
            "All",
        ] {
            assert!(RuleSelection::parse(bad).is_err(), "{bad:?}");
        }
        let empty: RuleSelection = serde_json::from_str("[]").unwrap();
        assert_eq!(empty, RuleSelection::None);
        assert_eq!(RuleSelection::parse(&only.label()), Ok(only));
        let e = RuleSelection::parse("full_step,fullstep").unwrap_err();
        assert_eq!(e.name, "fullstep");
        assert!(e.to_string().contains("standoff_while_unsure"));
        let from_list: RuleSelection = serde_json::from_str(r#"["full_step"]"#).unwrap();
        let from_text: RuleSelection = serde_json::from_str(r#""full_step""#).unwrap();
        assert_eq!(from_list, from_text);
        assert!(serde_json::from_str::<RuleSelection>(r#"["nope"]"#).is_err());
    }

    #[test]
    fn a_selection_switches_exactly_the_rules_it_names() {
        let mut cell = RulesConfig::default();
        cell.steered_against_drift.enabled = false;
        assert_eq!(cell.selected(&RuleSelection::All), cell);
        assert!(cell.selected(&RuleSelection::None).enabled().is_empty());
        let only = cell.selected(&RuleSelection::parse("steered_against_drift").unwrap());
        assert_eq!(only.enabled().names(), ["steered_against_drift"]);
        // Parameters are kept.
        assert_eq!(only.full_step.from_share, cell.full_step.from_share);
    }

    #[test]
    fn a_parameter_out_of_range_is_named() {
        let mut config = RulesConfig::default();
        assert_eq!(config.invalid(), None);
        config.centred_as_demonstrated.shortest_share = 1.5;
        let (key, value, _) = config.invalid().unwrap();
        assert_eq!(
            (key, value),
            ("rules.centred_as_demonstrated.shortest_share", 1.5)
        );
        config.centred_as_demonstrated.shortest_share = f64::NAN;
        assert!(config.invalid().is_some());
    }
}
