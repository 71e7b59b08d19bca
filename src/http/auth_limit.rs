//! Failed authentication, limited per client address: after `access.auth_failure_limit`
//! refused tokens within `access.auth_failure_window_s` from one address, every request from
//! it that presents a token is answered 429 with `Retry-After`, without looking at the token,
//! until that window ends. A good token from a limited address is refused as well: checking
//! it would tell a guesser which guess was right. Successes neither count nor clear the count;
//! requests without a token (401 without a guess) are not counted.
//!
//! The address is the peer's IP (`ConnectInfo<SocketAddr>`, any port); a request without one
//! (a router served without connection info) counts in one shared bucket. The table holds at
//! most `access.auth_failure_addresses` addresses: when full, windows that ended go first,
//! then the oldest.

use super::error::ApiError;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One address's failures in its current window.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Window {
    started: Instant,
    failures: u32,
}

/// The failures per address (none: unknown). Pure: every call takes `now`.
#[derive(Debug)]
pub struct FailureTable {
    limit: u32,
    window: Duration,
    capacity: usize,
    windows: HashMap<Option<IpAddr>, Window>,
}

impl FailureTable {
    /// `limit` failures (≥ 1) per `window` per address; at most `capacity` (≥ 1) addresses.
    pub fn new(limit: u32, window: Duration, capacity: usize) -> Self {
        FailureTable {
            limit: limit.max(1),
            window,
            capacity: capacity.max(1),
            windows: HashMap::new(),
        }
    }

    /// How long until `address` may try again, when it is limited now.
    pub fn limited(&self, address: Option<IpAddr>, now: Instant) -> Option<Duration> {
        let window = self.windows.get(&address)?;
        let ends = window.started + self.window;
        (window.failures >= self.limit && now < ends).then(|| ends - now)
    }

    /// Counts a refused token from `address`.
    pub fn fail(&mut self, address: Option<IpAddr>, now: Instant) {
        let period = self.window;
        if let Some(window) = self.windows.get_mut(&address) {
            if now >= window.started + period {
                *window = Window {
                    started: now,
                    failures: 1,
                };
            } else {
                window.failures = window.failures.saturating_add(1);
            }
            return;
        }
        if self.windows.len() >= self.capacity {
            self.windows.retain(|_, w| now < w.started + period);
        }
        if self.windows.len() >= self.capacity
            && let Some(oldest) = self
                .windows
                .iter()
                .min_by_key(|(_, w)| w.started)
                .map(|(address, _)| *address)
        {
            self.windows.remove(&oldest);
        }
        self.windows.insert(
            address,
            Window {
                started: now,
                failures: 1,
            },
        );
    }

    /// Addresses held.
    pub fn len(&self) -> usize {
        self.windows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.windows.is_empty()
    }
}

/// The table shared by every request of a router.
pub type Limiter = Arc<Mutex<FailureTable>>;

/// Whether the request presents a token (a bearer header or `?access_token=`), right or wrong.
fn presents_token(request: &Request) -> bool {
    request.headers().contains_key(header::AUTHORIZATION)
        || request.uri().query().is_some_and(|query| {
            query
                .split('&')
                .any(|pair| pair.starts_with("access_token="))
        })
}

/// The middleware: 429 for a limited address that presents a token; a 401 to a request that
/// presented one is counted.
pub async fn limit(State(limiter): State<Limiter>, request: Request, next: Next) -> Response {
    if !presents_token(&request) {
        return next.run(request).await;
    }
    let address = request
        .extensions()
        .get::<ConnectInfo<SocketAddr>>()
        .map(|ConnectInfo(peer)| peer.ip());
    let wait = limiter
        .lock()
        .ok()
        .and_then(|table| table.limited(address, Instant::now()));
    if let Some(wait) = wait {
        // Whole seconds, rounded up: never an invitation to retry early.
        let seconds = wait.as_millis().div_ceil(1000).max(1);
        let mut response = ApiError::new(
            StatusCode::TOO_MANY_REQUESTS,
            "too_many_requests",
            format!(
                "too many refused tokens from this address: try again in {seconds} s \
                 (no token is checked until then)"
            ),
        )
        .into_response();
        if let Ok(value) = HeaderValue::from_str(&seconds.to_string()) {
            response.headers_mut().insert(header::RETRY_AFTER, value);
        }
        return response;
    }
    let response = next.run(request).await;
    if response.status() == StatusCode::UNAUTHORIZED
        && let Ok(mut table) = limiter.lock()
    {
        table.fail(address, Instant::now());
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(last: u8) -> Option<IpAddr> {
        Some(IpAddr::from([10, 0, 0, last]))
    }

    #[test]
    fn an_address_is_limited_after_its_failures_until_its_window_ends() {
        let start = Instant::now();
        let mut table = FailureTable::new(3, Duration::from_secs(60), 100);
        for _ in 0..2 {
            table.fail(ip(1), start);
        }
        assert_eq!(table.limited(ip(1), start), None, "two of three");
        table.fail(ip(1), start + Duration::from_secs(10));
        let at = start + Duration::from_secs(15);
        assert_eq!(table.limited(ip(1), at), Some(Duration::from_secs(45)));
        assert_eq!(table.limited(ip(2), at), None, "another address is not");
        assert_eq!(table.limited(None, at), None);
        // The window began with the first failure: it ends 60 s after it.
        let ended = start + Duration::from_secs(60);
        assert_eq!(table.limited(ip(1), ended), None);
        // A failure after it starts a new window with a count of one.
        table.fail(ip(1), ended);
        assert_eq!(table.limited(ip(1), ended), None);
    }

    #[test]
    fn the_table_keeps_at_most_its_capacity_dropping_ended_windows_then_the_oldest() {
        let start = Instant::now();
        let second = Duration::from_secs(1);
        let mut table = FailureTable::new(1, Duration::from_secs(60), 3);
        for last in 1..=3 {
            table.fail(ip(last), start + second * u32::from(last));
        }
        assert_eq!(table.len(), 3);
        // Full, none ended: the oldest (10.0.0.1) goes.
        table.fail(ip(4), start + second * 4);
        assert_eq!(table.len(), 3);
        let now = start + second * 5;
        assert_eq!(table.limited(ip(1), now), None);
        assert!(table.limited(ip(2), now).is_some() && table.limited(ip(4), now).is_some());
        // Much later every window has ended: all of them make room at once.
        let later = start + Duration::from_secs(600);
        table.fail(ip(5), later);
        assert_eq!(table.len(), 1);
        assert!(table.limited(ip(5), later).is_some());
        for round in 0..10_000u32 {
            let address = Some(IpAddr::from(round.to_be_bytes()));
            table.fail(address, later);
        }
        assert_eq!(table.len(), 3);
    }
}
