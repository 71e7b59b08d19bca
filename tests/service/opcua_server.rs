//! The OPC UA server over a fake cell, as a plant's client meets it: asyncua (PyPI), a library no
//! one here wrote, browses, reads, subscribes, calls and signs in with and without Sign &
//! Encrypt (tests/service/opcua_client.py says what it checks).
//!
//! `.ci/run` installs asyncua. Elsewhere, without it, the client test says so and passes; with
//! `CI` set, a missing asyncua fails it.

use crate::drivers_support::python_has;
use crate::opcua_service::run_client;
use assembly_cell::opcua::server::OpcUaSettings;
use assembly_cell::opcua::{
    Identification, Plant, PlantEvent, PlantJob, PlantMethod, PlantUser, PlantView, Refused, serve,
};
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{broadcast, watch};

/// A cell that runs one part per Start: Execute, then Complete with one more part processed.
#[derive(Clone)]
struct FakePlant {
    view: Arc<watch::Sender<PlantView>>,
    events: broadcast::Sender<PlantEvent>,
    next_job: Arc<AtomicI64>,
    /// Every call that reached the cell: who and what.
    calls: Arc<Mutex<Vec<(String, PlantMethod)>>>,
}

impl FakePlant {
    fn new() -> FakePlant {
        let idle = PlantView {
            state: "Idle".into(),
            state_number: 4,
            unit_mode: "Production".into(),
            unit_mode_number: 1,
            processed_count: 41,
            ..PlantView::default()
        };
        FakePlant {
            view: Arc::new(watch::channel(idle).0),
            events: broadcast::channel(16).0,
            next_job: Arc::new(AtomicI64::new(7)),
            calls: Arc::default(),
        }
    }

    fn set_state(&self, state: &str, number: u32) {
        self.view.send_modify(|v| {
            v.state = state.into();
            v.state_number = number;
        });
    }
}

impl Plant for FakePlant {
    fn watch(&self) -> watch::Receiver<PlantView> {
        self.view.subscribe()
    }

    fn events(&self) -> broadcast::Receiver<PlantEvent> {
        self.events.subscribe()
    }

    fn identification(&self) -> Identification {
        Identification {
            manufacturer: "celld".into(),
            model: "shaft-in-bore cell".into(),
            product_instance_uri: "urn:celld:test".into(),
            serial_number: "T-1".into(),
            software_revision: env!("CARGO_PKG_VERSION").into(),
            cell_name: "test cell".into(),
        }
    }

    async fn sign_in(&self, user: &str, password: &str) -> Result<PlantUser, Refused> {
        let may_operate = match password {
            "operator-token" => true,
            "viewer-token" => false,
            _ => return Err(Refused::BadIdentity(format!("no such token for {user}"))),
        };
        Ok(PlantUser {
            name: user.to_string(),
            may_operate,
            key: password.len().to_string(),
        })
    }

    async fn call(&self, user: &PlantUser, method: PlantMethod) -> Result<Option<i64>, Refused> {
        self.calls
            .lock()
            .unwrap()
            .push((user.name.clone(), method.clone()));
        let state = self.view.borrow().state.clone();
        match method {
            PlantMethod::Start { controller, .. } => {
                if state != "Idle" {
                    return Err(Refused::InvalidState(format!("the cell is {state}")));
                }
                if controller != "expert" {
                    return Err(Refused::InvalidArgument(format!(
                        "no controller {controller}"
                    )));
                }
                let id = self.next_job.fetch_add(1, Ordering::SeqCst);
                self.view.send_modify(|v| {
                    v.state = "Execute".into();
                    v.state_number = 6;
                    v.job = Some(PlantJob {
                        id,
                        controller,
                        step: 0,
                        pose_error_mm: 1.5,
                        sigma_mm: 0.02,
                    });
                });
                let plant = self.clone();
                tokio::spawn(async move {
                    tokio::time::sleep(Duration::from_millis(300)).await;
                    plant.view.send_modify(|v| {
                        v.state = "Complete".into();
                        v.state_number = 17;
                        v.processed_count += 1;
                        v.last_cycle_time_s = 0.3;
                        v.mean_cycle_time_s = 0.3;
                        v.job = None;
                    });
                    let _ = plant.events.send(PlantEvent::JobEnded {
                        id,
                        status: "succeeded".into(),
                        reason: None,
                        steps: 12,
                        cycle_time_s: Some(0.3),
                    });
                });
                Ok(Some(id))
            }
            PlantMethod::Stop | PlantMethod::Clear => {
                self.set_state("Stopped", 2);
                Ok(None)
            }
            PlantMethod::Abort => {
                self.set_state("Aborted", 9);
                Ok(None)
            }
            PlantMethod::Reset => {
                self.set_state("Idle", 4);
                Ok(None)
            }
        }
    }
}

fn settings(dir: &std::path::Path, listen: Option<&str>) -> OpcUaSettings {
    OpcUaSettings {
        listen: listen.map(|a| a.parse().unwrap()),
        pki_dir: dir.join("opcua-pki"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn asyncua_browses_subscribes_and_commands_the_cell() {
    if !python_has("asyncua", "asyncua") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let plant = FakePlant::new();
    let (stop, shutdown) = watch::channel(false);
    let server = serve(
        plant.clone(),
        &settings(dir.path(), Some("127.0.0.1:0")),
        shutdown,
    )
    .await
    .unwrap()
    .expect("listen is set");
    let port = server.local_addr().port();
    assert_ne!(port, 0, "the real port is reported");
    assert_eq!(
        server.endpoint_url(),
        format!("opc.tcp://127.0.0.1:{port}/")
    );
    assert!(server.certificate_path().is_file());
    let pki = dir.path().join("opcua-pki");
    assert_eq!(server.trusted_dir(), pki.join("trusted"));

    let url = server.endpoint_url().to_string();
    tokio::task::spawn_blocking(move || {
        run_client(
            "opcua_client.py",
            &[
                "--url",
                &url,
                "--operator-token",
                "operator-token",
                "--viewer-token",
                "viewer-token",
                "--pki",
                pki.to_str().unwrap(),
                "--initial-state",
                "Idle",
            ],
        )
    })
    .await
    .unwrap();

    // Only the operator's Start reached the cell, its negative seed meaning a random one.
    assert_eq!(
        *plant.calls.lock().unwrap(),
        vec![(
            "operator".to_string(),
            PlantMethod::Start {
                controller: "expert".into(),
                seed: None
            }
        )]
    );
    assert_eq!(plant.view.borrow().processed_count, 42);
    assert_eq!(
        std::fs::read_dir(server.trusted_dir()).unwrap().count(),
        1,
        "the client's certificate, moved there by the script"
    );

    stop.send(true).unwrap();
    tokio::time::timeout(Duration::from_secs(60), server.finished())
        .await
        .expect("the server stops when told")
        .unwrap();
}

#[tokio::test]
async fn off_means_no_server_and_a_taken_port_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (_stop, shutdown) = watch::channel(false);
    let none = serve(
        FakePlant::new(),
        &settings(dir.path(), None),
        shutdown.clone(),
    )
    .await
    .unwrap();
    assert!(none.is_none());

    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = taken.local_addr().unwrap().to_string();
    let error = serve(
        FakePlant::new(),
        &settings(dir.path(), Some(&address)),
        shutdown,
    )
    .await
    .unwrap_err();
    assert!(
        format!("{error:#}").contains(&format!("cannot listen on {address}")),
        "{error:#}"
    );
}

/// A server certificate past its end is made again at start; a valid one is kept.
#[tokio::test]
async fn an_expired_server_certificate_is_made_again() {
    use opcua::crypto::{CertificateStore, X509, X509Data};
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("opcua-pki");
    let expired = X509Data {
        key_size: 1024,
        common_name: "expired".into(),
        organization: "celld".into(),
        organizational_unit: "test".into(),
        country: "DE".into(),
        state: "Berlin".into(),
        alt_host_names: vec!["urn:celld".to_string()].into(),
        certificate_duration_days: 0,
    };
    CertificateStore::new(&pki)
        .create_and_store_application_instance_cert(&expired, false)
        .unwrap();
    let certificate = pki.join("own/cert.der");
    let old = std::fs::read(&certificate).unwrap();

    let start = |plant: FakePlant| {
        let settings = settings(dir.path(), Some("127.0.0.1:0"));
        async move {
            let (stop, shutdown) = watch::channel(false);
            let server = serve(plant, &settings, shutdown).await.unwrap().unwrap();
            stop.send(true).unwrap();
            server.finished().await.unwrap();
        }
    };
    start(FakePlant::new()).await;
    let new = std::fs::read(&certificate).unwrap();
    assert_ne!(new, old, "a new certificate");
    let end = X509::from_der(&new).unwrap().not_after().unwrap();
    assert!(
        end.timestamp()
            > std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_secs() as i64
                + 300 * 86_400,
        "valid for most of a year: {end}"
    );

    start(FakePlant::new()).await;
    assert_eq!(
        std::fs::read(&certificate).unwrap(),
        new,
        "a valid one is kept"
    );
}
