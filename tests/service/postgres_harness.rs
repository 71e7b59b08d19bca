//! The throwaway PostgreSQL the fleet tests run against (tests/support/postgres.rs): rows
//! written before a stop or a crash are read back after the start again, a stopped server
//! refuses connections, and databases made for different tests are separate.

use crate::postgres_support::{
    Postgres, SHARED_URL_ENV, block_on, execute, find_binaries, fleet_database, with_database,
};
use sqlx::{Connection, PgConnection};
use std::net::TcpStream;
use std::path::Path;
use std::process::Command;

const PARTS: &str = "CREATE TABLE parts (id BIGINT PRIMARY KEY, name TEXT NOT NULL)";

/// `parts`, ordered by id.
fn parts(url: &str) -> Result<Vec<(i64, String)>, sqlx::Error> {
    block_on(move || async move {
        let mut connection = PgConnection::connect(url).await?;
        let rows = sqlx::query_as("SELECT id, name FROM parts ORDER BY id")
            .fetch_all(&mut connection)
            .await?;
        connection.close().await?;
        Ok(rows)
    })
}

fn scalar(url: &str, sql: &str) -> String {
    block_on(move || async move {
        let mut connection = PgConnection::connect(url).await?;
        let (value,): (String,) = sqlx::query_as(sql).fetch_one(&mut connection).await?;
        connection.close().await?;
        Ok::<_, sqlx::Error>(value)
    })
    .unwrap_or_else(|e| panic!("{sql} on {url}: {e}"))
}

fn owned(rows: &[(i64, &str)]) -> Vec<(i64, String)> {
    rows.iter()
        .map(|&(id, name)| (id, name.to_string()))
        .collect()
}

/// The SQLSTATE of a database error, or the error itself when it is not one.
fn sqlstate(error: sqlx::Error) -> String {
    match error.as_database_error().and_then(|e| e.code()) {
        Some(code) => code.into_owned(),
        None => panic!("not a database error: {error}"),
    }
}

/// A connection to the stopped server fails at the socket, not in PostgreSQL.
fn assert_down(postgres: &Postgres) {
    let error = parts(&postgres.url()).expect_err("a stopped server answered");
    assert!(matches!(error, sqlx::Error::Io(_)), "{error}");
    assert!(TcpStream::connect(("127.0.0.1", postgres.port())).is_err());
}

#[test]
fn a_cluster_keeps_its_rows_across_a_stop_and_a_start() {
    let postgres = Postgres::start();
    let url = postgres.url();
    assert_eq!(
        url,
        format!("postgres://postgres@127.0.0.1:{}/celld", postgres.port())
    );
    assert_eq!(scalar(&url, "SELECT current_database()::text"), "celld");
    execute(
        &url,
        &format!("{PARTS}; INSERT INTO parts VALUES (2, 'bore'), (1, 'shaft'), (3, 'gripper')"),
    )
    .unwrap();
    let expected = owned(&[(1, "shaft"), (2, "bore"), (3, "gripper")]);
    assert_eq!(parts(&url).unwrap(), expected);

    postgres.stop();
    assert_down(&postgres);

    postgres.start_again();
    assert_eq!(postgres.url(), url);
    assert_eq!(parts(&url).unwrap(), expected);
}

#[test]
fn a_killed_cluster_recovers_its_committed_rows() {
    let postgres = Postgres::start();
    let url = postgres.url();
    execute(&url, PARTS).unwrap();
    execute(&url, "INSERT INTO parts VALUES (1, 'shaft')").unwrap();
    execute(&url, "INSERT INTO parts VALUES (2, 'bore')").unwrap();

    postgres.kill9();
    assert_down(&postgres);

    postgres.start_again();
    assert_eq!(parts(&url).unwrap(), owned(&[(1, "shaft"), (2, "bore")]));
    execute(&url, "INSERT INTO parts VALUES (3, 'gripper')").unwrap();
    assert_eq!(parts(&url).unwrap().len(), 3);
}

#[test]
fn databases_of_one_cluster_are_separate() {
    let postgres = Postgres::start();
    let first = postgres.database("harness");
    let second = postgres.database("harness");
    assert_ne!(first, second);
    for url in [&first, &second] {
        let named = url.rsplit('/').next().unwrap();
        assert_eq!(scalar(url, "SELECT current_database()::text"), named);
    }

    execute(
        &first,
        &format!("{PARTS}; INSERT INTO parts VALUES (1, 'shaft')"),
    )
    .unwrap();
    // undefined_table: the second database has no `parts` yet.
    assert_eq!(sqlstate(parts(&second).unwrap_err()), "42P01");
    execute(
        &second,
        &format!("{PARTS}; INSERT INTO parts VALUES (7, 'bore')"),
    )
    .unwrap();

    assert_eq!(parts(&first).unwrap(), owned(&[(1, "shaft")]));
    assert_eq!(parts(&second).unwrap(), owned(&[(7, "bore")]));
    assert_eq!(
        parts(&postgres.url()).map_err(sqlstate),
        Err("42P01".into())
    );
}

#[test]
fn fleet_databases_are_fresh_and_separate() {
    let shared = std::env::var(SHARED_URL_ENV).is_ok_and(|url| !url.is_empty());
    let (first, first_cluster) = fleet_database("harness");
    let (second, second_cluster) = fleet_database("harness");
    // On CI's cluster no cluster of its own is started; elsewhere each comes with one.
    assert_eq!(first_cluster.is_none(), shared);
    assert_eq!(second_cluster.is_none(), shared);
    assert_ne!(first, second);

    let tables =
        "SELECT count(*)::text FROM information_schema.tables WHERE table_schema = 'public'";
    assert_eq!(scalar(&first, tables), "0");
    execute(
        &first,
        &format!("{PARTS}; INSERT INTO parts VALUES (1, 'shaft')"),
    )
    .unwrap();
    assert_eq!(scalar(&first, tables), "1");
    assert_eq!(scalar(&second, tables), "0");
    assert_eq!(parts(&first).unwrap(), owned(&[(1, "shaft")]));
}

#[test]
fn a_database_url_keeps_everything_but_the_database() {
    assert_eq!(
        with_database("postgres://postgres@127.0.0.1:5433/celld", "jobs_1_0"),
        "postgres://postgres@127.0.0.1:5433/jobs_1_0"
    );
    assert_eq!(
        with_database(
            "postgresql://celld:s3cret@fleet.example:5432/fleet?sslmode=disable",
            "x"
        ),
        "postgresql://celld:s3cret@fleet.example:5432/x?sslmode=disable"
    );
    assert_eq!(
        with_database("postgres://postgres@localhost", "x"),
        "postgres://postgres@localhost/x"
    );
}

#[test]
fn the_binaries_are_found_or_named_missing() {
    let empty = tempfile::tempdir().unwrap();
    let problem = find_binaries(Some(empty.path())).unwrap_err();
    assert!(problem.contains("CELLD_PG_BIN"), "{problem}");
    assert!(
        problem.contains(&empty.path().display().to_string()),
        "{problem}"
    );

    let bin = find_binaries(None).unwrap_or_else(|problem| panic!("{problem}"));
    assert_eq!(find_binaries(Some(&bin)), Ok(bin.clone()));
    for program in ["initdb", "pg_ctl", "postgres"] {
        let version = Command::new(Path::new(&bin).join(program))
            .arg("--version")
            .output()
            .unwrap();
        let version = String::from_utf8_lossy(&version.stdout);
        assert!(version.contains("(PostgreSQL)"), "{program}: {version}");
    }
}
