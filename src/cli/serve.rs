//! `celld serve` and `celld token create|list|revoke`: the CLI side of the service (settings layering and a
//! runtime); the service itself is `app`.

use anyhow::Result;
use assembly_cell::app;
use assembly_cell::config::service::ServiceConfig;
use clap::{Args, Subcommand};
use std::net::SocketAddr;
use std::path::PathBuf;

#[derive(Args, Default)]
pub struct ServeArgs {
    /// Settings file (TOML, deploy/celld.example.toml); CELLD_* variables and flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Address to listen on (default 127.0.0.1:8080; port 0 picks a free one).
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// SQLite database file (default data/celld.db).
    #[arg(long)]
    db: Option<PathBuf>,
    /// Cell file (default: the bundled reference cell, cells/phi170.toml).
    #[arg(long)]
    cell: Option<PathBuf>,
    /// Run the twin as fast as it can instead of at the camera's rate.
    #[arg(long)]
    fast: bool,
    /// Join a fleet: replicate this cell's record to the PostgreSQL at this URL
    /// (postgres://user:password@host/database); the cell's own SQLite stays its record.
    #[arg(long, value_name = "URL")]
    fleet: Option<String>,
}

#[derive(Subcommand)]
pub enum TokenCommand {
    /// Make a new API token and print it (it is stored only as a hash).
    Create {
        /// viewer (read), operator (jobs, e-stop) or admin (policies, training, tokens).
        #[arg(long)]
        role: String,
        /// Who or what the token is for.
        #[arg(long)]
        name: String,
        /// Lifetime: whole seconds, or a number with s, m, h or d (`30d`); default: never
        /// expires.
        #[arg(long)]
        expires_in: Option<String>,
        /// SQLite database file (default data/celld.db, or the one CELLD_DB names).
        #[arg(long)]
        db: Option<PathBuf>,
    },
    /// List the tokens (never their secrets): id, role, state, created, expires, revoked, name.
    List {
        /// SQLite database file (default data/celld.db, or the one CELLD_DB names).
        #[arg(long)]
        db: Option<PathBuf>,
    },
    /// Revoke a token by its id; a running service refuses it within two seconds. The last
    /// admin token that still authenticates is kept: make another first.
    Revoke {
        /// The token's id (`celld token list`).
        id: i64,
        /// SQLite database file (default data/celld.db, or the one CELLD_DB names).
        #[arg(long)]
        db: Option<PathBuf>,
    },
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

pub fn serve(args: ServeArgs) -> Result<()> {
    let mut settings = ServiceConfig::load(args.config.as_deref())?;
    settings.apply_env(std::env::vars())?;
    if let Some(listen) = args.listen {
        settings.listen = listen;
    }
    if let Some(db) = args.db {
        settings.db = db;
    }
    if let Some(cell) = args.cell {
        settings.cell = Some(cell);
    }
    if args.fast {
        settings.fast = true;
    }
    if let Some(url) = args.fleet {
        settings.fleet.url = Some(url);
    }
    init_logging();
    app::run(settings)
}

pub fn token(command: TokenCommand) -> Result<()> {
    let database = |db: Option<PathBuf>| -> Result<PathBuf> {
        let mut settings = ServiceConfig::default();
        settings.apply_env(std::env::vars())?;
        Ok(db.unwrap_or(settings.db))
    };
    match command {
        TokenCommand::Create {
            role,
            name,
            expires_in,
            db,
        } => runtime()?.block_on(app::create_token(
            &database(db)?,
            &role,
            &name,
            expires_in.as_deref(),
        )),
        TokenCommand::List { db } => runtime()?.block_on(app::list_tokens(&database(db)?)),
        TokenCommand::Revoke { id, db } => {
            runtime()?.block_on(app::revoke_token(&database(db)?, id))
        }
    }
}

/// Logs to stderr; `CELLD_LOG` = error, warn, info (default), debug or trace.
fn init_logging() {
    let level = std::env::var("CELLD_LOG")
        .ok()
        .and_then(|l| l.parse().ok())
        .unwrap_or(tracing::Level::INFO);
    tracing_subscriber::fmt()
        .with_max_level(level)
        .with_writer(std::io::stderr)
        .init();
}
