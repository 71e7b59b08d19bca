//! The operator dashboard: the files of `static/`, built into the binary so that `celld serve`
//! needs nothing beside it (and no build step: plain HTML, CSS and JavaScript). The page signs
//! in with a token and calls the same API as everyone else.

use super::Context;
use axum::Router;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;

/// Served path, content type, bytes.
const FILES: &[(&str, &str, &[u8])] = &[
    (
        "/",
        "text/html; charset=utf-8",
        include_bytes!("../../static/index.html"),
    ),
    (
        "/app.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/app.js"),
    ),
    (
        "/lib.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/lib.js"),
    ),
    (
        "/charts.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/charts.js"),
    ),
    (
        "/live.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/live.js"),
    ),
    (
        "/jobs.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/jobs.js"),
    ),
    (
        "/policies.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/policies.js"),
    ),
    (
        "/demonstrations.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/demonstrations.js"),
    ),
    (
        "/training.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/training.js"),
    ),
    (
        "/style.css",
        "text/css; charset=utf-8",
        include_bytes!("../../static/style.css"),
    ),
    (
        "/vendor/chart.umd.min.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../static/vendor/chart.umd.min.js"),
    ),
    (
        "/vendor/chart.js-LICENSE.md",
        "text/markdown; charset=utf-8",
        include_bytes!("../../static/vendor/chart.js-LICENSE.md"),
    ),
];

/// Scripts, styles and requests only from this server; no framing (clickjacking on the
/// e-stop and reset buttons).
const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; img-src 'self' data: blob:; \
     object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'";

pub fn router() -> Router<Context> {
    FILES
        .iter()
        .fold(Router::new(), |router, &(path, content_type, bytes)| {
            router.route(
                path,
                get(move || async move {
                    (
                        [
                            (header::CONTENT_TYPE, content_type),
                            (header::CACHE_CONTROL, "no-cache"),
                            (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
                            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
                            (header::REFERRER_POLICY, "no-referrer"),
                        ],
                        bytes,
                    )
                        .into_response()
                }),
            )
        })
}
