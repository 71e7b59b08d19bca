//! Starting and stopping the OPC UA server: settings, certificates, endpoints, and the tasks that
//! mirror the cell into the address space.
//!
//! Endpoints, both at `opc.tcp://host:port/`:
//! - security policy None, mode None: messages and the password (a celld API token) travel in
//!   clear, so it is meant for loopback (the default address, 127.0.0.1:4840) or a network as
//!   trusted as the machine;
//! - Basic256Sha256, SignAndEncrypt: for the plant network. The server's certificate and key
//!   are made at first start in `opcua-pki/` beside the database (`own/cert.der`,
//!   `private/private.pem`, valid 365 days; made again at a start after they expire, or after
//!   an administrator deletes both). A client's certificate is not trusted until an
//!   administrator moves it from `rejected/`, where its first attempt leaves it, to `trusted/`.
//!
//! Sign-in is by user name and password only (no anonymous user).

use super::address_space::{self, Field, changes, data_value};
use super::auth::PlantAuth;
use super::methods::{CellNodeManager, CellNodes};
use super::plant::{Plant, PlantView};
use crate::config::service::{OpcUaListen, ServiceConfig};
use anyhow::{Context, bail};
use opcua::crypto::{SecurityPolicy, X509};
use opcua::server::node_manager::memory::InMemoryNodeManagerBuilder;
use opcua::server::{ServerBuilder, ServerEndpoint, SubscriptionCache};
use opcua::types::{DateTime, MessageSecurityMode, NodeId};
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// The server's application URI (also in its certificate).
pub const APPLICATION_URI: &str = "urn:celld";

/// Where the OPC UA server listens and keeps its certificates.
#[derive(Debug, Clone, PartialEq)]
pub struct OpcUaSettings {
    /// None: no OPC UA server. Port 0 picks a free port.
    pub listen: Option<SocketAddr>,
    /// The PKI directory: own/, private/, trusted/, rejected/.
    pub pki_dir: PathBuf,
}

impl OpcUaSettings {
    /// The service's `[opcua]` settings, with the PKI directory `opcua-pki/` beside the
    /// database file.
    pub fn from_config(config: &ServiceConfig) -> Self {
        let listen = match config.opcua.listen {
            OpcUaListen::Off => None,
            OpcUaListen::Address(address) => Some(address),
        };
        OpcUaSettings {
            listen,
            pki_dir: pki_dir_beside(&config.db),
        }
    }
}

/// `opcua-pki/` in the directory of the database file `db`.
pub fn pki_dir_beside(db: &Path) -> PathBuf {
    db.parent()
        .filter(|dir| !dir.as_os_str().is_empty())
        .unwrap_or_else(|| Path::new("."))
        .join("opcua-pki")
}

/// How often the server looks for notifications to publish, ms. The crate's 100 ms would
/// make a state change wait up to 100 ms before its publish; a plant's client watching the
/// state asks for a publishing interval of tens of ms.
const SUBSCRIPTION_TICK_MS: u64 = 10;
/// The shortest publishing interval a client may ask for, ms.
const MIN_PUBLISHING_INTERVAL_MS: f64 = 20.0;

/// The server's own certificate and key, in the PKI directory.
const CERTIFICATE: &str = "own/cert.der";
const PRIVATE_KEY: &str = "private/private.pem";

/// Removes the server's certificate and key when the certificate has expired, so that new ones
/// are made (clients must then trust the new certificate).
fn renew_expired_certificate(pki_dir: &Path) -> anyhow::Result<()> {
    let path = pki_dir.join(CERTIFICATE);
    let Ok(der) = std::fs::read(&path) else {
        return Ok(());
    };
    let Ok(end) = X509::from_der(&der).and_then(|c| c.not_after()) else {
        return Ok(()); // not ours to replace: the check after start names it
    };
    if end > DateTime::now().as_chrono() {
        return Ok(());
    }
    tracing::warn!(
        "the OPC UA server certificate {} expired at {end}: making a new one, which clients \
         must trust again",
        path.display()
    );
    for file in [CERTIFICATE, PRIVATE_KEY] {
        let path = pki_dir.join(file);
        std::fs::remove_file(&path)
            .with_context(|| format!("cannot remove the expired {}", path.display()))?;
    }
    Ok(())
}

/// A running OPC UA server.
#[derive(Debug)]
pub struct OpcUaServer {
    local_addr: SocketAddr,
    endpoint_url: String,
    pki_dir: PathBuf,
    task: JoinHandle<Result<(), String>>,
}

impl OpcUaServer {
    /// The bound address (the real port when the settings said 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// `opc.tcp://host:port/`.
    pub fn endpoint_url(&self) -> &str {
        &self.endpoint_url
    }

    /// The server's certificate (DER), for clients to trust.
    pub fn certificate_path(&self) -> PathBuf {
        self.pki_dir.join(CERTIFICATE)
    }

    /// Client certificates trusted by the server.
    pub fn trusted_dir(&self) -> PathBuf {
        self.pki_dir.join("trusted")
    }

    /// Client certificates seen and not trusted.
    pub fn rejected_dir(&self) -> PathBuf {
        self.pki_dir.join("rejected")
    }

    /// Waits until the server has stopped (after `shutdown` became true).
    pub async fn finished(self) -> anyhow::Result<()> {
        match self.task.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(message)) => bail!("OPC UA server failed: {message}"),
            Err(join) => bail!("OPC UA server task failed: {join}"),
        }
    }
}

/// Starts the OPC UA server over `plant` (None when the settings turn it off); returns once it
/// listens. It runs until `shutdown` becomes true (or its sender is dropped).
pub async fn serve<P: Plant>(
    plant: P,
    settings: &OpcUaSettings,
    mut shutdown: watch::Receiver<bool>,
) -> anyhow::Result<Option<OpcUaServer>> {
    let Some(listen) = settings.listen else {
        return Ok(None);
    };
    let pki_dir = settings.pki_dir.clone();
    std::fs::create_dir_all(&pki_dir).with_context(|| {
        format!(
            "cannot create the OPC UA PKI directory {}",
            pki_dir.display()
        )
    })?;
    renew_expired_certificate(&pki_dir)?;
    let listener = tokio::net::TcpListener::bind(listen)
        .await
        .with_context(|| format!("OPC UA cannot listen on {listen}"))?;
    let local_addr = listener.local_addr().context("OPC UA listener address")?;
    let host = match local_addr.ip() {
        IpAddr::V4(ip) => ip.to_string(),
        IpAddr::V6(ip) => format!("[{ip}]"),
    };
    let endpoint_url = format!("opc.tcp://{host}:{}/", local_addr.port());

    let identification = plant.identification();
    let mut view_rx = plant.watch();
    let view = view_rx.borrow_and_update().clone();
    let events = plant.events();
    let token = CancellationToken::new();

    // Making the key pair at first start takes a while: off the async threads.
    let (server, handle) = {
        let (plant, token, pki_dir, host) = (plant.clone(), token.clone(), pki_dir.clone(), host);
        let view = view.clone();
        let name = if identification.cell_name.is_empty() {
            "celld".to_string()
        } else {
            format!("celld {}", identification.cell_name)
        };
        tokio::task::spawn_blocking(move || {
            let auth = PlantAuth::new(plant.clone());
            let nodes =
                move |context: opcua::server::node_manager::ServerContext,
                      space: &mut opcua::server::address_space::AddressSpace| {
                    let nodes = CellNodes::new(plant, &context, space);
                    address_space::build(space, nodes.namespace_index(), &identification, &view);
                    nodes
                };
            let mut builder =
                ServerBuilder::new().subscription_poll_interval_ms(SUBSCRIPTION_TICK_MS);
            let limits = &mut builder.limits_mut().subscriptions;
            limits.min_publishing_interval_ms = MIN_PUBLISHING_INTERVAL_MS;
            limits.min_sampling_interval_ms = SUBSCRIPTION_TICK_MS as f64;
            builder
                .application_name(name)
                .application_uri(APPLICATION_URI)
                .product_uri(APPLICATION_URI)
                .create_sample_keypair(true)
                .pki_dir(pki_dir)
                .trust_client_certs(false)
                .host(host)
                .port(local_addr.port())
                .discovery_urls(vec!["/".to_string()])
                .add_endpoint("none", ServerEndpoint::new_none("/", &[]))
                .add_endpoint(
                    "basic256sha256_sign_encrypt",
                    ServerEndpoint::new(
                        "/",
                        SecurityPolicy::Basic256Sha256,
                        MessageSecurityMode::SignAndEncrypt,
                        &[],
                    ),
                )
                .with_authenticator(Arc::new(auth))
                .with_node_manager(InMemoryNodeManagerBuilder::new(nodes))
                .token(token)
                .build()
        })
        .await
        .context("OPC UA server set-up task")?
        .map_err(|message| anyhow::anyhow!("OPC UA server settings: {message}"))?
    };
    if handle.info().server_certificate.is_none() || handle.info().server_pkey.is_none() {
        bail!(
            "the OPC UA server has no certificate and key: {} and {} are missing or unreadable \
             and could not be made again",
            pki_dir.join(CERTIFICATE).display(),
            pki_dir.join(PRIVATE_KEY).display()
        );
    }
    let manager = handle
        .node_managers()
        .get_of_type::<CellNodeManager<P>>()
        .context("the cell's OPC UA node manager is missing")?;
    let ns = manager.inner().namespace_index();
    let subscriptions = handle.subscriptions().clone();

    tokio::spawn(mirror(
        manager,
        subscriptions.clone(),
        view_rx,
        view,
        token.clone(),
    ));
    tokio::spawn(raise_events(
        subscriptions,
        events,
        address_space::node_id(ns, ""),
        token.clone(),
    ));
    {
        let token = token.clone();
        tokio::spawn(async move {
            tokio::select! {
                _ = shutdown.wait_for(|stop| *stop) => {}
                _ = token.cancelled() => {}
            }
            token.cancel();
        });
    }
    let task = tokio::spawn(async move {
        let result = server.run_with(listener).await;
        // The server also ends on its own failure: stop the mirroring tasks with it.
        token.cancel();
        result
    });
    tracing::info!(%endpoint_url, pki = %pki_dir.display(), "OPC UA server listening");
    Ok(Some(OpcUaServer {
        local_addr,
        endpoint_url,
        pki_dir,
        task,
    }))
}

/// Writes each change of the view into the variables that changed, at the time it arrived.
async fn mirror<P: Plant>(
    manager: Arc<CellNodeManager<P>>,
    subscriptions: Arc<SubscriptionCache>,
    mut view_rx: watch::Receiver<PlantView>,
    mut shown: PlantView,
    token: CancellationToken,
) {
    let ns = manager.inner().namespace_index();
    let ids: Vec<NodeId> = Field::ALL
        .iter()
        .map(|f| address_space::node_id(ns, &f.path()))
        .collect();
    loop {
        tokio::select! {
            changed = view_rx.changed() => if changed.is_err() {
                tracing::warn!("the cell's view ended: OPC UA variables keep their last values");
                return;
            },
            _ = token.cancelled() => return,
        }
        let view = view_rx.borrow_and_update().clone();
        let now = DateTime::now();
        let updates = changes(&shown, &view);
        let values = updates.into_iter().map(|(field, value)| {
            let index = Field::ALL.iter().position(|f| *f == field).unwrap_or(0);
            (&ids[index], None, data_value(value, now))
        });
        if let Err(status) = manager.set_values(&subscriptions, values) {
            tracing::warn!("OPC UA variables not updated: {status}");
        }
        shown = view;
    }
}

/// Raises each plant event from the `Cell` object (and so the Server object).
async fn raise_events(
    subscriptions: Arc<SubscriptionCache>,
    mut events: broadcast::Receiver<crate::opcua::plant::PlantEvent>,
    cell: NodeId,
    token: CancellationToken,
) {
    let mut number = 0u64;
    loop {
        let event = tokio::select! {
            event = events.recv() => event,
            _ = token.cancelled() => return,
        };
        match event {
            Ok(event) => {
                number += 1;
                let event = address_space::event(&event, &cell, "Cell", number, DateTime::now());
                subscriptions.notify_events(
                    [(&event as &dyn opcua::server::address_space::Event, &cell)].into_iter(),
                );
            }
            Err(broadcast::error::RecvError::Lagged(skipped)) => {
                tracing::warn!(skipped, "OPC UA events fell behind and skipped some");
            }
            Err(broadcast::error::RecvError::Closed) => return,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pki_directory_lies_beside_the_database() {
        assert_eq!(
            pki_dir_beside(Path::new("data/celld.db")),
            PathBuf::from("data/opcua-pki")
        );
        assert_eq!(
            pki_dir_beside(Path::new("celld.db")),
            PathBuf::from("./opcua-pki")
        );
        let mut config = ServiceConfig::default();
        config.opcua.listen = OpcUaListen::Off;
        assert_eq!(OpcUaSettings::from_config(&config).listen, None);
    }
}
