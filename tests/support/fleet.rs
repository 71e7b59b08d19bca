//! A cell's record read twice, from its SQLite and from the fleet's PostgreSQL, each row as a
//! JSON object of its columns, so that a test can say every row arrived, as it is, once.
#![allow(dead_code)] // not every binary that includes this module uses all of it

use serde_json::{Map, Value};
use sqlx::{Column, Connection, Row};
use std::path::Path;
use std::time::{Duration, Instant};

/// The replicated tables and the columns they are ordered by.
pub const TABLES: &[(&str, &str)] = &[
    ("jobs", "id"),
    ("steps", "job_id, step"),
    ("policy_evaluations", "id"),
    ("demonstrations", "id"),
    ("training_runs", "id"),
    ("audit", "id"),
    ("machine_transitions", "id"),
    ("tokens", "id"),
    ("policies", "id"),
];

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

fn sqlite_url(db: &Path) -> String {
    format!("sqlite://{}?mode=ro", db.display())
}

/// The cell's columns of `table` and their declared types, the policy file left out (the
/// fleet keeps it once, in its registry).
async fn columns(db: &mut sqlx::SqliteConnection, table: &str) -> Vec<(String, String)> {
    let rows: Vec<(String, String)> =
        sqlx::query_as("SELECT name, type FROM pragma_table_info(?) ORDER BY cid")
            .bind(table)
            .fetch_all(&mut *db)
            .await
            .unwrap();
    rows.into_iter()
        .filter(|(name, _)| !(table == "policies" && name == "file"))
        .collect()
}

fn value<'r, R: Row>(row: &'r R, index: usize, declared: &str) -> Value
where
    usize: sqlx::ColumnIndex<R>,
    Option<i64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
    Option<f64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
    Option<String>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
{
    let read = match declared {
        "INTEGER" => row
            .try_get::<Option<i64>, _>(index)
            .map(|v| v.map(Value::from)),
        "REAL" => row
            .try_get::<Option<f64>, _>(index)
            .map(|v| v.map(Value::from)),
        _ => row
            .try_get::<Option<String>, _>(index)
            .map(|v| v.map(Value::from)),
    };
    let name = row.columns()[index].name().to_string();
    read.unwrap_or_else(|e| panic!("column {name}: {e}"))
        .unwrap_or(Value::Null)
}

/// A row as a JSON object of its `columns`.
fn object<R: Row>(row: &R, columns: &[(String, String)]) -> Value
where
    usize: sqlx::ColumnIndex<R>,
    for<'r> Option<i64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
    for<'r> Option<f64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
    for<'r> Option<String>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
{
    let mut object = Map::new();
    for (i, (name, declared)) in columns.iter().enumerate() {
        object.insert(name.clone(), value(row, i, declared));
    }
    Value::Object(object)
}

/// Every row of `table` on the cell, ordered by its key.
pub fn cell_rows(db: &Path, table: &str, order: &str) -> Vec<Value> {
    runtime().block_on(async {
        let mut connection = sqlx::SqliteConnection::connect(&sqlite_url(db))
            .await
            .unwrap();
        let columns = columns(&mut connection, table).await;
        let names: Vec<&str> = columns.iter().map(|(n, _)| n.as_str()).collect();
        let sql = format!("SELECT {} FROM {table} ORDER BY {order}", names.join(", "));
        let rows = sqlx::query(&sql).fetch_all(&mut connection).await.unwrap();
        rows.iter().map(|row| object(row, &columns)).collect()
    })
}

/// Every row of `table` the fleet holds for `cell_id`, with the cell's columns, ordered by key.
pub fn fleet_rows(url: &str, db: &Path, cell_id: &str, table: &str, order: &str) -> Vec<Value> {
    runtime().block_on(async {
        let mut cell = sqlx::SqliteConnection::connect(&sqlite_url(db))
            .await
            .unwrap();
        let columns = columns(&mut cell, table).await;
        let mut fleet = sqlx::PgConnection::connect(url).await.unwrap();
        let names: Vec<&str> = columns.iter().map(|(n, _)| n.as_str()).collect();
        let sql = format!(
            "SELECT {} FROM {table} WHERE cell_id = $1 ORDER BY {order}",
            names.join(", ")
        );
        let rows = sqlx::query(&sql)
            .bind(cell_id)
            .fetch_all(&mut fleet)
            .await
            .unwrap();
        rows.iter().map(|row| object(row, &columns)).collect()
    })
}

/// Rows the cell has not sent yet (its outbox).
pub fn backlog(db: &Path) -> i64 {
    runtime().block_on(async {
        let mut connection = sqlx::SqliteConnection::connect(&sqlite_url(db))
            .await
            .unwrap();
        sqlx::query_scalar("SELECT count(*) FROM fleet_outbox")
            .fetch_one(&mut connection)
            .await
            .unwrap()
    })
}

/// Waits until the cell's outbox is empty.
pub fn wait_caught_up(db: &Path, limit: Duration) -> Duration {
    let start = Instant::now();
    loop {
        let left = backlog(db);
        if left == 0 {
            return start.elapsed();
        }
        assert!(
            start.elapsed() < limit,
            "{} still holds {left} rows for the fleet after {limit:?}",
            db.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// How many rows of each table the two sides hold, and the tables where they differ.
pub fn compare(url: &str, db: &Path, cell_id: &str) -> Result<usize, String> {
    let mut rows = 0;
    let mut differences = Vec::new();
    for (table, order) in TABLES {
        let here = cell_rows(db, table, order);
        let there = fleet_rows(url, db, cell_id, table, order);
        rows += here.len();
        if here != there {
            let first = here
                .iter()
                .zip(&there)
                .find(|(a, b)| a != b)
                .map(|(a, b)| format!("; first difference: cell {a} fleet {b}"))
                .unwrap_or_default();
            differences.push(format!(
                "{table}: {} rows on the cell, {} in the fleet{first}",
                here.len(),
                there.len()
            ));
        }
    }
    if differences.is_empty() {
        Ok(rows)
    } else {
        Err(differences.join("\n"))
    }
}
