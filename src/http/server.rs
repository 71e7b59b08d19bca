//! The HTTP/1.1 server: its own accept loop over hyper, so that no number of idle or slow
//! clients can keep a new one (an operator's e-stop) out.
//!
//! - A connection waiting for a request is closed after `idle_timeout` (no byte of one yet) or
//!   `header_timeout` from its first byte (the head not complete): a slowloris client is closed
//!   however slowly it trickles. hyper's own `header_read_timeout`, which runs from the moment a
//!   connection waits for a request to its complete head, is set to their sum as a backstop.
//! - At most `max_connections` are open. At the cap a new connection is still accepted (a
//!   client left in the kernel's backlog would wait for a timeout) and the oldest connection
//!   with no request in progress is closed for it; one with a request in progress (a telemetry
//!   stream, a running handler) is never closed by this rule. With none to close, the new
//!   connection is closed instead.
//! - The soft file-descriptor limit is raised to the hard one, and the cap must leave
//!   [`RESERVED_FDS`] of it for the database, drivers and logs.
//! - Each request carries `ConnectInfo<SocketAddr>` in its extensions.
//!
//! Knows nothing of the cell: it serves whatever [`Router`] it is given.

use crate::config::service::HttpConfig;
use axum::Router;
use axum::extract::ConnectInfo;
use hyper::body::{Body, Bytes, Frame, Incoming, SizeHint};
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::collections::BTreeMap;
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, watch};
use tokio::time::Instant;

/// File descriptors kept out of the connection cap's reach: SQLite's files and pools, the
/// drivers' sockets, the listener, logs.
pub const RESERVED_FDS: u64 = 256;

/// How long an accept error that is not the client's (out of descriptors or memory) pauses
/// the loop: long enough not to spin, short enough that a freed descriptor is used soon.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(50);

/// How long, after shutdown, requests in progress have to finish before the server stops
/// waiting for them.
const DRAIN: Duration = Duration::from_secs(2);

/// The same warning at most this often.
const WARN_EVERY: Duration = Duration::from_secs(5);

/// The connection limits (`[http]` settings).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConnectionLimits {
    /// Open connections at most (one over for a moment while the oldest idle one closes).
    pub max_connections: usize,
    /// From a request's first byte to its complete head.
    pub header_timeout: Duration,
    /// A keep-alive (or new) connection with no byte of a request.
    pub idle_timeout: Duration,
}

impl From<&HttpConfig> for ConnectionLimits {
    fn from(http: &HttpConfig) -> Self {
        ConnectionLimits {
            max_connections: http.max_connections,
            header_timeout: Duration::from_millis(http.header_timeout_ms),
            idle_timeout: Duration::from_secs(http.idle_timeout_s),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot read or raise the file-descriptor limit (RLIMIT_NOFILE): {0}")]
    FdLimit(io::Error),
    #[error(
        "http.max_connections = {max_connections} leaves fewer than {RESERVED_FDS} of this \
         process's {limit} file descriptors (RLIMIT_NOFILE, hard limit {hard}) for the \
         database and drivers: lower it to at most {most}, or raise the hard limit"
    )]
    TooManyConnections {
        max_connections: usize,
        limit: u64,
        hard: u64,
        most: u64,
    },
}

/// Raises the soft RLIMIT_NOFILE to the hard one; answers (soft, hard) as they are after.
#[cfg(unix)]
pub fn raise_fd_limit() -> io::Result<(u64, u64)> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes the struct it is given and reads nothing else.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
        return Err(io::Error::last_os_error());
    }
    if limit.rlim_cur < limit.rlim_max {
        let raised = libc::rlimit {
            rlim_cur: limit.rlim_max,
            rlim_max: limit.rlim_max,
        };
        // SAFETY: setrlimit reads the struct it is given. It may refuse an unlimited hard
        // limit (macOS caps the soft one): the soft limit then stays as it was.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
            limit.rlim_cur = limit.rlim_max;
        }
    }
    Ok((limit.rlim_cur, limit.rlim_max))
}

/// Serves `router` on `listener` until `shutdown` turns true (or its sender is dropped):
/// then stops accepting, closes idle connections, lets requests in progress finish (at most
/// [`DRAIN`]) and ends. Raises the file-descriptor limit and checks the cap against it first.
pub fn serve(
    listener: TcpListener,
    router: Router,
    limits: ConnectionLimits,
    shutdown: watch::Receiver<bool>,
) -> Result<impl Future<Output = ()> + Send + 'static, ServeError> {
    #[cfg(unix)]
    {
        let (limit, hard) = raise_fd_limit().map_err(ServeError::FdLimit)?;
        let most = limit.saturating_sub(RESERVED_FDS);
        if limits.max_connections as u64 > most {
            return Err(ServeError::TooManyConnections {
                max_connections: limits.max_connections,
                limit,
                hard,
                most,
            });
        }
    }
    Ok(accept_loop(listener, router, limits, shutdown))
}

async fn accept_loop(
    listener: TcpListener,
    router: Router,
    limits: ConnectionLimits,
    mut shutdown: watch::Receiver<bool>,
) {
    let service = TowerToHyperService::new(router);
    let registry = Arc::new(Registry::default());
    let epoch = Instant::now();
    // Each connection holds a receiver: `closed()` is the last one ending.
    let (open_tx, open_rx) = watch::channel(());
    let mut next_id = 0u64;
    let mut refusals = Warning::default();
    let mut accept_errors = Warning::default();
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            _ = shutdown.wait_for(|stop| *stop) => break,
        };
        let (stream, remote) = match accepted {
            Ok(accepted) => accepted,
            // The client gave up between its SYN and our accept: nothing of ours is wrong.
            Err(e) if is_connection_error(&e) => continue,
            Err(e) => {
                // Out of descriptors or memory: free one idle connection and pause.
                let evicted = registry.evict_oldest_idle();
                accept_errors.warn(|skipped| {
                    tracing::warn!(
                        error = %e, evicted, skipped,
                        "cannot accept a connection; pausing {} ms",
                        ACCEPT_BACKOFF.as_millis()
                    )
                });
                tokio::select! {
                    _ = tokio::time::sleep(ACCEPT_BACKOFF) => {}
                    _ = shutdown.wait_for(|stop| *stop) => break,
                }
                continue;
            }
        };
        if !registry.make_room(limits.max_connections) {
            refusals.warn(|skipped| {
                tracing::warn!(
                    %remote, skipped,
                    "{} connections, each with a request in progress: a new one is refused",
                    limits.max_connections
                )
            });
            continue;
        }
        let _ = stream.set_nodelay(true);
        next_id += 1;
        let tracker = Arc::new(Tracker::new(epoch, Instant::now()));
        registry.insert(next_id, tracker.clone());
        let connection = Connection {
            id: next_id,
            registry: registry.clone(),
            _open: open_rx.clone(),
        };
        tokio::spawn(connection.run(
            stream,
            remote,
            tracker,
            service.clone(),
            limits,
            shutdown.clone(),
        ));
    }
    drop(listener);
    drop(open_rx);
    if tokio::time::timeout(DRAIN, open_tx.closed()).await.is_err() {
        tracing::warn!(
            open = registry.len(),
            "requests still in progress {} s after shutdown are left to end with the process",
            DRAIN.as_secs()
        );
    }
}

/// Accept errors about one client's connection (it reset or vanished before the accept).
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

/// Logs the first occurrence and then at most once every [`WARN_EVERY`], with the count of
/// those not logged.
#[derive(Default)]
struct Warning {
    last: Option<Instant>,
    skipped: u64,
}

impl Warning {
    fn warn(&mut self, log: impl FnOnce(u64)) {
        let now = Instant::now();
        if self.last.is_some_and(|last| now < last + WARN_EVERY) {
            self.skipped += 1;
            return;
        }
        log(self.skipped);
        self.last = Some(now);
        self.skipped = 0;
    }
}

/// The open connections, oldest (lowest id) first.
#[derive(Default)]
struct Registry {
    open: Mutex<BTreeMap<u64, Arc<Tracker>>>,
}

impl Registry {
    fn insert(&self, id: u64, tracker: Arc<Tracker>) {
        self.lock().insert(id, tracker);
    }

    fn remove(&self, id: u64) {
        self.lock().remove(&id);
    }

    fn len(&self) -> usize {
        self.lock().len()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<Tracker>>> {
        // A panic while holding this lock leaves the map whole (each change is one call).
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether a new connection may open: under the cap (not counting those already told to
    /// close), or after telling the oldest one with no request in progress to close.
    fn make_room(&self, max: usize) -> bool {
        let open = self.lock();
        if open.len() < max {
            return true;
        }
        let closing = open.values().filter(|t| t.evicted()).count();
        if open.len() - closing < max {
            return true;
        }
        match open.values().find(|t| !t.evicted() && !t.busy()) {
            Some(oldest) => {
                oldest.evict();
                true
            }
            None => false,
        }
    }

    /// Tells the oldest connection with no request in progress to close; whether there was one.
    fn evict_oldest_idle(&self) -> bool {
        let open = self.lock();
        match open.values().find(|t| !t.evicted() && !t.busy()) {
            Some(oldest) => {
                oldest.evict();
                true
            }
            None => false,
        }
    }
}

/// One connection's state, shared by its reads, its requests and the accept loop.
struct Tracker {
    epoch: Instant,
    /// Requests whose response has not ended (a telemetry stream lasts).
    in_flight: AtomicU32,
    /// Bytes of a request have arrived since the connection went idle.
    reading_head: AtomicBool,
    /// When the connection went idle or the head's first byte came, ns after `epoch`.
    since_ns: AtomicU64,
    /// The accept loop wants it closed for a new connection.
    evict: AtomicBool,
    /// Wakes the connection's task to look at the above again.
    wake: Notify,
}

impl Tracker {
    /// A connection accepted `now`, idle since then; `epoch` is the server's.
    fn new(epoch: Instant, now: Instant) -> Tracker {
        let tracker = Tracker {
            epoch,
            in_flight: AtomicU32::new(0),
            reading_head: AtomicBool::new(false),
            since_ns: AtomicU64::new(0),
            evict: AtomicBool::new(false),
            wake: Notify::new(),
        };
        tracker.mark_since(now);
        tracker
    }

    fn mark_since(&self, now: Instant) {
        let ns = now.saturating_duration_since(self.epoch).as_nanos();
        self.since_ns
            .store(u64::try_from(ns).unwrap_or(u64::MAX), Ordering::SeqCst);
    }

    fn busy(&self) -> bool {
        self.in_flight.load(Ordering::SeqCst) > 0
    }

    fn evicted(&self) -> bool {
        self.evict.load(Ordering::SeqCst)
    }

    fn evict(&self) {
        self.evict.store(true, Ordering::SeqCst);
        self.wake.notify_one();
    }

    /// Bytes came in `now`: the first while idle starts the head's clock.
    fn bytes_arrived(&self, now: Instant) {
        if !self.busy() && !self.reading_head.load(Ordering::SeqCst) {
            self.mark_since(now);
            self.reading_head.store(true, Ordering::SeqCst);
            self.wake.notify_one();
        }
    }

    fn request_started(self: &Arc<Self>) -> InFlight {
        self.in_flight.fetch_add(1, Ordering::SeqCst);
        self.reading_head.store(false, Ordering::SeqCst);
        InFlight(self.clone())
    }

    /// When the connection must close unless something changes; none while a request is in
    /// progress.
    fn deadline(&self, limits: &ConnectionLimits) -> Option<Instant> {
        if self.busy() {
            return None;
        }
        let reading = self.reading_head.load(Ordering::SeqCst);
        let since = self.epoch + Duration::from_nanos(self.since_ns.load(Ordering::SeqCst));
        Some(
            since
                + if reading {
                    limits.header_timeout
                } else {
                    limits.idle_timeout
                },
        )
    }
}

/// A request in progress: from the handler's call to the end (or drop) of its response body.
struct InFlight(Arc<Tracker>);

impl Drop for InFlight {
    fn drop(&mut self) {
        let tracker = &self.0;
        if tracker.in_flight.fetch_sub(1, Ordering::SeqCst) == 1 {
            tracker.reading_head.store(false, Ordering::SeqCst);
            tracker.mark_since(Instant::now());
            tracker.wake.notify_one();
        }
    }
}

/// A response body that keeps its request in progress while it lives.
struct Tracked {
    body: axum::body::Body,
    _in_flight: InFlight,
}

impl Body for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

/// The socket, telling the tracker when bytes arrive.
struct Watched {
    stream: TcpStream,
    tracker: Arc<Tracker>,
}

impl AsyncRead for Watched {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let poll = Pin::new(&mut this.stream).poll_read(cx, buf);
        if matches!(poll, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            this.tracker.bytes_arrived(Instant::now());
        }
        poll
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_shutdown(cx)
    }
}

/// One connection's task; leaves the registry however it ends.
struct Connection {
    id: u64,
    registry: Arc<Registry>,
    _open: watch::Receiver<()>,
}

impl Drop for Connection {
    fn drop(&mut self) {
        self.registry.remove(self.id);
    }
}

impl Connection {
    async fn run(
        self,
        stream: TcpStream,
        remote: SocketAddr,
        tracker: Arc<Tracker>,
        router: TowerToHyperService<Router>,
        limits: ConnectionLimits,
        mut shutdown: watch::Receiver<bool>,
    ) {
        let requests = tracker.clone();
        let service = hyper::service::service_fn(move |mut request: hyper::Request<Incoming>| {
            request.extensions_mut().insert(ConnectInfo(remote));
            let in_flight = requests.request_started();
            let call = hyper::service::Service::call(&router, request);
            async move {
                let response = call.await?;
                Ok::<_, std::convert::Infallible>(response.map(|body| Tracked {
                    body,
                    _in_flight: in_flight,
                }))
            }
        });
        let io = TokioIo::new(Watched {
            stream,
            tracker: tracker.clone(),
        });
        let mut builder = http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .keep_alive(true)
            .header_read_timeout(limits.idle_timeout + limits.header_timeout);
        let connection = builder.serve_connection(io, service);
        tokio::pin!(connection);
        let mut stopping = false;
        loop {
            let deadline = tracker.deadline(&limits);
            tokio::select! {
                result = connection.as_mut() => {
                    if let Err(e) = result {
                        tracing::debug!(%remote, error = %e, "connection ended");
                    }
                    return;
                }
                _ = shutdown.wait_for(|stop| *stop), if !stopping => {
                    stopping = true;
                    if !tracker.busy() {
                        return;
                    }
                    // Ends once the request in progress has its answer.
                    connection.as_mut().graceful_shutdown();
                }
                _ = tracker.wake.notified() => {
                    if (stopping || tracker.evicted()) && !tracker.busy() {
                        tracing::debug!(%remote, "idle connection closed for a new one");
                        return;
                    }
                }
                _ = tokio::time::sleep_until(deadline.unwrap_or_else(Instant::now)),
                    if deadline.is_some() =>
                {
                    if tracker.deadline(&limits).is_some_and(|d| Instant::now() >= d) {
                        tracing::debug!(%remote, "connection closed: no request in time");
                        return;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
