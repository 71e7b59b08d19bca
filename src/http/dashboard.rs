//! The operator dashboard: the files of `static/`, built into the binary so that `celld serve`
//! needs nothing beside it (and no build step: plain HTML, CSS and JavaScript). The page signs
//! in with a token and calls the same API as everyone else.

use super::Context;
use axum::Router;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use rust_embed::RustEmbed;

/// The files of `static/`, embedded at build time (also in debug builds).
#[derive(RustEmbed)]
#[folder = "static/"]
struct Assets;

/// Scripts, styles and requests only from this server; no framing (clickjacking on the
/// e-stop and reset buttons).
const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; img-src 'self' data: blob:; \
     object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'";

/// A route for each file of `static/` at its own path (`index.html` also at `/`), with its
/// content type; `static/README.md` describes the folder and is not served.
pub fn router() -> Router<Context> {
    Assets::iter()
        .filter(|path| path != "README.md")
        .fold(Router::new(), |router, path| {
            let file = Assets::get(&path).expect("an embedded file is there");
            let content_type = match file.metadata.mimetype() {
                text if text.starts_with("text/") || text.ends_with("javascript") => {
                    format!("{text}; charset=utf-8")
                }
                other => other.to_string(),
            };
            let bytes = file.data;
            let serve = get(move || async move {
                (
                    [
                        (header::CONTENT_TYPE, content_type.as_str()),
                        (header::CACHE_CONTROL, "no-cache"),
                        (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
                        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
                        (header::REFERRER_POLICY, "no-referrer"),
                    ],
                    bytes.clone(),
                )
                    .into_response()
            });
            let router = router.route(&format!("/{path}"), serve.clone());
            if path == "index.html" {
                router.route("/", serve)
            } else {
                router
            }
        })
}

#[cfg(test)]
mod tests {
    use super::Assets;

    /// Every file of `static/` (but its README) is embedded, read back byte for byte.
    #[test]
    fn every_dashboard_file_is_embedded_as_it_is_on_disk() {
        let folder = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("static");
        let mut on_disk = Vec::new();
        let mut stack = vec![folder.clone()];
        while let Some(dir) = stack.pop() {
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if path.is_dir() {
                    stack.push(path);
                } else {
                    on_disk.push(path);
                }
            }
        }
        assert!(on_disk.len() >= 12, "{on_disk:?}");
        for path in on_disk {
            let name = path.strip_prefix(&folder).unwrap().to_str().unwrap();
            let embedded = Assets::get(name).unwrap_or_else(|| panic!("{name} is not embedded"));
            assert_eq!(*embedded.data, std::fs::read(&path).unwrap()[..], "{name}");
        }
    }
}
