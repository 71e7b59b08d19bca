//! The fleet: one PostgreSQL that every cell replicates its record to, and that holds the
//! fleet's policy registry and activation requests (sqlx, runtime-checked queries; schema in
//! `migrations_fleet/`, embedded at build time).
//!
//! The cell's SQLite stays its record: the control loop and every request write there as
//! before. Triggers put the key of each row written into the `fleet_outbox` in the same
//! transaction ([`outbox`]); [`replicate`] sends those rows as they are now and deletes their
//! keys from the outbox only once PostgreSQL has committed them. A row re-sent (after a kill,
//! a retry) is an upsert on `(cell_id, key)` and changes nothing, so a row is never lost and
//! never there twice, and PostgreSQL being away only makes the outbox longer.

pub mod outbox;
pub mod reads;
pub mod registry;
pub mod replicate;

use sqlx::PgPool;
use sqlx::postgres::{PgConnectOptions, PgPoolOptions};
use std::str::FromStr;
use std::time::Duration;

/// A replicated table: its name and key columns on the cell (in PostgreSQL `cell_id` comes
/// before them), and the columns that stay on the cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Replicated {
    pub name: &'static str,
    pub key: &'static [&'static str],
    /// A policy's file goes to the registry (`fleet_policy_files`) once, not with every row.
    pub kept_local: &'static [&'static str],
}

const fn by_id(name: &'static str) -> Replicated {
    Replicated {
        name,
        key: &["id"],
        kept_local: &[],
    }
}

/// Everything the cell records, in the order the outbox's triggers were made.
pub const REPLICATED: &[Replicated] = &[
    by_id("jobs"),
    Replicated {
        name: "steps",
        key: &["job_id", "step"],
        kept_local: &[],
    },
    by_id("policy_evaluations"),
    by_id("demonstrations"),
    by_id("training_runs"),
    by_id("audit"),
    by_id("machine_transitions"),
    by_id("tokens"),
    Replicated {
        name: "policies",
        key: &["id"],
        kept_local: &["file"],
    },
];

/// The replicated table named `name`.
pub fn replicated(name: &str) -> Option<&'static Replicated> {
    REPLICATED.iter().find(|t| t.name == name)
}

#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    #[error("fleet.url is not a PostgreSQL URL the service can use: {0}")]
    Url(String),
    #[error("the fleet's database is unreachable: {0}")]
    Unreachable(sqlx::Error),
    #[error("cannot migrate the fleet's database: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("the fleet's database refused: {0}")]
    Refused(sqlx::Error),
}

impl From<sqlx::Error> for FleetError {
    fn from(error: sqlx::Error) -> Self {
        if crate::storage::is_fault(&error) {
            FleetError::Unreachable(error)
        } else {
            FleetError::Refused(error)
        }
    }
}

/// PostgreSQL's `to_char` format of a UTC time as the cell writes its times (ISO 8601, ms).
const ISO: &str = r#"'YYYY-MM-DD"T"HH24:MI:SS.MS"Z"'"#;

/// How long a connection to the fleet may take before the attempt counts as an outage.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

/// The fleet's database, as this cell sees it.
#[derive(Clone)]
pub struct Fleet {
    pub pool: PgPool,
    pub cell_id: String,
    /// Where the fleet's database is: host, port and database, without user or password.
    pub target: String,
}

impl Fleet {
    /// A pool that connects when first used, so that the cell starts and runs while the
    /// fleet's database is down. A URL that cannot be parsed is refused here.
    pub fn connect_lazy(url: &str, cell_id: &str) -> Result<Fleet, FleetError> {
        let options =
            PgConnectOptions::from_str(url).map_err(|e| FleetError::Url(e.to_string()))?;
        let target = format!(
            "{}:{}/{}",
            options.get_host(),
            options.get_port(),
            options.get_database().unwrap_or_default()
        );
        let pool = PgPoolOptions::new()
            .max_connections(3)
            .acquire_timeout(CONNECT_TIMEOUT)
            .connect_lazy_with(options.application_name(&format!("celld {cell_id}")));
        Ok(Fleet {
            pool,
            cell_id: cell_id.to_string(),
            target,
        })
    }

    /// Creates or brings up to date the fleet's schema; cells migrating at once wait for
    /// each other (sqlx takes an advisory lock). A schema a newer cell already took further
    /// is accepted: the fleet's migrations only add, so a fleet upgrades one cell at a time.
    pub async fn migrate(&self) -> Result<(), FleetError> {
        let mut migrator = sqlx::migrate!("./migrations_fleet");
        migrator.set_ignore_missing(true);
        migrator.run(&self.pool).await?;
        Ok(())
    }
}

pub use crate::config::service::check_cell_id;
