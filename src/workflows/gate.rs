//! The evaluation gate, the one rule for every way a registered policy reaches the robot: a
//! policy drives the cell only when it is the active policy (activation passed this gate, or
//! an admin forced it), when its bytes are a bundled policy's, or when its latest finished
//! evaluation on this cell's current configuration (the twin as the cell file says: no
//! mismatch, not on drawn cells) reached `policies.activation_threshold`. An admin may pass a
//! shut gate with a reason, which the audit log keeps.

use super::{Context, Result};
use crate::storage::policies::{self, Evaluation, Policy};
use crate::storage::tokens::hash_bytes;
use std::sync::OnceLock;

/// Why the gate lets a policy through.
#[derive(Debug, Clone, PartialEq)]
pub enum Pass {
    /// The active policy.
    Active,
    /// The same bytes as a bundled policy.
    Bundled,
    /// This evaluation on this cell reached the threshold.
    Evaluated { evaluation_id: i64 },
}

/// The sha256 of every bundled policy file.
fn bundled_hashes() -> &'static [String] {
    static HASHES: OnceLock<Vec<String>> = OnceLock::new();
    HASHES.get_or_init(|| {
        crate::policy::LEARNED_CONTROLLERS
            .iter()
            .filter_map(|name| crate::policy::bundled_policy(name))
            .map(hash_bytes)
            .collect()
    })
}

/// Whether `evaluation` ran on the cell with `cell_hash` as its file says: the kind the gate
/// reads.
fn nominal_on(evaluation: &Evaluation, cell_hash: &str) -> bool {
    evaluation.cell_hash == cell_hash
        && evaluation.noise_scale == 1.0
        && evaluation.calibration_scale == 1.0
        && evaluation.fault.is_none()
        && !evaluation.randomise_cells
}

/// The gate on evaluations alone, pure: `finished` is the latest finished evaluation of
/// `policy_id` on this cell (as [`policies::latest_evaluation_on`] reads it), `latest` its
/// newest evaluation of any kind. Passes with the evaluation's id, or says why not, with the
/// figures; `needed_for` names what asks ("activation", "a job").
pub fn judge(
    policy_id: i64,
    cell_hash: &str,
    threshold: f64,
    needed_for: &str,
    finished: Option<&Evaluation>,
    latest: Option<&Evaluation>,
) -> std::result::Result<i64, String> {
    let running = latest
        .filter(|e| matches!(e.status.as_str(), "queued" | "running") && nominal_on(e, cell_hash))
        .map(|e| {
            format!(
                "evaluation {} ({} episodes) is still {}",
                e.id, e.episodes, e.status
            )
        });
    match finished {
        None => Err(match running {
            Some(running) => format!(
                "policy {policy_id} has no finished evaluation on this cell (config \
                 {cell_hash}) yet: {running}"
            ),
            None => format!(
                "policy {policy_id} has no finished evaluation on this cell (config \
                 {cell_hash}): POST /api/policies/{policy_id}/evaluate first"
            ),
        }),
        Some(e) if e.success_rate.unwrap_or(0.0) < threshold => {
            let mut why = format!(
                "policy {policy_id} reached success {:.3} over {} episodes on this cell \
                 (evaluation {}); {needed_for} needs ≥ {threshold}",
                e.success_rate.unwrap_or(0.0),
                e.episodes,
                e.id
            );
            if let Some(running) = running {
                why.push_str(&format!("; {running}"));
            }
            Err(why)
        }
        Some(e) => Ok(e.id),
    }
}

/// [`judge`] on what storage holds for policy `id` on this cell; also answers the finished
/// evaluation it read.
pub async fn evaluated(
    context: &Context,
    id: i64,
    needed_for: &str,
) -> Result<(Option<Evaluation>, std::result::Result<i64, String>)> {
    let cell_hash = context.cell_config.config_hash();
    let finished = policies::latest_evaluation_on(&context.db, id, &cell_hash).await?;
    let latest = policies::latest_evaluation(&context.db, id).await?;
    let verdict = judge(
        id,
        &cell_hash,
        context.settings.policies.activation_threshold,
        needed_for,
        finished.as_ref(),
        latest.as_ref(),
    );
    Ok((finished, verdict))
}

/// Whether `policy` may drive a job: how it passes, or why not.
pub async fn may_drive(
    context: &Context,
    policy: &Policy,
) -> Result<std::result::Result<Pass, String>> {
    if policy.status == "active" {
        return Ok(Ok(Pass::Active));
    }
    if bundled_hashes().contains(&policy.sha256) {
        return Ok(Ok(Pass::Bundled));
    }
    let (_, verdict) = evaluated(context, policy.id, "a job").await?;
    Ok(verdict.map(|evaluation_id| Pass::Evaluated { evaluation_id }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn evaluation(id: i64, status: &str, success: Option<f64>) -> Evaluation {
        Evaluation {
            id,
            policy_id: 7,
            status: status.to_string(),
            episodes: 40,
            seed: 1,
            cell_hash: "cell".to_string(),
            noise_scale: 1.0,
            calibration_scale: 1.0,
            fault: None,
            randomise_cells: false,
            rules: "all".to_string(),
            success_rate: success,
            avg_steps: None,
            failures: json!({}),
            error: None,
            requested_by: "test".to_string(),
            started_at: String::new(),
            finished_at: None,
            queue_position: None,
        }
    }

    #[test]
    fn the_gate_says_why_it_is_shut_with_the_figures() {
        let never = judge(7, "cell", 0.95, "a job", None, None).unwrap_err();
        assert!(never.contains("no finished evaluation") && never.contains("config cell"));
        assert!(never.contains("/api/policies/7/evaluate"), "{never}");

        let running = evaluation(3, "running", None);
        let waiting = judge(7, "cell", 0.95, "a job", None, Some(&running)).unwrap_err();
        assert!(
            waiting.contains("evaluation 3 (40 episodes) is still running"),
            "{waiting}"
        );
        // A running evaluation under a mismatch, or of another cell, is not the gate's.
        let mut other_cell = running.clone();
        other_cell.cell_hash = "elsewhere".to_string();
        let mut noisy = running.clone();
        noisy.noise_scale = 2.0;
        for other in [other_cell, noisy] {
            let why = judge(7, "cell", 0.95, "a job", None, Some(&other)).unwrap_err();
            assert!(!why.contains("still running"), "{why}");
        }

        // 37 of 40 is 0.925, under 0.95.
        let short = evaluation(2, "done", Some(37.0 / 40.0));
        let failed = judge(7, "cell", 0.95, "a job", Some(&short), Some(&short)).unwrap_err();
        assert!(
            failed.contains("success 0.925 over 40 episodes")
                && failed.contains("evaluation 2")
                && failed.contains("a job needs ≥ 0.95"),
            "{failed}"
        );
        let both = judge(7, "cell", 0.95, "activation", Some(&short), Some(&running));
        let both = both.unwrap_err();
        assert!(both.contains("activation needs ≥ 0.95") && both.contains("still running"));

        // 38 of 40 is 0.95: the threshold itself passes.
        let enough = evaluation(4, "done", Some(38.0 / 40.0));
        assert_eq!(judge(7, "cell", 0.95, "a job", Some(&enough), None), Ok(4));
    }

    #[test]
    fn every_bundled_policy_file_is_known_by_its_hash() {
        assert_eq!(
            bundled_hashes().len(),
            crate::policy::LEARNED_CONTROLLERS.len()
        );
        let default = crate::policy::bundled_policy(crate::policy::DEFAULT_POLICY).unwrap();
        assert!(bundled_hashes().contains(&hash_bytes(default)));
        assert!(!bundled_hashes().contains(&hash_bytes(b"not a policy")));
    }
}
