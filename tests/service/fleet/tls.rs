//! A fleet reached over TLS: with `sslmode=verify-full` and the server's authority the cell
//! replicates over encrypted connections; without that authority it refuses the server and
//! says why, and runs on.

use super::{assert_replicated, cell, postgres, run_jobs};
use serde_json::json;

#[test]
fn a_cell_replicates_over_tls_and_refuses_a_server_it_cannot_verify() {
    let cluster = postgres::Postgres::start();
    let authority = cluster.enable_tls();
    let base = cluster.url();
    let url = format!(
        "{base}?sslmode=verify-full&sslrootcert={}",
        authority.display()
    );
    let dir = tempfile::tempdir().unwrap();
    let server = cell(dir.path(), &url, "cell-tls");
    run_jobs(&server, 1);
    assert_replicated(&base, &server, "cell-tls");
    let encrypted: i64 = postgres::block_on(|| async {
        use sqlx::Connection;
        let mut connection = sqlx::PgConnection::connect(&base).await.unwrap();
        sqlx::query_scalar(
            "SELECT count(*) FROM pg_stat_ssl s JOIN pg_stat_activity a USING (pid)
             WHERE s.ssl AND a.application_name = 'celld cell-tls'",
        )
        .fetch_one(&mut connection)
        .await
        .unwrap()
    });
    assert!(encrypted > 0, "the cell's connections are encrypted");

    // Trusting only the public authorities, the cell refuses the test CA's certificate.
    let dir = tempfile::tempdir().unwrap();
    let unverified = cell(
        dir.path(),
        &format!("{base}?sslmode=verify-full"),
        "cell-untrusting",
    );
    run_jobs(&unverified, 1);
    let (status, body) = unverified.get("/api/fleet/cells", Some(&unverified.admin));
    assert_eq!(
        (status, &body["error"]["code"]),
        (503, &json!("fleet_unavailable")),
        "{body}"
    );
    assert!(
        body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("certificate"),
        "{body}"
    );
}
