//! Bad input to the driver commands ends with a message naming the problem and a non-zero
//! exit: `celld twin-server`, `celld latency`, and `celld serve` with drivers it cannot reach.

use std::net::TcpListener;
use std::process::Command;

fn celld(args: &[&str], env: &[(&str, &str)]) -> (bool, String) {
    let output = Command::new(env!("CARGO_BIN_EXE_celld"))
        .args(args)
        .envs(env.iter().copied())
        .output()
        .expect("celld runs");
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn twin_server_and_latency_name_bad_arguments() {
    let any = ["--gcs-port", "0", "--igtl-port", "0"];
    let (ok, stderr) = celld(
        &[&["twin-server", "--igtl-version", "3"][..], &any].concat(),
        &[],
    );
    assert!(
        !ok && stderr.contains("header version must be 1 or 2, got 3"),
        "{stderr}"
    );
    let (ok, stderr) = celld(
        &[&["twin-server", "--camera-stream-hz=-1"][..], &any].concat(),
        &[],
    );
    assert!(!ok && stderr.contains("stream rate"), "{stderr}");
    let (ok, stderr) = celld(
        &[&["twin-server", "--cell", "no/such/cell.toml"][..], &any].concat(),
        &[],
    );
    assert!(!ok && stderr.contains("no/such/cell.toml"), "{stderr}");
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port().to_string();
    let (ok, stderr) = celld(
        &["twin-server", "--gcs-port", &port, "--igtl-port", "0"],
        &[],
    );
    assert!(
        !ok && stderr.contains(&format!("cannot listen on 127.0.0.1:{port} (GCS)")),
        "{stderr}"
    );
    let (ok, stderr) = celld(&["latency", "--samples", "3"], &[]);
    assert!(
        !ok && stderr.contains("--samples must be at least 10, got 3"),
        "{stderr}"
    );
}

#[test]
fn serve_names_a_controller_it_cannot_reach_and_drivers_that_do_not_go_together() {
    // A port nobody listens on: bound, then let go.
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
        .to_string();
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("celld.db");
    let db = db.to_str().unwrap();
    let serve = ["serve", "--listen", "127.0.0.1:0", "--db", db];
    let (ok, stderr) = celld(
        &serve,
        &[
            ("CELLD_ROBOT_DRIVER", "gcs"),
            ("CELLD_ROBOT_PORT", &port),
            ("CELLD_CAMERA_DRIVER", "igtl"),
            ("CELLD_CONTROL_CPU", "off"),
            ("CELLD_OPCUA_LISTEN", "off"),
            ("CELLD_EVALUATION_EPISODES", "1"),
        ],
    );
    assert!(
        !ok && stderr.contains(&format!(
            "cannot connect to the controller at 127.0.0.1:{port}"
        )),
        "{stderr}"
    );
    let (ok, stderr) = celld(&serve, &[("CELLD_ROBOT_DRIVER", "gcs")]);
    assert!(!ok && stderr.contains("camera.driver"), "{stderr}");
}
