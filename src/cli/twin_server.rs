//! `celld twin-server`: the digital twin as a GCS hexapod controller and an OpenIGTLink
//! camera, so `celld serve` with the real drivers (or any GCS and OpenIGTLink client) runs
//! against it on one machine.

use anyhow::{Context, Result};
use assembly_cell::config::cell::CellConfig;
use assembly_cell::drivers::twin_server::{TwinServer, TwinServerOptions};
use clap::Args;
use std::io::Write;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;

#[derive(Args)]
pub struct TwinServerArgs {
    /// Cell file (default: the bundled reference cell, cells/phi170.toml).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// The episode's seed: its initial pose, calibration error and noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Address both servers listen on.
    #[arg(long, default_value_t = IpAddr::V4(Ipv4Addr::LOCALHOST))]
    host: IpAddr,
    /// The GCS controller's TCP port (0: any free one, printed at start).
    #[arg(long, default_value_t = 50000)]
    gcs_port: u16,
    /// The OpenIGTLink camera's TCP port (0: any free one, printed at start).
    #[arg(long, default_value_t = 18944)]
    igtl_port: u16,
    /// Start as after power-on (servos off, not referenced) instead of ready to move.
    #[arg(long)]
    unreferenced: bool,
    /// Moves arrive at once (ONT? 1 right after MOV) instead of taking the time the cell's
    /// speeds (robot.speed_mm_s, robot.speed_deg_s) give them.
    #[arg(long)]
    instant_moves: bool,
    /// Also stream a capture to every camera client at this rate, Hz (0: capture only when
    /// asked with GET_POINT).
    #[arg(long, default_value_t = 0.0)]
    camera_stream_hz: f64,
    /// OpenIGTLink header version of the messages sent: 1 or 2.
    #[arg(long, default_value_t = 2)]
    igtl_version: u16,
}

pub fn run(args: TwinServerArgs) -> Result<()> {
    let cell = match &args.cell {
        Some(path) => {
            CellConfig::load(path).with_context(|| format!("--cell {}", path.display()))?
        }
        None => CellConfig::reference(),
    };
    let options = TwinServerOptions {
        cell,
        seed: args.seed,
        gcs: SocketAddr::new(args.host, args.gcs_port),
        igtl: SocketAddr::new(args.host, args.igtl_port),
        ready: !args.unreferenced,
        stream_hz: args.camera_stream_hz,
        igtl_version: args.igtl_version,
        instant_moves: args.instant_moves,
    };
    let server = TwinServer::start(&options)?;
    println!(
        "celld twin-server: cell `{}`, seed {}: GCS controller on {}, OpenIGTLink camera on {}",
        options.cell.name, options.seed, server.gcs, server.igtl
    );
    std::io::stdout().flush().ok();
    loop {
        std::thread::park();
    }
}
