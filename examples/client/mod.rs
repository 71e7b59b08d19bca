//! What the client examples share: their flags, where the service is and the token it takes,
//! and requests whose refusals become errors naming the status and the service's message.
//!
//! Every example takes `--url URL` (else `CELLD_URL`, else `http://127.0.0.1:8080`) and
//! `--token TOKEN` (else `CELLD_TOKEN`, else the first line of `--token-file FILE`, by
//! default `data/admin.token`: the admin token `celld serve` writes beside its database on
//! its first start).

// Each example uses what it needs of this module.
#![allow(dead_code)]

use anyhow::{Context as _, bail};
use serde_json::Value;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::str::FromStr;
use std::time::Duration;

/// The flags every example takes, besides its own.
const CONNECTION_FLAGS: [&str; 3] = ["url", "token", "token-file"];

/// `--name value` flags, each named once.
pub struct Flags {
    values: BTreeMap<String, String>,
}

impl Flags {
    /// Reads the command line: every argument is `--name value` with `name` among `known` or
    /// the connection flags. `--help` prints `usage` and exits.
    pub fn parse(known: &[&str], usage: &str) -> anyhow::Result<Flags> {
        Flags::from_args(std::env::args().skip(1), known, usage)
    }

    fn from_args(
        args: impl IntoIterator<Item = String>,
        known: &[&str],
        usage: &str,
    ) -> anyhow::Result<Flags> {
        let mut values = BTreeMap::new();
        let mut args = args.into_iter();
        while let Some(arg) = args.next() {
            if arg == "--help" || arg == "-h" {
                println!("{usage}");
                std::process::exit(0);
            }
            let Some(name) = arg.strip_prefix("--") else {
                bail!("unexpected argument {arg:?}\n{usage}");
            };
            if !known.contains(&name) && !CONNECTION_FLAGS.contains(&name) {
                bail!("unknown flag --{name}\n{usage}");
            }
            let Some(value) = args.next() else {
                bail!("--{name} needs a value\n{usage}");
            };
            if values.insert(name.to_string(), value).is_some() {
                bail!("--{name} is given twice");
            }
        }
        Ok(Flags { values })
    }

    pub fn get(&self, name: &str) -> Option<&str> {
        self.values.get(name).map(String::as_str)
    }

    /// The flag's value parsed, `None` when it is not given; an error naming it when it does
    /// not parse.
    pub fn parsed<T: FromStr>(&self, name: &str) -> anyhow::Result<Option<T>> {
        self.get(name)
            .map(|text| {
                text.parse().map_err(|_| {
                    anyhow::anyhow!("--{name} {text:?} is not a {}", std::any::type_name::<T>())
                })
            })
            .transpose()
    }
}

/// A `celld serve` and the token to call it with.
pub struct Client {
    base: String,
    token: String,
    agent: ureq::Agent,
}

impl Client {
    /// The service and token the flags or the environment name (see the module's doc).
    pub fn from_flags(flags: &Flags) -> anyhow::Result<Client> {
        let base = match flags.get("url") {
            Some(url) => url.to_string(),
            None => std::env::var("CELLD_URL").unwrap_or_else(|_| "http://127.0.0.1:8080".into()),
        };
        let token = match (flags.get("token"), std::env::var("CELLD_TOKEN")) {
            (Some(token), _) => token.to_string(),
            (None, Ok(token)) => token,
            (None, Err(_)) => {
                let file = flags.get("token-file").unwrap_or("data/admin.token");
                let text = std::fs::read_to_string(file).with_context(|| {
                    format!(
                        "no token: give --token or CELLD_TOKEN, or a readable --token-file ({file})"
                    )
                })?;
                text.lines().next().unwrap_or_default().trim().to_string()
            }
        };
        if token.is_empty() {
            bail!("the token is empty");
        }
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_connect(Some(Duration::from_secs(5)))
            .build()
            .into();
        Ok(Client {
            base: base.trim_end_matches('/').to_string(),
            token,
            agent,
        })
    }

    pub fn base(&self) -> &str {
        &self.base
    }

    /// `GET path`, its JSON answer.
    pub fn get(&self, path: &str) -> anyhow::Result<Value> {
        json(
            self.answer("GET", path, self.authorised_get(path).call())?,
            path,
        )
    }

    /// `GET path`, its answer as text (CSV, say).
    pub fn get_text(&self, path: &str) -> anyhow::Result<String> {
        let mut response = self.answer("GET", path, self.authorised_get(path).call())?;
        response
            .body_mut()
            .read_to_string()
            .with_context(|| format!("GET {path}: reading the answer"))
    }

    /// `POST path` with a JSON body (or none), its JSON answer.
    pub fn post(&self, path: &str, body: Option<&Value>) -> anyhow::Result<Value> {
        let request = self
            .agent
            .post(self.url(path))
            .header("Authorization", self.bearer());
        let response = match body {
            Some(body) => request.send_json(body),
            None => request.send_empty(),
        };
        json(self.answer("POST", path, response)?, path)
    }

    /// `POST path` with raw bytes (`application/octet-stream`): the status and the JSON answer.
    pub fn post_bytes(&self, path: &str, bytes: &[u8]) -> anyhow::Result<(u16, Value)> {
        let response = self
            .agent
            .post(self.url(path))
            .header("Authorization", self.bearer())
            .header("Content-Type", "application/octet-stream")
            .send(bytes);
        let response = self.answer("POST", path, response)?;
        let status = response.status().as_u16();
        Ok((status, json(response, path)?))
    }

    /// The Server-Sent Events at `path`, as they come.
    pub fn events(&self, path: &str) -> anyhow::Result<Events> {
        let response = self.answer("GET", path, self.authorised_get(path).call())?;
        Ok(Events {
            reader: Box::new(BufReader::new(response.into_body().into_reader())),
        })
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    fn bearer(&self) -> String {
        format!("Bearer {}", self.token)
    }

    fn authorised_get(&self, path: &str) -> ureq::RequestBuilder<ureq::typestate::WithoutBody> {
        self.agent
            .get(self.url(path))
            .header("Authorization", self.bearer())
    }

    /// A 2xx answer, or an error naming the request, the status and the service's message.
    fn answer(
        &self,
        method: &str,
        path: &str,
        response: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> anyhow::Result<ureq::http::Response<ureq::Body>> {
        let mut response = response.map_err(|e| {
            anyhow::anyhow!(
                "{method} {path}: cannot reach celld at {} ({e}); is `celld serve` running there?",
                self.base
            )
        })?;
        let status = response.status();
        if status.is_success() {
            return Ok(response);
        }
        let text = response.body_mut().read_to_string().unwrap_or_default();
        let refusal = serde_json::from_str::<Value>(&text)
            .ok()
            .and_then(|body| {
                let error = &body["error"];
                Some(format!(
                    "{}: {}",
                    error["code"].as_str()?,
                    error["message"].as_str()?
                ))
            })
            .unwrap_or(text);
        bail!("{method} {path}: {status}: {refusal}")
    }
}

/// The answer's body as JSON.
fn json(mut response: ureq::http::Response<ureq::Body>, path: &str) -> anyhow::Result<Value> {
    let text = response
        .body_mut()
        .read_to_string()
        .with_context(|| format!("{path}: reading the answer"))?;
    serde_json::from_str(&text).with_context(|| format!("{path}: the answer is not JSON: {text}"))
}

/// One Server-Sent Event: its name and its data.
pub struct Event {
    pub name: String,
    pub data: String,
}

impl Event {
    /// The data as JSON.
    pub fn json(&self) -> anyhow::Result<Value> {
        serde_json::from_str(&self.data)
            .with_context(|| format!("a `{}` event that is not JSON: {}", self.name, self.data))
    }
}

/// A stream of Server-Sent Events (`event:` and `data:` lines, a blank line after each; lines
/// starting with `:` are keep-alive comments).
pub struct Events {
    reader: Box<dyn BufRead>,
}

impl Iterator for Events {
    type Item = anyhow::Result<Event>;

    /// The next event; `None` when the stream ends.
    fn next(&mut self) -> Option<Self::Item> {
        let (mut name, mut data) = (String::new(), Vec::new());
        loop {
            let mut line = String::new();
            match self.reader.read_line(&mut line) {
                Err(e) => return Some(Err(anyhow::anyhow!("the event stream broke: {e}"))),
                Ok(0) => return None,
                Ok(_) => {}
            }
            let line = line.trim_end_matches(['\r', '\n']);
            if line.is_empty() {
                if name.is_empty() && data.is_empty() {
                    continue;
                }
                let name = if name.is_empty() {
                    "message".into()
                } else {
                    name
                };
                return Some(Ok(Event {
                    name,
                    data: data.join("\n"),
                }));
            }
            let (field, value) = line.split_once(':').unwrap_or((line, ""));
            let value = value.strip_prefix(' ').unwrap_or(value);
            match field {
                "event" => name = value.to_string(),
                "data" => data.push(value.to_string()),
                _ => {} // A comment (keep-alive), `id` or `retry`.
            }
        }
    }
}

/// `text` made safe for a URL's query.
pub fn query_value(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}
