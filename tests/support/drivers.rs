//! Helpers for the driver tests: `celld twin-server` as a child process on loopback ports,
//! and the Python peers' availability.
#![allow(dead_code)] // not every test binary that includes this module uses all of it

use assembly_cell::drivers::igtl::codec::{HEADER_BYTES, Header};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

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

/// [`camera_relay`] passes the camera's messages on.
pub const PASS: u8 = 0;
/// [`camera_relay`] swallows them.
pub const SILENT: u8 = 1;
/// [`camera_relay`] sends the last message passed on again instead (the same bytes).
pub const REPEAT: u8 = 2;
/// [`camera_relay`] sends 80 bytes of garbage instead.
pub const GARBAGE: u8 = 3;

/// A relay in front of the camera at `upstream`, on a free loopback port: queries go through;
/// the camera's messages are passed on, or not, as `mode` says at each message.
pub fn camera_relay(upstream: SocketAddr, mode: Arc<AtomicU8>) -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for client in listener.incoming() {
            let Ok(mut client) = client else { return };
            let Ok(mut camera) = TcpStream::connect(upstream) else {
                return;
            };
            let mut queries = client.try_clone().unwrap();
            let mut to_camera = camera.try_clone().unwrap();
            std::thread::spawn(move || std::io::copy(&mut queries, &mut to_camera));
            let mode = mode.clone();
            std::thread::spawn(move || {
                let mut last: Option<Vec<u8>> = None;
                loop {
                    let mut message = vec![0u8; HEADER_BYTES];
                    if camera.read_exact(&mut message).is_err() {
                        return;
                    }
                    let header = Header::decode(message[..].try_into().unwrap()).unwrap();
                    let mut body = vec![0u8; header.body_size as usize];
                    if camera.read_exact(&mut body).is_err() {
                        return;
                    }
                    message.extend_from_slice(&body);
                    // One reading of the mode per message: a message passed on is always the
                    // one a later repeat sends, even when the mode changes while it is written
                    // (read twice, a repeat could send the message before it, out of order).
                    let sent = match mode.load(Ordering::SeqCst) {
                        PASS => {
                            let sent = client.write_all(&message);
                            last = Some(message);
                            sent
                        }
                        SILENT => Ok(()),
                        REPEAT => client.write_all(last.get_or_insert(message)),
                        _ => client.write_all(&[0xEE; 80]),
                    };
                    if sent.is_err() {
                        return;
                    }
                }
            });
        }
    });
    address
}
