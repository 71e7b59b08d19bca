//! The report's tables of what the networks decide: every learned policy on the reference cell
//! with all its rules and with none (`--rules none`), and how often each rule changed its
//! decisions (docs/policy-rules.md).

use super::data::Cell;
use super::page::{failures, steps};
use assembly_cell::policy::shield::RuleId;
use std::fmt::Write as _;

/// `with_rules`: Table 5's cells (the learned policies among them are read); `without`: the
/// same policies on the same episodes with no rule.
pub(super) fn render(md: &mut String, with_rules: &[Cell], without: &[Cell]) {
    let _ = writeln!(
        md,
        "The rules between a learned policy's proposal and the supervisor (docs/policy-rules.md), \
         all on as the cell file has them, then all off (`celld eval --rules none`): the \
         networks' own moves within the step limits. \"changed\" is the share of decisions some \
         rule changed.\n"
    );
    let _ = writeln!(
        md,
        "| policy | success, rules | steps, rules | changed | success, no rules | steps, no rules | failures, no rules |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|");
    let pairs: Vec<(&Cell, &Cell)> = without
        .iter()
        .filter_map(|bare| {
            let ruled = with_rules
                .iter()
                .find(|c| c.controller == bare.controller)?;
            Some((ruled, bare))
        })
        .collect();
    for (ruled, bare) in &pairs {
        let changed = ruled
            .summary
            .rules
            .as_ref()
            .map_or("-".to_string(), |r| format!("{:.3}", r.changed_share()));
        let _ = writeln!(
            md,
            "| {} | {:.3} | {} | {changed} | {:.3} | {} | {} |",
            ruled.controller,
            ruled.summary.success_rate,
            steps(&ruled.summary),
            bare.summary.success_rate,
            steps(&bare.summary),
            failures(&bare.summary)
        );
    }
    let _ = writeln!(md);
    let _ = writeln!(
        md,
        "Share of each policy's decisions each rule changed, with every rule on (rules in \
         pipeline order):\n"
    );
    let names: Vec<&str> = pairs.iter().map(|(c, _)| c.controller.as_str()).collect();
    let _ = writeln!(md, "| rule | {} |", names.join(" | "));
    let _ = writeln!(md, "|---|{}", "---|".repeat(names.len()));
    for id in RuleId::ALL {
        let shares: Vec<String> = pairs
            .iter()
            .map(|(ruled, _)| {
                ruled
                    .summary
                    .rules
                    .as_ref()
                    .map_or("-".to_string(), |r| format!("{:.3}", r.share(id.name())))
            })
            .collect();
        let _ = writeln!(md, "| `{id}` | {} |", shares.join(" | "));
    }
    let _ = writeln!(md);
}
