//! Step rows: written in batches by the recorder, read back as JSON or CSV.

use super::{Db, DbError};
use crate::cell::{StepRecord, StepUncertainty};
use crate::policy::shield::RuleSet;
use crate::sim::RewardTerms;
use serde::Serialize;
use serde_json::Value;
use sqlx::{QueryBuilder, Sqlite};

/// Rows per INSERT statement (24 values each, well under SQLite's 32766 parameters).
pub const ROWS_PER_STATEMENT: usize = 100;

/// Inserts the records in one transaction.
pub async fn insert_batch(db: &Db, records: &[StepRecord]) -> Result<(), DbError> {
    let done = async {
        let mut tx = db.writer.begin().await?;
        for chunk in records.chunks(ROWS_PER_STATEMENT) {
            insert_rows(&mut *tx, chunk).await?;
        }
        tx.commit().await
    }
    .await;
    db.track(done)
}

/// Inserts the records with whatever executor the caller holds (a transaction).
pub async fn insert_rows<'e>(
    executor: impl sqlx::SqliteExecutor<'e>,
    records: &[StepRecord],
) -> Result<(), DbError> {
    if records.is_empty() {
        return Ok(());
    }
    let mut insert: QueryBuilder<Sqlite> = QueryBuilder::new(
        "INSERT INTO steps (job_id, step, t_s, state, action, actor, scale, legs_mm, verdict,
             veto_reason, reward_global, reward_position, reward_orientation, reward_error,
             reward_step, reward_total, compute_us, sd_lateral_mm, sd_axial_mm, sd_tilt_deg,
             noise_scale, detected, proposed, rules) ",
    );
    insert.push_values(records, |mut row, r| {
        row.push_bind(r.job_id)
            .push_bind(i64::from(r.step))
            .push_bind(r.t_s)
            .push_bind(json_array(&r.state))
            .push_bind(json_array(&r.action))
            .push_bind(r.actor.map(|a| actor_name(&a)))
            .push_bind(r.scale)
            .push_bind(json_array(&r.legs_mm))
            .push_bind(r.verdict)
            .push_bind(r.veto_reason.clone())
            .push_bind(r.reward.global)
            .push_bind(r.reward.position)
            .push_bind(r.reward.orientation)
            .push_bind(r.reward.error)
            .push_bind(r.reward.step)
            .push_bind(r.reward.total)
            .push_bind(r.compute_us)
            .push_bind(r.uncertainty.sd_lateral_mm)
            .push_bind(r.uncertainty.sd_axial_mm)
            .push_bind(r.uncertainty.sd_tilt_deg)
            .push_bind(r.uncertainty.noise_scale)
            .push_bind(r.detected.clone())
            .push_bind(r.proposed.as_ref().map(|p| json_array(p)))
            .push_bind(rule_names(r.rules));
    });
    insert.build().execute(executor).await?;
    Ok(())
}

fn json_array(values: &[f64]) -> String {
    serde_json::to_string(values).expect("finite numbers serialise")
}

/// The rules as stored: their names as a JSON array, NULL where none fired (most steps), so
/// a step costs no text for them. Names rather than bits: a stored step keeps its meaning when
/// rules are added or reordered.
fn rule_names(rules: RuleSet) -> Option<String> {
    (!rules.is_empty()).then(|| serde_json::to_string(&rules).expect("names serialise"))
}

fn actor_name(actor: &crate::policy::Actor) -> &'static str {
    match actor {
        crate::policy::Actor::Position => "position",
        crate::policy::Actor::Orientation => "orientation",
    }
}

/// A stored step as served: the same fields as the live [`StepRecord`].
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct StoredStep {
    pub step: i64,
    pub t_s: f64,
    pub state: Value,
    pub action: Value,
    /// The controller's own move `[Δx, Δy, Δz, θx, θy, θz]` (mm, deg) before the shield's
    /// rules shaped it into `action`; null for a controller without rules (the expert, the
    /// baselines) and for steps recorded before it was kept.
    #[schema(min_items = 6, max_items = 6)]
    pub proposed: Option<[f64; 6]>,
    /// The rules that changed the proposal, in pipeline order, by the names of the cell file's
    /// `[rules]` (`full_step`, `not_past_level`, ...); empty where none did.
    pub rules: Vec<String>,
    pub actor: Option<String>,
    pub scale: Option<f64>,
    pub legs_mm: Value,
    pub verdict: String,
    pub veto_reason: Option<String>,
    pub reward: RewardTerms,
    pub compute_us: f64,
    /// How sure the cell was of the state (none for steps recorded before it said).
    pub uncertainty: Option<StepUncertainty>,
    pub detected: Option<String>,
}

/// A row of `steps` as stored (vectors as JSON text).
#[derive(sqlx::FromRow)]
struct StepRow {
    step: i64,
    t_s: f64,
    state: String,
    action: String,
    proposed: Option<String>,
    rules: Option<String>,
    actor: Option<String>,
    scale: Option<f64>,
    legs_mm: String,
    verdict: String,
    veto_reason: Option<String>,
    reward_global: f64,
    reward_position: f64,
    reward_orientation: f64,
    reward_error: f64,
    reward_step: f64,
    reward_total: f64,
    compute_us: f64,
    sd_lateral_mm: Option<f64>,
    sd_axial_mm: Option<f64>,
    sd_tilt_deg: Option<f64>,
    noise_scale: Option<f64>,
    detected: Option<String>,
}

impl From<StepRow> for StoredStep {
    fn from(row: StepRow) -> Self {
        let parse = |text: &str| serde_json::from_str(text).unwrap_or(Value::Null);
        StoredStep {
            step: row.step,
            t_s: row.t_s,
            state: parse(&row.state),
            action: parse(&row.action),
            proposed: row
                .proposed
                .and_then(|text| serde_json::from_str(&text).ok()),
            rules: row
                .rules
                .and_then(|text| serde_json::from_str(&text).ok())
                .unwrap_or_default(),
            actor: row.actor,
            scale: row.scale,
            legs_mm: parse(&row.legs_mm),
            verdict: row.verdict,
            veto_reason: row.veto_reason,
            reward: RewardTerms {
                global: row.reward_global,
                position: row.reward_position,
                orientation: row.reward_orientation,
                error: row.reward_error,
                step: row.reward_step,
                total: row.reward_total,
            },
            compute_us: row.compute_us,
            uncertainty: match (
                row.sd_lateral_mm,
                row.sd_axial_mm,
                row.sd_tilt_deg,
                row.noise_scale,
            ) {
                (Some(sd_lateral_mm), Some(sd_axial_mm), Some(sd_tilt_deg), Some(noise_scale)) => {
                    Some(StepUncertainty {
                        sd_lateral_mm,
                        sd_axial_mm,
                        sd_tilt_deg,
                        noise_scale,
                    })
                }
                _ => None,
            },
            detected: row.detected,
        }
    }
}

/// Every step of a job, in order.
pub async fn list(db: &Db, job_id: i64) -> Result<Vec<StoredStep>, DbError> {
    let rows: Vec<StepRow> = sqlx::query_as("SELECT * FROM steps WHERE job_id = ? ORDER BY step")
        .bind(job_id)
        .fetch_all(&db.reader)
        .await?;
    Ok(rows.into_iter().map(StoredStep::from).collect())
}

/// The CSV form of [`list`]: one header line, vectors spread over numbered columns; the rules
/// that fired as one field, `;` between names.
pub fn to_csv(steps: &[StoredStep]) -> String {
    let mut header: Vec<String> = vec!["step".into(), "t_s".into()];
    header.extend((0..12).map(|i| format!("state_{i}")));
    header.extend(["dx_mm", "dy_mm", "dz_mm", "rx_deg", "ry_deg", "rz_deg"].map(String::from));
    header.extend(["actor", "scale"].map(String::from));
    header.extend((1..=6).map(|i| format!("leg{i}_mm")));
    header.extend(["verdict", "veto_reason"].map(String::from));
    header.extend(
        [
            "reward_global",
            "reward_position",
            "reward_orientation",
            "reward_error",
            "reward_step",
            "reward_total",
            "compute_us",
            "sd_lateral_mm",
            "sd_axial_mm",
            "sd_tilt_deg",
            "noise_scale",
            "detected",
        ]
        .map(String::from),
    );
    header.extend(
        ["dx_mm", "dy_mm", "dz_mm", "rx_deg", "ry_deg", "rz_deg"].map(|c| format!("proposed_{c}")),
    );
    header.push("rules".into());
    let mut out = header.join(",");
    out.push('\n');
    let numbers = |value: &Value, n: usize| -> Vec<String> {
        let items = value.as_array().cloned().unwrap_or_default();
        (0..n)
            .map(|i| items.get(i).map(|v| v.to_string()).unwrap_or_default())
            .collect()
    };
    for s in steps {
        let mut fields = vec![s.step.to_string(), s.t_s.to_string()];
        fields.extend(numbers(&s.state, 12));
        fields.extend(numbers(&s.action, 6));
        fields.push(s.actor.clone().unwrap_or_default());
        fields.push(s.scale.map(|v| v.to_string()).unwrap_or_default());
        fields.extend(numbers(&s.legs_mm, 6));
        fields.push(s.verdict.clone());
        fields.push(s.veto_reason.clone().unwrap_or_default());
        let r = &s.reward;
        fields.extend(
            [
                r.global,
                r.position,
                r.orientation,
                r.error,
                r.step,
                r.total,
                s.compute_us,
            ]
            .map(|v| v.to_string()),
        );
        let u = s.uncertainty;
        fields.extend(
            [
                u.map(|u| u.sd_lateral_mm),
                u.map(|u| u.sd_axial_mm),
                u.map(|u| u.sd_tilt_deg),
                u.map(|u| u.noise_scale),
            ]
            .map(|v| v.map(|v| v.to_string()).unwrap_or_default()),
        );
        fields.push(s.detected.clone().unwrap_or_default());
        fields.extend((0..6).map(|i| s.proposed.map(|p| p[i].to_string()).unwrap_or_default()));
        // Names hold no comma; `;` keeps the list in one field.
        fields.push(s.rules.join(";"));
        out.push_str(&fields.join(","));
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::shield::RuleId;
    use crate::storage::jobs::{self, NewJob};

    fn record(job_id: i64, step: u32) -> StepRecord {
        StepRecord {
            job_id,
            step,
            t_s: 0.25 * f64::from(step),
            state: [0.5; 12],
            action: [0.5, -0.25, -1.0, 0.0, 0.125, 0.0],
            proposed: None,
            rules: RuleSet::default(),
            actor: None,
            scale: None,
            legs_mm: [760.0; 6],
            verdict: "allowed",
            veto_reason: None,
            reward: RewardTerms::default(),
            compute_us: 30.0,
            uncertainty: StepUncertainty::default(),
            detected: None,
        }
    }

    async fn job(db: &Db) -> i64 {
        let new = NewJob {
            controller: "hierarchical".into(),
            policy_id: None,
            seed: 1,
            initial_pos_mm: 1.0,
            initial_ori_deg: 1.0,
            demonstration: false,
            created_by: "test".into(),
        };
        jobs::insert(db, &new).await.unwrap().id
    }

    #[tokio::test]
    async fn a_steps_proposal_and_rules_read_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let db = Db::open(&dir.path().join("celld.db")).await.unwrap();
        let id = job(&db).await;
        let shaped = StepRecord {
            proposed: Some([2.5, -7.75, -5.0, 0.0, 0.3, -0.1]),
            rules: [RuleId::StandoffWhileUnsure, RuleId::FullStep]
                .into_iter()
                .collect(),
            ..record(id, 1)
        };
        let unshaped = StepRecord {
            proposed: Some(record(id, 2).action),
            ..record(id, 2)
        };
        let expert = record(id, 3);
        insert_batch(&db, &[shaped.clone(), unshaped.clone(), expert])
            .await
            .unwrap();
        // A row as written before proposals were kept.
        sqlx::query(
            "INSERT INTO steps (job_id, step, t_s, state, action, legs_mm, verdict,
                 reward_global, reward_position, reward_orientation, reward_error, reward_step,
                 reward_total, compute_us)
             VALUES (?, 4, 1.0, '[]', '[0,0,0,0,0,0]', '[]', 'allowed', 0, 0, 0, 0, 0, 0, 1)",
        )
        .bind(id)
        .execute(&db.writer)
        .await
        .unwrap();

        let stored = list(&db, id).await.unwrap();
        let read: Vec<_> = stored
            .iter()
            .map(|s| (s.step, s.proposed, s.rules.clone()))
            .collect();
        assert_eq!(
            read,
            [
                (
                    1,
                    shaped.proposed,
                    vec!["full_step".to_string(), "standoff_while_unsure".into()]
                ),
                (2, unshaped.proposed, vec![]),
                (3, None, vec![]),
                (4, None, vec![]),
            ]
        );
        // The names are the rules' own: they read back as the set written.
        assert_eq!(
            RuleSet::from_names(stored[0].rules.iter().map(String::as_str)),
            Ok(shaped.rules)
        );
        // Most steps fire no rule: their rules cost no text.
        let texts: Vec<Option<String>> =
            sqlx::query_scalar("SELECT rules FROM steps WHERE job_id = ? ORDER BY step")
                .bind(id)
                .fetch_all(&db.reader)
                .await
                .unwrap();
        assert_eq!(
            texts,
            [
                Some(r#"["full_step","standoff_while_unsure"]"#.to_string()),
                None,
                None,
                None
            ]
        );

        let csv = to_csv(&stored);
        let lines: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
        let column = |name: &str| lines[0].iter().position(|c| *c == name).unwrap();
        assert!(lines.iter().all(|l| l.len() == lines[0].len()), "{csv}");
        assert_eq!(lines[1][column("proposed_dy_mm")], "-7.75");
        assert_eq!(lines[1][column("proposed_rz_deg")], "-0.1");
        assert_eq!(lines[1][column("rules")], "full_step;standoff_while_unsure");
        assert_eq!(lines[2][column("proposed_dz_mm")], "-1");
        assert_eq!(lines[2][column("rules")], "");
        assert_eq!(lines[3][column("proposed_dx_mm")], "");
    }
}
