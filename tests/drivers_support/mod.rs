//! Helpers for the driver tests: `celld twin-server` as a child process on loopback ports,
//! and the Python peers' availability.
#![allow(dead_code)] // not every test binary that includes this module uses all of it

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// A running `celld twin-server`, killed when dropped.
pub struct TwinServer {
    child: Child,
    pub gcs: SocketAddr,
    pub igtl: SocketAddr,
}

impl TwinServer {
    /// Starts `celld twin-server` on free loopback ports with `args` added.
    pub fn start(args: &[&str]) -> TwinServer {
        TwinServer::start_on(0, 0, args)
    }

    /// Starts `celld twin-server` on these loopback ports (0: a free one) with `args` added.
    pub fn start_on(gcs_port: u16, igtl_port: u16, args: &[&str]) -> TwinServer {
        let mut child = Command::new(env!("CARGO_BIN_EXE_celld"))
            .args(["twin-server", "--gcs-port", &gcs_port.to_string()])
            .args(["--igtl-port", &igtl_port.to_string()])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start celld twin-server");
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("stdout"))
            .read_line(&mut line)
            .expect("the twin-server's first line");
        let address = |after: &str| -> SocketAddr {
            let start = line.find(after).unwrap_or_else(|| panic!("{line}")) + after.len();
            line[start..]
                .split([',', ' ', '\n'])
                .next()
                .unwrap()
                .parse()
                .unwrap_or_else(|e| panic!("{e}: {line}"))
        };
        TwinServer {
            gcs: address("GCS controller on "),
            igtl: address("OpenIGTLink camera on "),
            child,
        }
    }
}

impl Drop for TwinServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A peer script under tests/drivers/.
pub fn script(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/drivers")
        .join(name)
}

/// Whether `python3` can import `module`. Without it the test says so and passes, unless
/// `CI` is set: then it fails.
pub fn python_has(module: &str, package: &str) -> bool {
    let found = Command::new("python3")
        .args(["-c", &format!("import {module}")])
        .output()
        .is_ok_and(|output| output.status.success());
    if !found {
        assert!(
            std::env::var_os("CI").is_none(),
            "{package} is not installed (pip install {package}); CI needs it"
        );
        eprintln!("{package} is not installed: this peer test is skipped");
    }
    found
}
