//! `/api/stats`: jobs, success rate, average steps and failure reasons, overall and by day or
//! by controller, over a time range.

use super::Context;
use super::auth::Auth;
use super::error::{ApiError, ApiResult, Json, Query};
use crate::storage::jobs::{self, GroupBy, JobStats};
use crate::storage::tokens::Role;
use axum::extract::State;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<Context> {
    OpenApiRouter::new().routes(routes!(read))
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub struct StatsQuery {
    /// Jobs created at or after this UTC time (2026-11-22 or 2026-11-22T08:00:00Z).
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    since: Option<String>,
    /// Jobs created before this UTC time.
    #[param(
        pattern = "^[0-9]{4}-[0-9]{2}-[0-9]{2}(T[0-9]{2}:[0-9]{2}(:[0-9]{2}(\\.[0-9]{1,3})?)?)?Z?$"
    )]
    until: Option<String>,
    /// `day` (default) or `controller`.
    #[param(inline, value_type = Option<StatsGroup>)]
    by: Option<String>,
}

/// How the groups are formed.
#[derive(ToSchema)]
#[allow(dead_code)] // Described, not built: the query carries the name as text.
#[schema(rename_all = "snake_case")]
pub enum StatsGroup {
    Day,
    Controller,
}

#[derive(Serialize, ToSchema)]
pub struct Stats {
    pub total: JobStats,
    pub groups: Vec<JobStats>,
}

/// Jobs, success rate, average steps and failure reasons over a time range, overall and by
/// day or by controller (viewer).
#[utoipa::path(get, path = "/api/stats", tag = "stats", params(StatsQuery),
    responses((status = 200, description = "The figures", body = Stats)))]
async fn read(
    State(context): State<Context>,
    auth: Auth,
    Query(query): Query<StatsQuery>,
) -> ApiResult<Json<Stats>> {
    auth.require(Role::Viewer)?;
    let by = group_by(query.by.as_deref())?;
    check_time_range(&query.since, &query.until)?;
    let (total, groups) = jobs::stats(
        &context.db,
        query.since.as_deref(),
        query.until.as_deref(),
        by,
    )
    .await?;
    Ok(Json(Stats { total, groups }))
}

/// The grouping `by` names: `day` (the default) or `controller`.
pub fn group_by(by: Option<&str>) -> ApiResult<GroupBy> {
    match by {
        None | Some("day") => Ok(GroupBy::Day),
        Some("controller") => Ok(GroupBy::Controller),
        Some(other) => Err(ApiError::bad_request(format!(
            "by `{other}` is not day or controller"
        ))),
    }
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
