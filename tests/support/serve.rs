//! A real `celld serve` on a free port with its own SQLite file, and a small HTTP client.
#![allow(dead_code)]

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

pub struct Server {
    child: Child,
    pub base: String,
    pub admin: String,
    /// The dashboard link `celld serve` printed, which signs in as admin (first start only).
    pub signin_url: Option<String>,
    /// The OPC UA endpoint `celld serve` printed (none when `CELLD_OPCUA_LISTEN` is `off`).
    pub opcua_url: Option<String>,
    pub db: PathBuf,
    agent: ureq::Agent,
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into()
}

impl Server {
    /// Starts a server on `dir/celld.db` with the given `CELLD_*` settings.
    pub fn start(dir: &Path, env: &[(&str, &str)]) -> Server {
        let db = dir.join("celld.db");
        let mut child = Command::new(env!("CARGO_BIN_EXE_celld"))
            .args(["serve", "--listen", "127.0.0.1:0", "--db"])
            .arg(&db)
            // Test servers share two cores; `control_thread_has_a_cpu_of_its_own` checks the
            // placement itself.
            .env("CELLD_CONTROL_CPU", "off")
            // Test servers run side by side; the OPC UA tests turn it on, on a free port.
            .env("CELLD_OPCUA_LISTEN", "off")
            .env("CELLD_LOG", "warn")
            // The bundled policy's evaluation at first start, kept short.
            .env("CELLD_EVALUATION_EPISODES", "20")
            // Test servers share two cores; the deadline rule has its own unit test.
            .env("CELLD_DEADLINE_MS", "5000")
            // The test's own settings win.
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start celld serve");
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let base = loop {
            let line = lines
                .next()
                .expect("celld serve exited before listening")
                .unwrap();
            if let Some(address) = line.strip_prefix("celld: listening on ") {
                break address.trim().to_string();
            }
        };
        let (mut signin_url, mut opcua_url) = (None, None);
        for line in lines.by_ref() {
            let line = line.unwrap();
            if let Some(url) = line.strip_prefix("celld: dashboard (signs in as admin) ") {
                signin_url = Some(url.trim().to_string());
            }
            if let Some(rest) = line.strip_prefix("celld: OPC UA ") {
                opcua_url = rest.split_whitespace().next().map(str::to_string);
            }
            if line.starts_with("celld: API ") {
                break;
            }
        }
        // Keep draining stdout so the server never blocks on a full pipe.
        std::thread::spawn(move || for _ in lines.by_ref() {});
        let admin = std::fs::read_to_string(dir.join("admin.token"))
            .expect("admin.token beside the database")
            .trim()
            .to_string();
        Server {
            child,
            base,
            admin,
            signin_url,
            opcua_url,
            db,
            agent: agent(),
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    fn answer(response: Result<ureq::http::Response<ureq::Body>, ureq::Error>) -> (u16, Value) {
        let mut response = response.expect("the server answers");
        let status = response.status().as_u16();
        let text = response.body_mut().read_to_string().unwrap_or_default();
        let value = serde_json::from_str(&text).unwrap_or(Value::String(text));
        (status, value)
    }

    pub fn get(&self, path: &str, token: Option<&str>) -> (u16, Value) {
        let mut request = self.agent.get(format!("{}{path}", self.base));
        if let Some(token) = token {
            request = request.header("Authorization", format!("Bearer {token}"));
        }
        Self::answer(request.call())
    }

    /// A body that is not JSON (a policy file), as bytes; panics unless the answer is 200.
    pub fn get_bytes(&self, path: &str, token: &str) -> Vec<u8> {
        let mut response = self
            .agent
            .get(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {token}"))
            .call()
            .expect("the server answers");
        assert_eq!(response.status().as_u16(), 200, "GET {path}");
        response.body_mut().read_to_vec().expect("a body")
    }

    pub fn post(&self, path: &str, token: Option<&str>, body: Option<Value>) -> (u16, Value) {
        let mut request = self.agent.post(format!("{}{path}", self.base));
        if let Some(token) = token {
            request = request.header("Authorization", format!("Bearer {token}"));
        }
        Self::answer(match body {
            Some(body) => request.send_json(body),
            None => request.send_empty(),
        })
    }

    pub fn delete(&self, path: &str, token: &str) -> (u16, Value) {
        let request = self
            .agent
            .delete(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {token}"));
        Self::answer(request.call())
    }

    pub fn post_raw(
        &self,
        path: &str,
        token: &str,
        content_type: &str,
        body: &[u8],
    ) -> (u16, Value) {
        let request = self
            .agent
            .post(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {token}"))
            .header("Content-Type", content_type);
        Self::answer(request.send(body))
    }

    /// Announces a body of `length` bytes and sends none of it: the server must refuse from
    /// the headers alone (a client that kept writing could see the connection close before it
    /// reads the answer).
    pub fn post_announcing(
        &self,
        path: &str,
        token: &str,
        content_type: &str,
        length: usize,
    ) -> (u16, Value) {
        use std::io::{Read, Write};
        let address = self.base.trim_start_matches("http://");
        let mut stream = std::net::TcpStream::connect(address).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        write!(
            stream,
            "POST {path} HTTP/1.1\r\nHost: {address}\r\nAuthorization: Bearer {token}\r\n\
             Content-Type: {content_type}\r\nContent-Length: {length}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut answer = Vec::new();
        let _ = stream.read_to_end(&mut answer);
        let answer = String::from_utf8_lossy(&answer);
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

    /// A new token of `role` made through the API.
    pub fn token(&self, role: &str) -> String {
        let (status, body) = self.post(
            "/api/tokens",
            Some(&self.admin),
            Some(serde_json::json!({"role": role, "name": format!("test {role}")})),
        );
        assert_eq!(status, 201, "{body}");
        body["token"].as_str().unwrap().to_string()
    }

    pub fn create_job(&self, token: &str, body: Value) -> Value {
        let (status, job) = self.post("/api/jobs", Some(token), Some(body));
        assert_eq!(status, 201, "{job}");
        job
    }

    pub fn job(&self, id: i64) -> Value {
        let (status, job) = self.get(&format!("/api/jobs/{id}"), Some(&self.admin));
        assert_eq!(status, 200, "{job}");
        job
    }

    pub fn steps(&self, id: i64) -> Vec<Value> {
        let (status, body) = self.get(&format!("/api/jobs/{id}/steps"), Some(&self.admin));
        assert_eq!(status, 200, "{body}");
        body["items"].as_array().unwrap().clone()
    }

    /// GETs `path` (as admin, expecting 200) until `done` holds for the answer; fails naming
    /// `what` never happened if that takes longer than `limit`.
    pub fn poll(
        &self,
        path: &str,
        what: &str,
        limit: Duration,
        done: impl Fn(&Value) -> bool,
    ) -> Value {
        let start = Instant::now();
        loop {
            let (status, body) = self.get(path, Some(&self.admin));
            assert_eq!(status, 200, "{path}: {body}");
            if done(&body) {
                return body;
            }
            assert!(start.elapsed() < limit, "{path} never {what}: {body}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Polls policy `id` until its evaluation is neither queued nor running (up to `limit`);
    /// answers the policy.
    pub fn wait_evaluated(&self, id: i64, limit: Duration) -> Value {
        let path = format!("/api/policies/{id}");
        self.poll(&path, "ended its evaluation", limit, |policy| {
            !matches!(
                policy["evaluation"]["status"].as_str(),
                Some("queued" | "running")
            )
        })
    }

    /// Polls the job until `done` holds (up to 60 s).
    pub fn wait_job(&self, id: i64, what: &str, done: impl Fn(&Value) -> bool) -> Value {
        let path = format!("/api/jobs/{id}");
        self.poll(&path, what, Duration::from_secs(60), done)
    }

    pub fn wait_final(&self, id: i64) -> Value {
        self.wait_job(id, "finished", |job| {
            !matches!(job["status"].as_str(), Some("queued" | "running"))
        })
    }

    pub fn kill9(&mut self) {
        self.child.kill().expect("kill -9");
        self.child.wait().unwrap();
    }

    /// Sends SIGTERM and waits for the exit (up to `limit`).
    pub fn terminate(&mut self, limit: Duration) -> (ExitStatus, Duration) {
        let start = Instant::now();
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .unwrap();
        assert!(sent.success());
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return (status, start.elapsed());
            }
            assert!(
                start.elapsed() < limit,
                "celld did not exit within {limit:?} of SIGTERM"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
