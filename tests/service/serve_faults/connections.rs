//! Connections: a flood of idle and slow clients cannot keep a new one (an operator's e-stop)
//! out, idle and slow ones are closed after their timeouts, and a request in progress (a
//! telemetry stream) is neither evicted nor timed out.

use super::serve_support::Server;
use serde_json::Value;
use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

fn address(server: &Server) -> String {
    server.base.trim_start_matches("http://").to_string()
}

/// One request on a connection of its own (`Connection: close`): status and JSON body.
fn request(address: &str, method: &str, path: &str, token: Option<&str>) -> (u16, Value) {
    let mut stream = TcpStream::connect(address).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Content-Length: 0\r\n\
         Connection: close\r\n\r\n"
    )
    .unwrap();
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).expect("an answer");
    parse(&String::from_utf8_lossy(&answer))
}

fn parse(answer: &str) -> (u16, Value) {
    let status = answer
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let body = answer.split("\r\n\r\n").nth(1).unwrap_or_default();
    (
        status,
        serde_json::from_str(body).unwrap_or(Value::String(body.into())),
    )
}

/// Reads one response with a `Content-Length` and leaves the connection open.
fn read_response(stream: &mut TcpStream) -> (u16, Value) {
    let mut received = Vec::new();
    let mut byte = [0u8; 1];
    while !received.ends_with(b"\r\n\r\n") {
        assert_eq!(stream.read(&mut byte).expect("a response head"), 1);
        received.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&received).to_string();
    let length: usize = head
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase()
                .strip_prefix("content-length:")
                .map(|v| v.trim().parse().unwrap())
        })
        .expect("a Content-Length");
    let mut body = vec![0u8; length];
    stream.read_exact(&mut body).unwrap();
    parse(&format!("{head}{}", String::from_utf8_lossy(&body)))
}

/// Whether the server has closed `stream` (what it sent is read and dropped).
fn closed(stream: &mut TcpStream) -> bool {
    stream.set_nonblocking(true).unwrap();
    let mut buffer = [0u8; 4096];
    let closed = loop {
        match stream.read(&mut buffer) {
            Ok(0) => break true,
            Ok(_) => continue,
            Err(e) if e.kind() == ErrorKind::WouldBlock => break false,
            Err(_) => break true,
        }
    };
    stream.set_nonblocking(false).unwrap();
    closed
}

/// A telemetry subscription on a raw connection.
struct Telemetry {
    stream: TcpStream,
    seen: String,
}

impl Telemetry {
    fn open(address: &str, token: &str) -> Telemetry {
        let mut stream = TcpStream::connect(address).unwrap();
        write!(
            stream,
            "GET /api/telemetry?access_token={token} HTTP/1.1\r\nHost: {address}\r\n\r\n"
        )
        .unwrap();
        let mut telemetry = Telemetry {
            stream,
            seen: String::new(),
        };
        telemetry.wait_for("event: cell");
        telemetry
    }

    /// Reads until `needle` has come (fails if the stream ends or 20 s pass first; the
    /// stream's keep-alive comments do not count).
    fn wait_for(&mut self, needle: &str) {
        let mut buffer = [0u8; 4096];
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(at) = self.seen.find(needle) {
                // What came after it is kept for the next wait.
                self.seen.drain(..at + needle.len());
                return;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            assert!(!left.is_zero(), "no `{needle}` in 20 s: {}", self.seen);
            self.stream.set_read_timeout(Some(left)).unwrap();
            let n = self.stream.read(&mut buffer).unwrap_or_else(|e| {
                panic!("telemetry: {e} before `{needle}`; so far: {}", self.seen)
            });
            assert!(n > 0, "telemetry ended before `{needle}`: {}", self.seen);
            self.seen.push_str(&String::from_utf8_lossy(&buffer[..n]));
        }
    }
}

/// A client that sends its request head a little at a time (its first line, then one byte of
/// a header line every `every`) and never finishes it; it notes when the server closes it.
struct Slowloris {
    stop: Arc<AtomicBool>,
    thread: JoinHandle<Option<Duration>>,
}

impl Slowloris {
    fn start(address: &str, every: Duration) -> Slowloris {
        let mut stream = TcpStream::connect(address).unwrap();
        stream.set_read_timeout(Some(every)).unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let halt = stop.clone();
        let head = format!("GET /api/health HTTP/1.1\r\nHost: {address}\r\nX-Slow: ");
        let thread = std::thread::spawn(move || {
            let start = Instant::now();
            let mut write = stream.write_all(head.as_bytes());
            let mut buffer = [0u8; 1024];
            while !halt.load(Ordering::Relaxed) {
                if write.is_err() {
                    return Some(start.elapsed());
                }
                match stream.read(&mut buffer) {
                    Ok(0) => return Some(start.elapsed()),
                    Ok(_) => {}
                    Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                    Err(_) => return Some(start.elapsed()),
                }
                write = stream.write_all(b"a");
            }
            None
        });
        Slowloris { stop, thread }
    }

    /// How long after its first bytes the server closed it; none if still open now.
    fn finish(self) -> Option<Duration> {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap()
    }
}

/// Polls `streams` until `enough` holds for when each was closed (after `start`; none for
/// those still open), or `limit` has passed since `start`.
fn wait_closed(
    streams: &mut [TcpStream],
    start: Instant,
    limit: Duration,
    enough: impl Fn(&[Option<Duration>]) -> bool,
) -> Vec<Option<Duration>> {
    let mut closed_at = vec![None; streams.len()];
    loop {
        for (stream, at) in streams.iter_mut().zip(closed_at.iter_mut()) {
            if at.is_none() && closed(stream) {
                *at = Some(start.elapsed());
            }
        }
        if enough(&closed_at) || start.elapsed() >= limit {
            return closed_at;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn open(closed_at: &[Option<Duration>]) -> usize {
    closed_at.iter().filter(|c| c.is_none()).count()
}

#[test]
fn a_flood_of_idle_and_slow_clients_cannot_keep_out_a_new_one() {
    let dir = tempfile::tempdir().unwrap();
    // Timeouts far away: only eviction can make room here.
    let mut server = Server::start(
        dir.path(),
        &[
            ("CELLD_MAX_CONNECTIONS", "64"),
            ("CELLD_IDLE_TIMEOUT_S", "600"),
            ("CELLD_HEADER_TIMEOUT_MS", "600000"),
        ],
    );
    let operator = server.token("operator");
    let address = address(&server);
    // The oldest connection of all, with a request in progress.
    let mut telemetry = Telemetry::open(&address, &server.admin);

    let slow: Vec<Slowloris> = (0..10)
        .map(|_| Slowloris::start(&address, Duration::from_secs(1)))
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let mut idle: Vec<TcpStream> = (0..200)
        .map(|_| TcpStream::connect(&address).expect("connect"))
        .collect();

    let (status, health) = request(&address, "GET", "/api/health", None);
    assert_eq!(status, 200, "{health}");
    let (status, cell) = request(&address, "POST", "/api/cell/estop", Some(&operator));
    assert_eq!(
        (status, &cell["estop_latched"]),
        (200, &Value::Bool(true)),
        "{cell}"
    );
    let (status, cell) = request(&address, "POST", "/api/cell/reset", Some(&operator));
    assert_eq!(
        (status, &cell["estop_latched"]),
        (200, &Value::Bool(false)),
        "{cell}"
    );

    // The stream saw both: it was not evicted, though it is the oldest.
    telemetry.wait_for("\"estop_latched\":true");
    telemetry.wait_for("\"estop_latched\":false");

    // The flood is cut to the cap, oldest first: every slow client, then the oldest idle ones.
    let closed_at = wait_closed(&mut idle, Instant::now(), Duration::from_secs(30), |c| {
        open(c) <= 64
    });
    let still_open = open(&closed_at);
    assert!(
        (1..=64).contains(&still_open),
        "{still_open} of 200 idle connections open with a cap of 64"
    );
    let last_closed = closed_at
        .iter()
        .rposition(Option::is_some)
        .expect("some closed");
    let first_open = closed_at
        .iter()
        .position(Option::is_none)
        .expect("some open");
    assert!(
        last_closed < first_open,
        "the oldest idle connections go first: #{last_closed} closed, #{first_open} open"
    );
    for (i, slowloris) in slow.into_iter().enumerate() {
        assert!(
            slowloris.finish().is_some(),
            "slow client #{i}, older than every idle one, is still open"
        );
    }

    // SIGTERM with a stream and a full house open: the stream ends, the process exits.
    let (status, _) = server.terminate(Duration::from_secs(10));
    assert!(status.success(), "{status}");
    let mut rest = Vec::new();
    telemetry
        .stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let _ = telemetry.stream.read_to_end(&mut rest);
}

#[test]
fn idle_and_slow_connections_are_closed_after_their_timeouts_and_streams_are_not() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_IDLE_TIMEOUT_S", "6"),
            ("CELLD_HEADER_TIMEOUT_MS", "1500"),
        ],
    );
    let operator = server.token("operator");
    let address = address(&server);
    let mut telemetry = Telemetry::open(&address, &server.admin);

    let start = Instant::now();
    let silent = TcpStream::connect(&address).unwrap();
    let mut kept = TcpStream::connect(&address).unwrap();
    kept.set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    write!(kept, "GET /api/health HTTP/1.1\r\nHost: {address}\r\n\r\n").unwrap();
    let (status, health) = read_response(&mut kept);
    assert_eq!(status, 200, "{health}");
    let answered = start.elapsed();
    // A byte every 300 ms: each one is news, but the head's clock runs from the first.
    let slowloris = Slowloris::start(&address, Duration::from_millis(300));

    let mut streams = [silent, kept];
    let closed_at = wait_closed(&mut streams, start, Duration::from_secs(30), |c| {
        open(c) == 0
    });
    let slow_closed = slowloris.finish().expect("the slow client is closed");
    assert!(
        slow_closed >= Duration::from_secs(1) && slow_closed <= Duration::from_millis(4500),
        "a head still incomplete 1.5 s after its first byte closes then, not after the 6 s \
         idle timeout: closed after {slow_closed:?}"
    );
    let silent_closed = closed_at[0].expect("the silent connection is closed");
    assert!(
        silent_closed >= Duration::from_secs(5) && silent_closed <= Duration::from_secs(20),
        "a connection that never sends a byte closes after the 6 s idle timeout: {silent_closed:?}"
    );
    let kept_idle = closed_at[1].expect("the kept-alive connection is closed") - answered;
    assert!(
        kept_idle >= Duration::from_secs(5) && kept_idle <= Duration::from_secs(20),
        "a kept-alive connection closes 6 s after its last answer: {kept_idle:?}"
    );

    // The stream, open all along, is not idle: it still delivers.
    assert!(
        !closed(&mut telemetry.stream),
        "the telemetry stream was closed"
    );
    let (status, cell) = request(&address, "POST", "/api/cell/estop", Some(&operator));
    assert_eq!(status, 200, "{cell}");
    telemetry.wait_for("\"estop_latched\":true");
    let (status, cell) = request(&address, "POST", "/api/cell/reset", Some(&operator));
    assert_eq!(status, 200, "{cell}");
}
