//! The connection clock, the cap's choice, `ConnectInfo` and the descriptor check.

use super::*;

fn limits() -> ConnectionLimits {
    ConnectionLimits {
        max_connections: 2,
        header_timeout: Duration::from_secs(1),
        idle_timeout: Duration::from_secs(10),
    }
}

#[test]
fn the_clock_is_the_idle_one_until_a_byte_then_the_heads_then_none() {
    let epoch = Instant::now();
    let at = |s: f64| epoch + Duration::from_secs_f64(s);
    let limits = limits();
    let tracker = Arc::new(Tracker::new(epoch, at(1.0)));
    assert_eq!(
        tracker.deadline(&limits),
        Some(at(11.0)),
        "idle from the accept"
    );
    tracker.bytes_arrived(at(4.0));
    assert_eq!(tracker.deadline(&limits), Some(at(5.0)), "1 s for the head");
    tracker.bytes_arrived(at(4.5));
    assert_eq!(
        tracker.deadline(&limits),
        Some(at(5.0)),
        "later bytes of the head do not restart its clock"
    );
    let request = tracker.request_started();
    assert_eq!(tracker.deadline(&limits), None);
    tracker.bytes_arrived(at(100.0)); // the body's
    assert_eq!(tracker.deadline(&limits), None);
    let before = Instant::now();
    drop(request);
    let deadline = tracker.deadline(&limits).unwrap();
    assert!(
        deadline >= before + limits.idle_timeout
            && deadline <= Instant::now() + limits.idle_timeout,
        "idle again from the answer's end"
    );
}

#[tokio::test]
async fn each_request_carries_its_peer_address_and_shutdown_ends_the_server() {
    use axum::routing::get;
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap();
    let router = Router::new().route(
        "/",
        get(|ConnectInfo(peer): ConnectInfo<SocketAddr>| async move { peer.to_string() }),
    );
    let (stop, shutdown) = watch::channel(false);
    let server = tokio::spawn(serve(listener, router, limits(), shutdown).unwrap());
    let (local, answer) = tokio::task::spawn_blocking(move || {
        use std::io::{Read, Write};
        let mut stream = std::net::TcpStream::connect(address).unwrap();
        let local = stream.local_addr().unwrap();
        stream
            .write_all(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            .unwrap();
        let mut answer = String::new();
        stream.read_to_string(&mut answer).unwrap();
        (local, answer)
    })
    .await
    .unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(answer.ends_with(&format!("\r\n\r\n{local}")), "{answer}");
    stop.send(true).unwrap();
    server.await.unwrap();
}

#[tokio::test]
async fn a_cap_that_leaves_too_few_descriptors_is_refused_with_the_numbers() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (limit, _) = raise_fd_limit().unwrap();
    let too_many = usize::try_from(limit).unwrap_or(usize::MAX);
    let (_stop, shutdown) = watch::channel(false);
    let limits = ConnectionLimits {
        max_connections: too_many,
        ..limits()
    };
    let Err(error) = serve(listener, Router::new(), limits, shutdown) else {
        panic!("a cap of {too_many} accepted with a limit of {limit}");
    };
    let error = error.to_string();
    assert!(
        error.contains(&too_many.to_string())
            && error.contains(&limit.saturating_sub(RESERVED_FDS).to_string()),
        "{error}"
    );
}

#[tokio::test]
async fn at_the_cap_the_oldest_connection_without_a_request_makes_room() {
    let registry = Registry::default();
    let epoch = Instant::now();
    let trackers: Vec<_> = (0..3)
        .map(|_| Arc::new(Tracker::new(epoch, epoch)))
        .collect();
    let streaming = trackers[0].request_started();
    registry.insert(1, trackers[0].clone());
    assert!(registry.make_room(2));
    registry.insert(2, trackers[1].clone());
    // Full: 1 streams, so 2 (idle) is told to close.
    assert!(registry.make_room(2));
    assert!(!trackers[0].evicted() && trackers[1].evicted());
    // 2 has not closed yet, but it no longer counts.
    registry.insert(3, trackers[2].clone());
    let busy = trackers[2].request_started();
    registry.remove(2);
    // Full with two requests in progress: nothing to close, the new one is refused.
    assert!(!registry.make_room(2));
    assert!(!registry.evict_oldest_idle());
    drop(streaming);
    assert!(registry.make_room(2));
    assert!(trackers[0].evicted() && !trackers[2].evicted());
    drop(busy);
}
