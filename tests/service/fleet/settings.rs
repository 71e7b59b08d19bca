//! A fleet URL or cell id the service cannot use is refused at start, naming it.

use std::process::Command;

fn serve(env: &[(&str, &str)], args: &[&str]) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(["serve", "--listen", "127.0.0.1:0", "--db"])
        .arg(dir.path().join("celld.db"))
        .args(args)
        .env("CELLD_OPCUA_LISTEN", "off")
        .envs(env.iter().copied())
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn a_fleet_url_that_is_not_postgres_is_refused() {
    let (ok, stderr) = serve(&[], &["--fleet", "mysql://fleet-db/fleet"]);
    assert!(!ok);
    assert!(
        stderr.contains("fleet.url") && stderr.contains("mysql"),
        "{stderr}"
    );
    let (ok, stderr) = serve(&[("CELLD_FLEET_URL", "fleet-db:5432")], &[]);
    assert!(!ok);
    assert!(stderr.contains("postgres://"), "{stderr}");
}

#[test]
fn a_fleet_url_with_a_bad_port_is_refused() {
    let (ok, stderr) = serve(&[], &["--fleet", "postgres://fleet-db:port/fleet"]);
    assert!(!ok);
    assert!(stderr.contains("fleet.url"), "{stderr}");
}

#[test]
fn a_cell_id_with_spaces_is_refused() {
    let url = "postgres://celld@127.0.0.1:1/fleet";
    let (ok, stderr) = serve(&[("CELLD_CELL_ID", "cell 7")], &["--fleet", url]);
    assert!(!ok);
    assert!(
        stderr.contains("service.cell_id") && stderr.contains("` `"),
        "{stderr}"
    );
}
