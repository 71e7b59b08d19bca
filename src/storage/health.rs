//! Whether the database takes writes: the last write fault (its error, since when, how many
//! writes failed since), held until a write commits again. The storage writer probes with a
//! small write while a fault stands and nothing else is waiting ([`probe`]), so the fault
//! clears once the disk has room again even when no one else writes.

use super::{Db, DbError, NOW};
use serde::Serialize;
use std::sync::Mutex;
use std::time::{SystemTime, UNIX_EPOCH};

/// Bytes the probe writes (a zero blob): more than a WAL frame's page, so a disk with no
/// room for a real write has none for the probe either.
pub const PROBE_BYTES: i64 = 16 * 1024;

/// A standing write fault.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct WriteFault {
    /// The first failed write's error.
    pub error: String,
    /// When writes began to fail (UTC, ISO 8601).
    pub since: String,
    /// The latest failed write's error.
    pub last_error: String,
    /// Writes that failed since.
    pub failed_writes: u64,
}

/// Shared by every clone of [`Db`].
#[derive(Debug, Default)]
pub struct WriteHealth {
    fault: Mutex<Option<WriteFault>>,
}

impl WriteHealth {
    /// The standing fault, if writes fail.
    pub fn fault(&self) -> Option<WriteFault> {
        self.lock().clone()
    }

    pub fn failed(&self, error: &DbError) {
        let mut fault = self.lock();
        match fault.as_mut() {
            Some(fault) => {
                fault.last_error = error.to_string();
                fault.failed_writes += 1;
            }
            None => {
                tracing::error!(%error, "the database takes no writes");
                *fault = Some(WriteFault {
                    error: error.to_string(),
                    since: iso_utc(SystemTime::now()),
                    last_error: error.to_string(),
                    failed_writes: 1,
                });
            }
        }
    }

    pub fn succeeded(&self) {
        if let Some(fault) = self.lock().take() {
            tracing::warn!(
                since = %fault.since,
                failed_writes = fault.failed_writes,
                "the database takes writes again"
            );
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Option<WriteFault>> {
        // A panic while holding it left a plain value behind: still usable.
        self.fault.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Writes one small row ([`PROBE_BYTES`]) and notes the outcome in [`Db::health`].
pub async fn probe(db: &Db) -> Result<(), DbError> {
    let done = sqlx::query(&format!(
        "INSERT INTO storage_probe (id, at, room) VALUES (1, {NOW}, zeroblob(?))
         ON CONFLICT (id) DO UPDATE SET at = excluded.at, room = excluded.room"
    ))
    .bind(PROBE_BYTES)
    .execute(&db.writer)
    .await
    .map(|_| ());
    db.track(done)
}

/// `time` as `YYYY-MM-DDTHH:MM:SS.mmmZ`, the schema's format.
pub fn iso_utc(time: SystemTime) -> String {
    let since = time.duration_since(UNIX_EPOCH).unwrap_or_default();
    let seconds = since.as_secs();
    let (days, of_day) = ((seconds / 86_400) as i64, seconds % 86_400);
    // Days since 1970-01-01 to a civil date (H. Hinnant's `civil_from_days`).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let day_of_era = z.rem_euclid(146_097);
    let year_of_era =
        (day_of_era - day_of_era / 1460 + day_of_era / 36_524 - day_of_era / 146_096) / 365;
    let day_of_year = day_of_era - (365 * year_of_era + year_of_era / 4 - year_of_era / 100);
    let mp = (5 * day_of_year + 2) / 153;
    let day = day_of_year - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = year_of_era + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        of_day / 3600,
        of_day / 60 % 60,
        of_day % 60,
        since.subsec_millis()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn times_are_iso_8601_utc() {
        // `date -u -d @951782400.25`: 2000-02-29 00:00:00.25 (a leap day of a century year).
        let t = UNIX_EPOCH + Duration::from_millis(951_782_400_250);
        assert_eq!(iso_utc(t), "2000-02-29T00:00:00.250Z");
        // `date -u -d @1796774399`: 2026-12-08 23:59:59.
        let t = UNIX_EPOCH + Duration::from_secs(1_796_774_399);
        assert_eq!(iso_utc(t), "2026-12-08T23:59:59.000Z");
        assert_eq!(iso_utc(UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
    }

    #[test]
    fn a_fault_stands_until_a_write_commits() {
        let health = WriteHealth::default();
        assert_eq!(health.fault(), None);
        health.failed(&DbError::PoolTimedOut);
        health.failed(&DbError::PoolClosed);
        let fault = health.fault().unwrap();
        assert_eq!(fault.failed_writes, 2);
        assert_eq!(fault.error, DbError::PoolTimedOut.to_string());
        assert_eq!(fault.last_error, DbError::PoolClosed.to_string());
        health.succeeded();
        assert_eq!(health.fault(), None);
    }
}
