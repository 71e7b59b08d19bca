//! `/api/stats`: jobs, success rate, average steps and failure reasons, overall and by day or
//! by controller, over a time range.

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json, Query};
use crate::storage::jobs::{self, GroupBy};
use crate::storage::tokens::Role;
use axum::Router;
use axum::extract::State;
use axum::routing::get;
use serde::Deserialize;
use serde_json::{Value, json};

pub fn router() -> Router<Context> {
    Router::new().route("/api/stats", get(read))
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StatsQuery {
    since: Option<String>,
    until: Option<String>,
    by: Option<String>,
}

async fn read(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<StatsQuery>,
) -> ApiResult<Json<Value>> {
    auth.require(Role::Viewer)?;
    let by = match query.by.as_deref() {
        None | Some("day") => GroupBy::Day,
        Some("controller") => GroupBy::Controller,
        Some(other) => {
            return Err(ApiError::bad_request(format!(
                "by `{other}` is not day or controller"
            )));
        }
    };
    check_time_range(&query.since, &query.until)?;
    let (total, groups) = jobs::stats(
        &context.db,
        query.since.as_deref(),
        query.until.as_deref(),
        by,
    )
    .await?;
    Ok(Json(json!({"total": total, "groups": groups})))
}

/// Refuses (400) a `since` or `until` that is not an ISO time [`is_iso_time`] takes.
pub fn check_time_range(since: &Option<String>, until: &Option<String>) -> ApiResult<()> {
    for (field, value) in [("since", since), ("until", until)] {
        if let Some(value) = value
            && !is_iso_time(value)
        {
            return Err(ApiError::bad_request(format!(
                "{field} `{value}` is not a UTC date or time like 2026-11-22 or 2026-11-22T08:00:00Z"
            )));
        }
    }
    Ok(())
}

/// `YYYY-MM-DD`, optionally followed by `THH:MM[:SS[.fff]][Z]`: the prefixes of the stored
/// times, which compare as text.
fn is_iso_time(text: &str) -> bool {
    let pattern = b"dddd-dd-ddTdd:dd:dd.ddd";
    let bytes = text.strip_suffix('Z').unwrap_or(text).as_bytes();
    let shape_ok = bytes.iter().zip(pattern).all(|(&b, &p)| match p {
        b'd' => b.is_ascii_digit(),
        _ => b == p,
    });
    // Date; date and minutes; seconds; seconds and 1 to 3 decimals.
    shape_ok && matches!(bytes.len(), 10 | 16 | 19 | 21..=23)
}

#[cfg(test)]
mod tests {
    use super::is_iso_time;

    #[test]
    fn iso_prefixes_are_accepted_and_others_refused() {
        for good in [
            "2026-11-22",
            "2026-11-22T08:00",
            "2026-11-22T08:00:00Z",
            "2026-11-22T08:00:00.123Z",
        ] {
            assert!(is_iso_time(good), "{good}");
        }
        for bad in [
            "yesterday",
            "2026-1-22",
            "2026-11-22T8",
            "2026-11-22 08:00",
            "2026-11-22T08:00:00+01:00",
        ] {
            assert!(!is_iso_time(bad), "{bad}");
        }
    }
}
