//! A throwaway PostgreSQL for the fleet tests: a cluster of its own in a temporary directory on
//! a free loopback port, or a fresh database on the cluster CI started for the whole run
//! (`CELLD_TEST_POSTGRES_URL`, see .ci/run). A missing PostgreSQL fails the test, CI or not:
//! the fleet cannot be tested without one.
#![allow(dead_code)] // not every test binary that includes this module uses all of it

use sqlx::Connection;
use std::ffi::OsStr;
use std::future::Future;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// The URL of CI's cluster, when it started one for the whole run.
pub const SHARED_URL_ENV: &str = "CELLD_TEST_POSTGRES_URL";
/// A directory holding `initdb`, `pg_ctl` and `postgres`, when not the newest Debian one.
pub const BIN_ENV: &str = "CELLD_PG_BIN";

/// A PostgreSQL cluster of its own: initialised in a temporary directory, listening on
/// 127.0.0.1 and a unix socket in that directory, with database `celld`. Dropping it stops the
/// server and removes the directory.
pub struct Postgres {
    bin: PathBuf,
    /// Holds `data/` (the cluster), `server.log` and the unix socket; removed when dropped.
    dir: tempfile::TempDir,
    port: u16,
    /// Root runs PostgreSQL's programs as user `postgres`: PostgreSQL refuses to run as root.
    as_postgres: bool,
}

impl Postgres {
    /// Initialises and starts a cluster, and creates database `celld`. Panics, with
    /// PostgreSQL's own output, when that fails.
    pub fn start() -> Postgres {
        let bin = find_binaries(std::env::var_os(BIN_ENV).as_deref().map(Path::new))
            .unwrap_or_else(|problem| panic!("{problem}"));
        // SAFETY: geteuid has no preconditions and cannot fail.
        let as_postgres = unsafe { libc::geteuid() } == 0;
        let dir = tempfile::Builder::new()
            .prefix("celld-pg-")
            .tempdir()
            .expect("a temporary directory for PostgreSQL");
        if as_postgres {
            run(
                Command::new("chown")
                    .arg("postgres:postgres")
                    .arg(dir.path()),
                "give the cluster's directory to user postgres",
            );
        }
        let mut postgres = Postgres {
            bin,
            dir,
            port: 0,
            as_postgres,
        };
        run(
            postgres
                .command("initdb")
                .arg("-D")
                .arg(postgres.data())
                .args(["-A", "trust", "-U", "postgres", "-E", "UTF8", "--locale=C"])
                // Nothing is flushed to disk: the cluster is thrown away after the test.
                .arg("--no-sync"),
            "initdb",
        );
        let settings = format!(
            "\n# A test cluster, thrown away after the test: speed over durability.\n\
             # No flush to disk. A crash of PostgreSQL itself (kill -9) still loses no\n\
             # committed transaction, since commits still reach the OS (synchronous_commit\n\
             # stays on); only a crash of the whole machine would.\n\
             fsync = off\n\
             full_page_writes = off\n\
             listen_addresses = '127.0.0.1'\n\
             unix_socket_directories = '{}'\n\
             shared_buffers = 16MB\n",
            postgres.dir.path().display()
        );
        append(&postgres.data().join("postgresql.conf"), &settings);
        // Another process may take the free port before the server binds it: try another.
        let mut attempts = 0;
        loop {
            postgres.port = free_port();
            match postgres.try_start() {
                Ok(()) => break,
                Err(log) if attempts < 4 && log.contains("could not bind") => attempts += 1,
                Err(log) => panic!("PostgreSQL did not start:\n{log}"),
            }
        }
        execute(&postgres.admin_url(), "CREATE DATABASE celld")
            .unwrap_or_else(|e| panic!("create database celld: {e}"));
        postgres
    }

    /// Turns TLS on: a certificate authority and a server certificate for 127.0.0.1 made with
    /// `openssl`, and the server restarted with them. Answers the authority's certificate, for
    /// a client's `sslrootcert`.
    pub fn enable_tls(&self) -> PathBuf {
        let dir = self.dir.path();
        let ca = dir.join("ca.crt");
        let (server_crt, server_key) = (dir.join("server.crt"), dir.join("server.key"));
        let openssl = |args: &[&str], what: &str| {
            run(Command::new("openssl").current_dir(dir).args(args), what);
        };
        openssl(
            &[
                "req",
                "-new",
                "-x509",
                "-days",
                "2",
                "-nodes",
                "-subj",
                "/CN=celld test CA",
                "-keyout",
                "ca.key",
                "-out",
                "ca.crt",
            ],
            "openssl: the test CA",
        );
        openssl(
            &[
                "req",
                "-new",
                "-nodes",
                "-subj",
                "/CN=127.0.0.1",
                "-keyout",
                "server.key",
                "-out",
                "server.csr",
            ],
            "openssl: the server's key",
        );
        std::fs::write(
            dir.join("server.ext"),
            "subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\n",
        )
        .unwrap();
        openssl(
            &[
                "x509",
                "-req",
                "-in",
                "server.csr",
                "-CA",
                "ca.crt",
                "-CAkey",
                "ca.key",
                "-CAcreateserial",
                "-days",
                "2",
                "-extfile",
                "server.ext",
                "-out",
                "server.crt",
            ],
            "openssl: the server's certificate",
        );
        if self.as_postgres {
            run(
                Command::new("chown")
                    .arg("postgres:postgres")
                    .arg(&server_crt)
                    .arg(&server_key),
                "give the server's certificate to user postgres",
            );
        }
        run(
            Command::new("chmod").arg("600").arg(&server_key),
            "chmod the server's key",
        );
        append(
            &self.data().join("postgresql.conf"),
            &format!(
                "ssl = on\nssl_cert_file = '{}'\nssl_key_file = '{}'\n",
                server_crt.display(),
                server_key.display()
            ),
        );
        self.stop();
        self.start_again();
        ca
    }

    /// `postgres://postgres@127.0.0.1:PORT/celld`.
    pub fn url(&self) -> String {
        format!("postgres://postgres@127.0.0.1:{}/celld", self.port)
    }

    /// The TCP port on 127.0.0.1, the same after `start_again`.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Creates a fresh database named after `name` (see [`create_database`]) and returns its URL.
    pub fn database(&self, name: &str) -> String {
        create_database(&self.admin_url(), name)
    }

    /// Stops the server (`pg_ctl stop -m fast`) and waits until it has exited. Connections
    /// fail until `start_again`.
    pub fn stop(&self) {
        run(
            self.command("pg_ctl")
                .arg("-D")
                .arg(self.data())
                .args(["-m", "fast", "-w", "-t", "60", "stop"]),
            "pg_ctl stop",
        );
    }

    /// Starts the server again on the same port with the same data.
    pub fn start_again(&self) {
        self.try_start()
            .unwrap_or_else(|log| panic!("PostgreSQL did not start again:\n{log}"));
    }

    /// Kills the server and its processes with SIGKILL, as a crash would, and waits until they
    /// are gone. `start_again` then recovers from the write-ahead log.
    pub fn kill9(&self) {
        let pid_file = self.data().join("postmaster.pid");
        let text = std::fs::read_to_string(&pid_file)
            .unwrap_or_else(|e| panic!("{}: {e} (is the server running?)", pid_file.display()));
        let postmaster: i32 = text
            .lines()
            .next()
            .and_then(|line| line.trim().parse().ok())
            .unwrap_or_else(|| panic!("{}: no process id in {text:?}", pid_file.display()));
        let mut pids = children_of(postmaster);
        pids.push(postmaster);
        for &pid in &pids {
            // SAFETY: kill only sends a signal; a process already gone is ESRCH, ignored.
            unsafe { libc::kill(pid, libc::SIGKILL) };
        }
        let deadline = Instant::now() + Duration::from_secs(30);
        while pids.iter().any(|&pid| alive(pid)) {
            assert!(
                Instant::now() < deadline,
                "PostgreSQL's processes {pids:?} outlived SIGKILL by 30 s"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        // The postmaster's System V shared memory block outlives it; the next start would remove
        // it only if it found the lock file (line 7: key and id). Nothing is attached any more.
        if let Some(id) = text
            .lines()
            .nth(6)
            .and_then(|line| line.split_whitespace().nth(1)?.parse::<i32>().ok())
        {
            // SAFETY: IPC_RMID takes no buffer; an id already gone is EINVAL, ignored.
            unsafe { libc::shmctl(id, libc::IPC_RMID, std::ptr::null_mut()) };
        }
        // The lock files name the dead postmaster. Where nothing reaps orphans promptly (a
        // container's init may not), its zombie would still pass PostgreSQL's is-it-running
        // check, so the next start would refuse. A zombie holds no memory and no socket: the
        // locks are stale, as after a crash of the machine.
        for lock in [
            pid_file,
            self.dir.path().join(format!(".s.PGSQL.{}.lock", self.port)),
        ] {
            std::fs::remove_file(&lock).unwrap_or_else(|e| panic!("{}: {e}", lock.display()));
        }
    }

    /// The server's log so far (for a failing test's message).
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("server.log")).unwrap_or_default()
    }

    fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    fn admin_url(&self) -> String {
        format!("postgres://postgres@127.0.0.1:{}/postgres", self.port)
    }

    /// `pg_ctl start -w` on `self.port`; on failure, pg_ctl's output and the server's log.
    fn try_start(&self) -> Result<(), String> {
        let output = self
            .command("pg_ctl")
            .arg("-D")
            .arg(self.data())
            .arg("-l")
            .arg(self.dir.path().join("server.log"))
            .args([
                "-o",
                &format!("-p {}", self.port),
                "-w",
                "-t",
                "60",
                "start",
            ])
            .output()
            .unwrap_or_else(|e| panic!("run pg_ctl: {e}"));
        if output.status.success() {
            Ok(())
        } else {
            Err(format!("{}\n{}", describe(&output), self.log()))
        }
    }

    /// One of PostgreSQL's programs, as user `postgres` when we are root.
    fn command(&self, program: &str) -> Command {
        let path = self.bin.join(program);
        let mut command = if self.as_postgres {
            let mut command = Command::new("runuser");
            command.args(["-u", "postgres", "--"]).arg(path);
            command
        } else {
            Command::new(path)
        };
        // User postgres may not be allowed into the test's working directory.
        command.current_dir(self.dir.path());
        command
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        if self.data().join("postmaster.pid").exists() {
            let stopped = self
                .command("pg_ctl")
                .arg("-D")
                .arg(self.data())
                .args(["-m", "immediate", "-w", "stop"])
                .output();
            if let Ok(output) = stopped
                && !output.status.success()
                && !String::from_utf8_lossy(&output.stderr).contains("no server running")
            {
                eprintln!("PostgreSQL did not stop: {}", describe(&output));
            }
        }
    }
}

/// A URL for a fresh database named after `name`: on CI's cluster when `CELLD_TEST_POSTGRES_URL`
/// names one, else on a cluster of its own, returned with it and kept running until dropped.
/// For tests that do not stop the server; those that do start a [`Postgres`] of their own.
pub fn fleet_database(name: &str) -> (String, Option<Postgres>) {
    match std::env::var(SHARED_URL_ENV) {
        Ok(shared) if !shared.is_empty() => (create_database(&shared, name), None),
        _ => {
            let postgres = Postgres::start();
            let url = postgres.database(name);
            (url, Some(postgres))
        }
    }
}

/// Creates a database through `server_url` (any database of the cluster) and returns the same
/// URL naming it. Its name is `name`, `_`, this process's id and a counter, so that tests and
/// test runs sharing a cluster never meet. `name`: lower-case letters, digits and `_`, at most
/// 40 characters.
pub fn create_database(server_url: &str, name: &str) -> String {
    static NEXT: AtomicU32 = AtomicU32::new(0);
    assert!(
        !name.is_empty()
            && name.len() <= 40
            && name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_'),
        "database name {name:?}: use 1 to 40 lower-case letters, digits and _"
    );
    let database = format!(
        "{name}_{}_{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    );
    execute(server_url, &format!("CREATE DATABASE {database}"))
        .unwrap_or_else(|e| panic!("create database {database} through {server_url}: {e}"));
    with_database(server_url, &database)
}

/// `url` with its database replaced by `database`, its query (`?sslmode=…`) kept.
pub fn with_database(url: &str, database: &str) -> String {
    let rest = url
        .strip_prefix("postgres://")
        .or_else(|| url.strip_prefix("postgresql://"))
        .unwrap_or_else(|| panic!("{url:?} is not a postgres:// URL"));
    let scheme = &url[..url.len() - rest.len()];
    let (rest, query) = match rest.find('?') {
        Some(at) => rest.split_at(at),
        None => (rest, ""),
    };
    let authority = rest.split('/').next().unwrap_or(rest);
    format!("{scheme}{authority}/{database}{query}")
}

/// Runs `sql` (one or more statements) on a connection to `url`.
pub fn execute(url: &str, sql: &str) -> Result<(), sqlx::Error> {
    block_on(move || async move {
        let mut connection = sqlx::PgConnection::connect(url).await?;
        sqlx::raw_sql(sql).execute(&mut connection).await?;
        connection.close().await
    })
}

/// Runs the future `make` returns on a runtime and a thread of its own, so that it works from a
/// plain test and from inside a tokio one alike. (The future is made on that thread, so it need
/// not be `Send`; sqlx's are not always.)
pub fn block_on<F, Fut>(make: F) -> Fut::Output
where
    F: FnOnce() -> Fut + Send,
    Fut: Future,
    Fut::Output: Send,
{
    std::thread::scope(|scope| {
        scope
            .spawn(|| {
                tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .expect("a tokio runtime")
                    .block_on(make())
            })
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

/// The directory of `initdb`, `pg_ctl` and `postgres`: `configured` (from `CELLD_PG_BIN`) if
/// given, else the newest /usr/lib/postgresql/*/bin, else the one on PATH holding `initdb`.
pub fn find_binaries(configured: Option<&Path>) -> Result<PathBuf, String> {
    let complete = |dir: &Path| {
        ["initdb", "pg_ctl", "postgres"]
            .iter()
            .all(|program| dir.join(program).is_file())
    };
    if let Some(dir) = configured {
        return if complete(dir) {
            Ok(dir.to_path_buf())
        } else {
            Err(format!(
                "{BIN_ENV}={}: no initdb, pg_ctl and postgres there",
                dir.display()
            ))
        };
    }
    let version = |name: &OsStr| -> Option<Vec<u32>> {
        name.to_str()?
            .split('.')
            .map(|part| part.parse().ok())
            .collect()
    };
    let debian = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .filter_map(|entry| {
            let entry = entry.ok()?;
            Some((version(&entry.file_name())?, entry.path().join("bin")))
        })
        .filter(|(_, bin)| complete(bin))
        .max();
    if let Some((_, bin)) = debian {
        return Ok(bin);
    }
    std::env::var_os("PATH")
        .iter()
        .flat_map(std::env::split_paths)
        .find(|dir| complete(dir))
        .ok_or_else(|| {
            format!(
                "PostgreSQL's server programs (initdb, pg_ctl, postgres) are not installed: not in \
                 {BIN_ENV}, /usr/lib/postgresql/*/bin or PATH (Debian: apt-get install postgresql)"
            )
        })
}

/// A port free on 127.0.0.1 now.
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|listener| listener.local_addr())
        .expect("a free port on 127.0.0.1")
        .port()
}

/// Runs `command`, panicking with its output when it fails.
fn run(command: &mut Command, what: &str) {
    let output = command
        .output()
        .unwrap_or_else(|e| panic!("{what}: cannot run {command:?}: {e}"));
    assert!(output.status.success(), "{what}: {}", describe(&output));
}

fn describe(output: &std::process::Output) -> String {
    format!(
        "{}\n{}{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    )
}

fn append(path: &Path, text: &str) {
    use std::io::Write;
    std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .and_then(|mut file| file.write_all(text.as_bytes()))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// The processes whose parent is `parent` (from /proc).
fn children_of(parent: i32) -> Vec<i32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|entry| {
            let pid: i32 = entry.ok()?.file_name().to_str()?.parse().ok()?;
            (stat(pid)?.get(1)? == &parent.to_string()).then_some(pid)
        })
        .collect()
}

/// Whether `pid` runs (a zombie, waiting for a parent to reap it, holds nothing any more).
fn alive(pid: i32) -> bool {
    stat(pid).is_some_and(|fields| fields.first().is_some_and(|state| state != "Z"))
}

/// /proc/PID/stat's fields after the command name: state, parent, …
fn stat(pid: i32) -> Option<Vec<String>> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let close = text.rfind(')')?;
    Some(
        text[close + 1..]
            .split_whitespace()
            .map(str::to_string)
            .collect(),
    )
}
