//! A headless Chromium driven through `chromedriver` with a small W3C WebDriver client.
//!
//! `Browser::start()` gives `None` only when `chromedriver` is not installed (Debian's `chromium`
//! and `chromium-driver` packages; `.ci/run` installs them); any other failure panics with the
//! WebDriver error and the failing selector, URL or script.
#![allow(dead_code)]

use serde_json::{Value, json};
use std::cell::RefCell;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The W3C key under which an element reference travels in JSON.
pub const ELEMENT_KEY: &str = "element-6066-11e4-a52e-4f735466cecf";

/// Where `wait_until` saves a screenshot on timeout when nothing else was set.
pub const SCREENSHOT_DIR_ENV: &str = "BROWSER_SCREENSHOT_DIR";

pub struct Browser {
    child: Child,
    /// `http://127.0.0.1:PORT`, chromedriver itself.
    driver: String,
    /// The session id; empty until the session exists.
    session: String,
    agent: ureq::Agent,
    /// Holds the Chromium profile and chromedriver's log; removed on drop.
    scratch: tempfile::TempDir,
    screenshot_dir: RefCell<Option<PathBuf>>,
}

/// An element of the current page, by its WebDriver reference.
pub struct Element<'a> {
    browser: &'a Browser,
    id: String,
    /// The selector it was found by, for messages.
    css: String,
}

/// A WebDriver error answer: its `error` code and `message`.
#[derive(Debug)]
pub struct WebDriverError {
    pub status: u16,
    pub error: String,
    pub message: String,
}

impl std::fmt::Display for WebDriverError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let message = self.message.lines().next().unwrap_or("");
        write!(f, "{} (HTTP {}): {}", self.error, self.status, message)
    }
}

fn find_in_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|candidate| candidate.is_file())
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|listener| listener.local_addr())
        .expect("bind 127.0.0.1:0 for a free port")
        .port()
}

fn agent(timeout: Duration) -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(timeout))
        .build()
        .into()
}

fn sanitise(what: &str) -> String {
    let mut name: String = what
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    while name.contains("--") {
        name = name.replace("--", "-");
    }
    let name = name.trim_matches('-');
    name.chars().take(80).collect()
}

impl Browser {
    /// Starts chromedriver and a headless Chromium session; `None` when chromedriver is not
    /// installed.
    pub fn start() -> Option<Browser> {
        let Some(chromedriver) = find_in_path("chromedriver") else {
            eprintln!(
                "browser tests: chromedriver is not installed \
                 (apt-get install chromium chromium-driver)"
            );
            return None;
        };
        let chromium =
            find_in_path("chromium").unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
        let scratch = tempfile::Builder::new()
            .prefix("browser-test-")
            .tempdir()
            .expect("create a temporary directory for the browser");
        let profile = scratch.path().join("profile");
        let log = scratch.path().join("chromedriver.log");
        let port = free_port();
        let child = Command::new(&chromedriver)
            .arg(format!("--port={port}"))
            .arg(format!("--log-path={}", log.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("start {}: {e}", chromedriver.display()));
        // From here on Drop kills chromedriver, also when a step below panics.
        let mut browser = Browser {
            child,
            driver: format!("http://127.0.0.1:{port}"),
            session: String::new(),
            agent: agent(Duration::from_secs(60)),
            scratch,
            screenshot_dir: RefCell::new(std::env::var_os(SCREENSHOT_DIR_ENV).map(PathBuf::from)),
        };
        browser.wait_ready(Duration::from_secs(20));
        let capabilities = json!({
            "capabilities": {
                "alwaysMatch": {
                    "browserName": "chrome",
                    "goog:chromeOptions": {
                        "binary": chromium.to_string_lossy(),
                        "args": [
                            "--headless",
                            "--no-sandbox",
                            "--disable-gpu",
                            "--no-first-run",
                            "--disable-background-networking",
                            "--disable-component-update",
                            "--disable-sync",
                            "--disable-dev-shm-usage",
                            "--window-size=1366,900",
                            format!("--user-data-dir={}", profile.display()),
                        ]
                    }
                }
            }
        });
        let url = format!("{}/session", browser.driver);
        let answer = browser.request("POST", &url, Some(capabilities));
        let value = answer.unwrap_or_else(|e| {
            panic!(
                "create a WebDriver session with {}: {e}\nchromedriver log tail:\n{}",
                chromium.display(),
                browser.log_tail()
            )
        });
        browser.session = value["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("no sessionId in the new-session answer: {value}"))
            .to_string();
        Some(browser)
    }

    fn wait_ready(&mut self, timeout: Duration) {
        let start = Instant::now();
        let url = format!("{}/status", self.driver);
        let quick = agent(Duration::from_secs(2));
        loop {
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!(
                    "chromedriver exited ({status}) before it was ready\nlog tail:\n{}",
                    self.log_tail()
                );
            }
            if let Ok(mut response) = quick.get(&url).call()
                && let Ok(body) = response.body_mut().read_json::<Value>()
                && body["value"]["ready"] == json!(true)
            {
                return;
            }
            if start.elapsed() > timeout {
                panic!(
                    "chromedriver at {url} not ready after {timeout:?}\nlog tail:\n{}",
                    self.log_tail()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(self.scratch.path().join("chromedriver.log"))
            .unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }

    /// One WebDriver request: the answer's `value`, or the WebDriver error.
    fn request(
        &self,
        method: &str,
        url: &str,
        body: Option<Value>,
    ) -> Result<Value, WebDriverError> {
        let response = match (method, body) {
            ("GET", _) => self.agent.get(url).call(),
            ("DELETE", _) => self.agent.delete(url).call(),
            ("POST", body) => self
                .agent
                .post(url)
                .send_json(body.unwrap_or_else(|| json!({}))),
            (other, _) => panic!("unsupported WebDriver method {other}"),
        };
        let mut response = response.map_err(|e| WebDriverError {
            status: 0,
            error: "transport".to_string(),
            message: format!("{method} {url}: {e}"),
        })?;
        let status = response.status().as_u16();
        let text = response
            .body_mut()
            .with_config()
            .limit(256 * 1024 * 1024)
            .read_to_string()
            .map_err(|e| WebDriverError {
                status,
                error: "transport".to_string(),
                message: format!("read the answer to {method} {url}: {e}"),
            })?;
        let answer: Value = serde_json::from_str(&text).map_err(|_| WebDriverError {
            status,
            error: "not JSON".to_string(),
            message: text.chars().take(500).collect(),
        })?;
        let value = answer.get("value").cloned().unwrap_or(Value::Null);
        if (200..300).contains(&status) {
            Ok(value)
        } else {
            Err(WebDriverError {
                status,
                error: value["error"]
                    .as_str()
                    .unwrap_or("unknown error")
                    .to_string(),
                message: value["message"].as_str().unwrap_or("").to_string(),
            })
        }
    }

    /// A session command, e.g. `("POST", "/url", ...)`.
    fn command(
        &self,
        method: &str,
        path: &str,
        body: Option<Value>,
    ) -> Result<Value, WebDriverError> {
        let url = format!("{}/session/{}{}", self.driver, self.session, path);
        self.request(method, &url, body)
    }

    /// The session's id (for raw WebDriver requests).
    pub fn session_id(&self) -> &str {
        &self.session
    }

    /// Sets (or with `None` unsets) where `wait_until` saves a screenshot on timeout. Starts as
    /// `$BROWSER_SCREENSHOT_DIR` when that is set.
    pub fn set_screenshot_dir(&self, dir: Option<&Path>) {
        *self.screenshot_dir.borrow_mut() = dir.map(Path::to_path_buf);
    }

    /// Navigates and waits for the page load.
    pub fn goto(&self, url: &str) {
        if let Err(e) = self.command("POST", "/url", Some(json!({ "url": url }))) {
            panic!("navigate to {url}: {e}");
        }
    }

    /// The current page's URL.
    pub fn current_url(&self) -> String {
        match self.command("GET", "/url", None) {
            Ok(value) => value.as_str().unwrap_or_default().to_string(),
            Err(e) => panic!("read the current URL: {e}"),
        }
    }

    fn url_for_message(&self) -> String {
        match self.command("GET", "/url", None) {
            Ok(Value::String(url)) => url.chars().take(200).collect(),
            _ => "an unknown page".to_string(),
        }
    }

    fn element(&self, value: &Value, css: &str) -> Element<'_> {
        let id = value[ELEMENT_KEY]
            .as_str()
            .unwrap_or_else(|| panic!("no element reference for {css:?} in {value}"));
        Element {
            browser: self,
            id: id.to_string(),
            css: css.to_string(),
        }
    }

    /// The first element matching `css`; panics when there is none.
    pub fn find(&self, css: &str) -> Element<'_> {
        let query = json!({ "using": "css selector", "value": css });
        match self.command("POST", "/element", Some(query)) {
            Ok(value) => self.element(&value, css),
            Err(e) => panic!("find {css:?} on {}: {e}", self.url_for_message()),
        }
    }

    /// All elements matching `css`, in document order.
    pub fn find_all(&self, css: &str) -> Vec<Element<'_>> {
        let query = json!({ "using": "css selector", "value": css });
        match self.command("POST", "/elements", Some(query)) {
            Ok(Value::Array(values)) => values.iter().map(|v| self.element(v, css)).collect(),
            Ok(other) => panic!("find all {css:?}: not a list: {other}"),
            Err(e) => panic!("find all {css:?}: {e}"),
        }
    }

    /// Whether some element matches `css`.
    pub fn exists(&self, css: &str) -> bool {
        !self.find_all(css).is_empty()
    }

    /// Runs `script` (a function body: `return ...`, `arguments[0]`, ...) and gives its result.
    pub fn execute(&self, script: &str, args: Vec<Value>) -> Value {
        let body = json!({ "script": script, "args": args });
        match self.command("POST", "/execute/sync", Some(body)) {
            Ok(value) => value,
            Err(e) => panic!("execute script {script:?}: {e}"),
        }
    }

    /// Picks the `<option>` with `value` in the `<select>` matching `css` and fires `input` and
    /// `change` as a user's pick would.
    pub fn select_value(&self, css: &str, value: &str) {
        let script = "const s = document.querySelector(arguments[0]);
            if (!s) return 'no such element';
            if (s.tagName !== 'SELECT') return 'not a <select> but a <' + s.tagName.toLowerCase() + '>';
            if (![...s.options].some(o => o.value === arguments[1])) return 'no such option';
            s.value = arguments[1];
            s.dispatchEvent(new Event('input', { bubbles: true }));
            s.dispatchEvent(new Event('change', { bubbles: true }));
            return 'ok';";
        let outcome = self.execute(script, vec![json!(css), json!(value)]);
        if outcome != json!("ok") {
            panic!("select value {value:?} in {css:?}: {outcome}");
        }
    }

    /// Polls `f` every 100 ms until it says true; on timeout saves a screenshot
    /// `timeout-<what>.png` into the screenshot directory (if one is set) and panics.
    pub fn wait_until(&self, what: &str, timeout: Duration, mut f: impl FnMut(&Browser) -> bool) {
        let start = Instant::now();
        loop {
            if f(self) {
                return;
            }
            if start.elapsed() > timeout {
                let dir = self.screenshot_dir.borrow().clone();
                let mut saved = String::new();
                if let Some(dir) = dir {
                    let path = dir.join(format!("timeout-{}.png", sanitise(what)));
                    if let Ok(png) = self.screenshot_png()
                        && std::fs::create_dir_all(&dir).is_ok()
                        && std::fs::write(&path, png).is_ok()
                    {
                        saved = format!(" (screenshot: {})", path.display());
                    }
                }
                panic!("timed out after {timeout:?} waiting until {what}{saved}");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn screenshot_png(&self) -> Result<Vec<u8>, String> {
        let value = self
            .command("GET", "/screenshot", None)
            .map_err(|e| e.to_string())?;
        let text = value
            .as_str()
            .ok_or_else(|| format!("not a string: {value}"))?;
        base64_decode(text)
    }

    /// Saves a PNG of the viewport at `path`, creating its parent directories.
    pub fn screenshot(&self, path: &Path) {
        let png = self
            .screenshot_png()
            .unwrap_or_else(|e| panic!("take a screenshot for {}: {e}", path.display()));
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .unwrap_or_else(|e| panic!("create {}: {e}", parent.display()));
        }
        std::fs::write(path, png).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    }

    /// Resizes the browser window (outer size, in CSS pixels).
    pub fn set_window_size(&self, width: u32, height: u32) {
        let rect = json!({ "width": width, "height": height });
        if let Err(e) = self.command("POST", "/window/rect", Some(rect)) {
            panic!("set the window size to {width}x{height}: {e}");
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let url = format!("{}/session/{}", self.driver, self.session);
            let _ = agent(Duration::from_secs(5)).delete(&url).call();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Element<'_> {
    fn command(
        &self,
        method: &str,
        what: &str,
        body: Option<Value>,
    ) -> Result<Value, WebDriverError> {
        let path = format!("/element/{}{}", self.id, what);
        self.browser.command(method, &path, body)
    }

    fn expect(&self, action: &str, answer: Result<Value, WebDriverError>) -> Value {
        answer.unwrap_or_else(|e| panic!("{action} {:?}: {e}", self.css))
    }

    /// The W3C element reference, to pass in `Browser::execute`'s `args`.
    pub fn as_arg(&self) -> Value {
        json!({ ELEMENT_KEY: self.id })
    }

    pub fn click(&self) {
        let answer = self.command("POST", "/click", Some(json!({})));
        self.expect("click", answer);
    }

    /// Types `text` at the end of the element's current value.
    pub fn send_keys(&self, text: &str) {
        let answer = self.command("POST", "/value", Some(json!({ "text": text })));
        self.expect("type into", answer);
    }

    pub fn clear(&self) {
        let answer = self.command("POST", "/clear", Some(json!({})));
        self.expect("clear", answer);
    }

    /// The rendered text (as a user sees it: hidden parts left out).
    pub fn text(&self) -> String {
        let answer = self.command("GET", "/text", None);
        self.expect("read the text of", answer)
            .as_str()
            .unwrap_or_default()
            .to_string()
    }

    /// The attribute `name`, or `None` when it is absent.
    pub fn attribute(&self, name: &str) -> Option<String> {
        let answer = self.command("GET", &format!("/attribute/{name}"), None);
        match self.expect(&format!("read attribute {name:?} of"), answer) {
            Value::Null => None,
            Value::String(s) => Some(s),
            other => Some(other.to_string()),
        }
    }

    /// The DOM property `name` (e.g. `value`, `checked`), as JSON.
    pub fn property(&self, name: &str) -> Value {
        let answer = self.command("GET", &format!("/property/{name}"), None);
        self.expect(&format!("read property {name:?} of"), answer)
    }

    pub fn is_displayed(&self) -> bool {
        let answer = self.command("GET", "/displayed", None);
        self.expect("check whether displayed:", answer) == json!(true)
    }
}

/// Standard base64 (with or without `=` padding; whitespace ignored).
pub fn base64_decode(text: &str) -> Result<Vec<u8>, String> {
    fn sextet(c: u8) -> Option<u32> {
        match c {
            b'A'..=b'Z' => Some((c - b'A') as u32),
            b'a'..=b'z' => Some((c - b'a') as u32 + 26),
            b'0'..=b'9' => Some((c - b'0') as u32 + 52),
            b'+' => Some(62),
            b'/' => Some(63),
            _ => None,
        }
    }
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let (mut bits, mut count) = (0u32, 0u32);
    for (i, c) in text.bytes().enumerate() {
        if c.is_ascii_whitespace() {
            continue;
        }
        if c == b'=' {
            break;
        }
        let v = sextet(c).ok_or_else(|| format!("not base64: byte {c:#04x} at {i}"))?;
        bits = (bits << 6) | v;
        count += 6;
        if count >= 8 {
            count -= 8;
            out.push((bits >> count) as u8);
            bits &= (1 << count) - 1;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_known_vectors() {
        assert_eq!(base64_decode("TWFu").unwrap(), b"Man");
        assert_eq!(base64_decode("TWE=").unwrap(), b"Ma");
        assert_eq!(base64_decode("TQ==").unwrap(), b"M");
        assert_eq!(base64_decode("").unwrap(), b"");
        assert_eq!(
            base64_decode("iVBORw0K\nGgo=").unwrap(),
            b"\x89PNG\r\n\x1a\n"
        );
        assert_eq!(base64_decode("+/+/").unwrap(), [0xfb, 0xff, 0xbf]);
        assert!(base64_decode("TW*u").is_err());
    }

    #[test]
    fn screenshot_names_are_sanitised() {
        assert_eq!(
            sanitise("the table shows 3 rows!"),
            "the-table-shows-3-rows"
        );
    }
}
