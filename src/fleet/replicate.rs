//! Sends the rows the outbox names to the fleet, a batch at a time: each batch is one
//! PostgreSQL transaction of upserts (and deletions, for rows gone from the cell), and its
//! outbox entries are deleted only after that transaction committed.

use super::outbox::{self, Entry};
use super::{Fleet, FleetError, REPLICATED, Replicated};
use crate::storage::{Db, DbError};
use sqlx::postgres::Postgres;
use sqlx::sqlite::SqliteRow;
use sqlx::{Connection, QueryBuilder, Row};
use std::collections::{BTreeMap, BTreeSet};

/// Outbox entries per batch: a few seconds of a busy cell's steps, sent in one transaction.
pub const BATCH_ENTRIES: i64 = 4000;

/// PostgreSQL takes at most 65,535 bound values in one statement.
const MAX_BINDS: usize = 60_000;

/// Keys read from SQLite per statement (SQLite's bound-value limit is 32,766).
const KEYS_PER_READ: usize = 500;

/// A column's storage class, from the cell's schema (`pragma_table_info`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Int,
    Real,
    Text,
    Blob,
}

/// A replicated table as the cell's schema has it.
#[derive(Debug, Clone)]
pub struct TableSchema {
    pub table: Replicated,
    /// The columns sent, in order, with their kinds (the key columns first).
    pub columns: Vec<(String, Kind)>,
}

/// The replicated tables' columns, read from the cell's schema: the fleet's tables have the
/// same (its migrations and the cell's are checked against each other by the tests).
pub async fn schema(db: &Db) -> Result<Vec<TableSchema>, DbError> {
    let mut tables = Vec::new();
    for table in REPLICATED {
        let rows: Vec<(String, String)> =
            sqlx::query_as("SELECT name, type FROM pragma_table_info(?) ORDER BY cid")
                .bind(table.name)
                .fetch_all(&db.reader)
                .await?;
        let mut columns: Vec<(String, Kind)> = rows
            .into_iter()
            .filter(|(name, _)| !table.kept_local.contains(&name.as_str()))
            .map(|(name, declared)| {
                let kind = match declared.to_ascii_uppercase().as_str() {
                    "INTEGER" => Kind::Int,
                    "REAL" => Kind::Real,
                    "BLOB" => Kind::Blob,
                    _ => Kind::Text,
                };
                (name, kind)
            })
            .collect();
        columns.sort_by_key(|(name, _)| !table.key.contains(&name.as_str()));
        tables.push(TableSchema {
            table: *table,
            columns,
        });
    }
    Ok(tables)
}

/// One value of a row, as read from the cell.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Int(Option<i64>),
    Real(Option<f64>),
    Text(Option<String>),
    Blob(Option<Vec<u8>>),
}

type Key = (i64, Option<i64>);

/// What a batch did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Sent {
    /// Outbox entries the batch covered.
    pub entries: usize,
    /// Rows upserted and deleted in the fleet.
    pub upserted: usize,
    pub deleted: usize,
    /// Each entry's wait from its commit on the cell to the fleet's commit, s.
    pub lags_s: Vec<f64>,
}

#[derive(Debug, thiserror::Error)]
pub enum ReplicationError {
    #[error("reading the cell's rows: {0}")]
    Cell(#[from] DbError),
    #[error(transparent)]
    Fleet(#[from] FleetError),
}

/// Sends the oldest batch of the outbox; `None` when it is empty.
pub async fn send_batch(
    db: &Db,
    fleet: &Fleet,
    tables: &[TableSchema],
) -> Result<Option<Sent>, ReplicationError> {
    // A connection to the fleet first: while it is unreachable no read transaction is held
    // open on the cell (which would keep SQLite from checkpointing its log).
    let mut fleet_connection = fleet.pool.acquire().await.map_err(FleetError::from)?;
    // One read transaction for the entries and the rows they name: the rows are then at least
    // as new as the entries, whichever reader connection the pool hands out.
    let mut snapshot = db.reader.begin().await?;
    let entries = outbox::oldest(&mut snapshot, BATCH_ENTRIES).await?;
    let Some(last) = entries.last() else {
        return Ok(None);
    };
    let through_seq = last.seq;
    let mut keys: BTreeMap<&str, BTreeSet<Key>> = BTreeMap::new();
    for entry in &entries {
        keys.entry(entry.table_name.as_str())
            .or_default()
            .insert((entry.key1, entry.key2));
    }
    let mut sent = Sent {
        entries: entries.len(),
        ..Sent::default()
    };
    let mut tx = fleet_connection.begin().await.map_err(FleetError::from)?;
    for schema in tables {
        let Some(wanted) = keys.get(schema.table.name) else {
            continue;
        };
        let rows = read_rows(&mut snapshot, schema, wanted).await?;
        let found: BTreeSet<Key> = rows.iter().map(|row| key_of(schema, row)).collect();
        let gone: Vec<Key> = wanted.difference(&found).copied().collect();
        upsert(&mut tx, &fleet.cell_id, schema, &rows)
            .await
            .map_err(FleetError::from)?;
        delete(&mut tx, &fleet.cell_id, schema, &gone)
            .await
            .map_err(FleetError::from)?;
        if schema.table.name == "policies" {
            let ids: Vec<i64> = found.iter().map(|(id, _)| *id).collect();
            super::registry::publish(&mut snapshot, &mut tx, &fleet.cell_id, &ids).await?;
        }
        sent.upserted += rows.len();
        sent.deleted += gone.len();
    }
    snapshot.rollback().await?;
    tx.commit().await.map_err(FleetError::from)?;
    let now = outbox::julian_now();
    sent.lags_s = entries
        .iter()
        .map(|Entry { at_julian, .. }| ((now - at_julian) * 86_400.0).max(0.0))
        .collect();
    outbox::sent(db, through_seq).await?;
    Ok(Some(sent))
}

fn key_of(schema: &TableSchema, row: &[Value]) -> Key {
    let int = |value: &Value| match value {
        Value::Int(Some(v)) => *v,
        _ => 0,
    };
    let second = (schema.table.key.len() > 1).then(|| int(&row[1]));
    (int(&row[0]), second)
}

fn column_list(schema: &TableSchema) -> String {
    let names: Vec<&str> = schema.columns.iter().map(|(n, _)| n.as_str()).collect();
    names.join(", ")
}

/// The rows of `schema`'s table with the `wanted` keys that the cell still holds.
async fn read_rows(
    reader: &mut sqlx::SqliteConnection,
    schema: &TableSchema,
    wanted: &BTreeSet<Key>,
) -> Result<Vec<Vec<Value>>, DbError> {
    let wanted: Vec<Key> = wanted.iter().copied().collect();
    let mut rows = Vec::with_capacity(wanted.len());
    for chunk in wanted.chunks(KEYS_PER_READ) {
        let mut query = QueryBuilder::<sqlx::Sqlite>::new(format!(
            "SELECT {} FROM {} WHERE ",
            column_list(schema),
            schema.table.name
        ));
        match schema.table.key {
            [one] => {
                query.push(format!("{one} IN ("));
                let mut list = query.separated(", ");
                for (key1, _) in chunk {
                    list.push_bind(*key1);
                }
                query.push(")");
            }
            [first, second, ..] => {
                query.push(format!("({first}, {second}) IN (VALUES "));
                let mut list = query.separated(", ");
                for (key1, key2) in chunk {
                    list.push("(");
                    list.push_bind_unseparated(*key1);
                    list.push_unseparated(", ");
                    list.push_bind_unseparated(key2.unwrap_or_default());
                    list.push_unseparated(")");
                }
                query.push(")");
            }
            [] => unreachable!("a replicated table has a key"),
        }
        let read = query.build().fetch_all(&mut *reader).await?;
        for row in read {
            rows.push(values(schema, &row)?);
        }
    }
    Ok(rows)
}

fn values(schema: &TableSchema, row: &SqliteRow) -> Result<Vec<Value>, DbError> {
    schema
        .columns
        .iter()
        .enumerate()
        .map(|(i, (_, kind))| {
            Ok(match kind {
                Kind::Int => Value::Int(row.try_get(i)?),
                Kind::Real => Value::Real(row.try_get(i)?),
                Kind::Text => Value::Text(fleet_text(row.try_get_unchecked(i)?)),
                Kind::Blob => Value::Blob(row.try_get(i)?),
            })
        })
        .collect()
}

/// A cell's text as PostgreSQL can hold it: SQLite keeps any bytes in a text column, while
/// PostgreSQL's text is valid UTF-8 without NUL. Each byte sequence that is not UTF-8, and
/// each NUL, becomes U+FFFD (so the fleet refuses no row); any other text arrives unchanged.
fn fleet_text(bytes: Option<Vec<u8>>) -> Option<String> {
    bytes.map(|b| String::from_utf8_lossy(&b).replace('\0', "\u{FFFD}"))
}

async fn upsert(
    tx: &mut sqlx::PgConnection,
    cell_id: &str,
    schema: &TableSchema,
    rows: &[Vec<Value>],
) -> Result<(), sqlx::Error> {
    let per_statement = (MAX_BINDS / (schema.columns.len() + 1)).max(1);
    let key = schema.table.key.join(", ");
    let updates: Vec<String> = schema
        .columns
        .iter()
        .filter(|(name, _)| !schema.table.key.contains(&name.as_str()))
        .map(|(name, _)| format!("{name} = EXCLUDED.{name}"))
        .collect();
    for chunk in rows.chunks(per_statement) {
        let mut query = QueryBuilder::<Postgres>::new(format!(
            "INSERT INTO {} (cell_id, {}) ",
            schema.table.name,
            column_list(schema)
        ));
        query.push_values(chunk, |mut row_values, row| {
            row_values.push_bind(cell_id.to_string());
            for value in row {
                match value.clone() {
                    Value::Int(v) => row_values.push_bind(v),
                    Value::Real(v) => row_values.push_bind(v),
                    Value::Text(v) => row_values.push_bind(v),
                    Value::Blob(v) => row_values.push_bind(v),
                };
            }
        });
        query.push(format!(
            " ON CONFLICT (cell_id, {key}) DO UPDATE SET {}",
            updates.join(", ")
        ));
        query.build().execute(&mut *tx).await?;
    }
    Ok(())
}

async fn delete(
    tx: &mut sqlx::PgConnection,
    cell_id: &str,
    schema: &TableSchema,
    gone: &[Key],
) -> Result<(), sqlx::Error> {
    for (key1, key2) in gone {
        let mut query = QueryBuilder::<Postgres>::new(format!(
            "DELETE FROM {} WHERE cell_id = ",
            schema.table.name
        ));
        query.push_bind(cell_id);
        for (column, value) in schema.table.key.iter().zip([Some(*key1), *key2]) {
            query.push(format!(" AND {column} = "));
            query.push_bind(value.unwrap_or_default());
        }
        query.build().execute(&mut *tx).await?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::fleet_text;

    #[test]
    fn text_postgres_cannot_hold_arrives_as_replacement_characters() {
        assert_eq!(fleet_text(None), None);
        assert_eq!(
            fleet_text(Some("Φ170 ok".into())).as_deref(),
            Some("Φ170 ok")
        );
        assert_eq!(
            fleet_text(Some(b"a\0b\xffc".to_vec())).as_deref(),
            Some("a\u{FFFD}b\u{FFFD}c")
        );
    }
}
