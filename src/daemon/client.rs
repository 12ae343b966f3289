//! A synchronous client of the daemon (what `glint trigger`, `jobs`, `follow`, `abort`,
//! `queue` and `daemon status|stop` use): connect, say hello, send requests, read replies
//! and events. Plain `std` sockets: a client has one conversation and no need of tokio.
//!
//! Nothing the daemon says is trusted blindly: every read has a bound (a reply within
//! [`REPLY_TIMEOUT`], an event or a heartbeat within [`HEARTBEATS_MISSED`] heartbeats while
//! following), every reply a command uses is parsed into the typed struct below (a
//! mistyped reply is an error, never a printed `null`), and the text a client prints goes
//! through [`crate::fsx::printable`] (the error messages here already have).

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::de::DeserializeOwned;
use serde::Deserialize;
use serde_json::{json, Value};

use super::protocol::{
    Job, JobState, HEARTBEATS_MISSED, MAX_LINE, PROTOCOL_VERSION, REPLY_TIMEOUT,
};
use crate::fsx::printable;

/// What went wrong talking to the daemon, in one line each.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot reach the glint daemon at {}: {reason}", .socket.display())]
    Connect { socket: PathBuf, reason: String },
    #[error("lost the glint daemon at {}: {reason}", .socket.display())]
    Lost { socket: PathBuf, reason: String },
    #[error("the glint daemon at {} did not answer within {:.1} s ({what}); is it hung? (`GLINT_REPLY_TIMEOUT=SECONDS` waits longer)", .socket.display(), .after.as_secs_f64())]
    Timeout {
        socket: PathBuf,
        what: String,
        after: Duration,
    },
    #[error("the glint daemon's reply to `{cmd}` is not what this glint {} expects ({reason}); is the daemon of the same version?", crate::VERSION)]
    Mistyped { cmd: String, reason: String },
    #[error("the daemon says: {0}")]
    Refused(String),
}

/// The daemon's reply to `hello`.
#[derive(Debug, Clone, Deserialize)]
pub struct Hello {
    pub protocol: u32,
    pub daemon: String,
    pub pid: u32,
    pub rig: String,
    /// How often a follower hears a `heartbeat` when nothing else happens, seconds.
    pub heartbeat_s: f64,
}

/// The reply to `add`.
#[derive(Debug, Clone, Deserialize)]
pub struct Added {
    pub job: u64,
    pub position: usize,
    pub queue_running: bool,
}

/// The reply to `status`.
#[derive(Debug, Clone, Deserialize)]
pub struct Status {
    pub daemon: StatusDaemon,
    pub devices: StatusDevices,
    pub queue: StatusQueue,
    pub running: Option<Job>,
    pub operator: Option<StatusOperator>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StatusDaemon {
    pub version: String,
    pub pid: u32,
    pub rig_name: String,
    pub rig: PathBuf,
    pub started: String,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StatusDevices {
    pub state: String,
    pub camera: String,
    pub lamp: String,
    pub since: String,
    #[serde(default)]
    pub last_error: Option<String>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StatusQueue {
    pub running: bool,
    pub queued: usize,
    pub shutting_down: bool,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StatusOperator {
    pub job: u64,
    pub message: String,
    pub since: String,
}

/// The reply to `jobs`.
#[derive(Debug, Clone, Deserialize)]
pub struct Jobs {
    pub queue_running: bool,
    pub running: Option<Job>,
    pub queue: Vec<Job>,
    pub history: Vec<Job>,
    #[serde(default)]
    pub history_omitted: usize,
}

/// The reply to `queue-start` and `queue-stop`.
#[derive(Debug, Clone, Deserialize)]
pub struct QueueRunning {
    pub queue_running: bool,
}

/// The reply to `remove` and `move`: the queue's order.
#[derive(Debug, Clone, Deserialize)]
pub struct QueueOrder {
    pub queue: Vec<u64>,
}

/// The reply to `abort`.
#[derive(Debug, Clone, Deserialize)]
pub struct Aborting {
    pub aborting: u64,
}

/// A `job-ended` event.
#[derive(Debug, Clone, Deserialize)]
pub struct JobEnded {
    pub job: u64,
    pub state: JobState,
    #[serde(default)]
    pub session: Option<PathBuf>,
    #[serde(default)]
    pub error: Option<String>,
    #[serde(default)]
    pub summary: Option<Value>,
    #[serde(default)]
    pub summary_text: Option<String>,
}

/// A connection to the daemon, past `hello`.
pub struct Client {
    socket: PathBuf,
    writer: UnixStream,
    reader: BufReader<UnixStream>,
    next_id: u64,
    /// Events read while waiting for a reply.
    events: VecDeque<Value>,
    /// How long a reply may take.
    reply_timeout: Duration,
    /// How long a follower waits for any line (events, heartbeats).
    event_timeout: Duration,
    /// What the daemon said to `hello`.
    pub hello: Hello,
}

/// A `GLINT_REPLY_TIMEOUT` that is not a number of seconds.
#[derive(Debug, thiserror::Error)]
#[error("GLINT_REPLY_TIMEOUT={}: give seconds, more than 0 and at most 86400", crate::fsx::quote(.value))]
pub struct BadReplyTimeout {
    pub value: String,
}

/// The reply bound: `GLINT_REPLY_TIMEOUT` seconds, else [`REPLY_TIMEOUT`].
fn reply_timeout() -> Result<Duration, BadReplyTimeout> {
    match std::env::var("GLINT_REPLY_TIMEOUT") {
        Err(_) => Ok(REPLY_TIMEOUT),
        Ok(s) => s
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|t| t.is_finite() && *t > 0.0 && *t <= 86400.0)
            .map(Duration::from_secs_f64)
            .ok_or(BadReplyTimeout { value: s }),
    }
}

impl Client {
    /// Connect to the daemon at `socket` and say hello.
    pub fn connect(socket: &Path) -> Result<Client, ClientError> {
        let connect_error = |reason: String| ClientError::Connect {
            socket: socket.into(),
            reason,
        };
        let reply_timeout = reply_timeout().map_err(|e| connect_error(e.to_string()))?;
        let stream = UnixStream::connect(socket).map_err(|e| ClientError::Connect {
            socket: socket.into(),
            reason: match e.kind() {
                std::io::ErrorKind::NotFound | std::io::ErrorKind::ConnectionRefused => format!(
                    "{e}; is `glint daemon --rig FILE` running? (give its socket with --socket or GLINT_SOCKET)"
                ),
                std::io::ErrorKind::PermissionDenied => format!(
                    "{e}; the daemon's socket is for its own user (and group, with --group) only"
                ),
                _ => e.to_string(),
            },
        })?;
        let _ = stream.set_write_timeout(Some(reply_timeout));
        let reader = BufReader::new(
            stream
                .try_clone()
                .map_err(|e| connect_error(e.to_string()))?,
        );
        let mut c = Client {
            socket: socket.into(),
            writer: stream,
            reader,
            next_id: 1,
            events: VecDeque::new(),
            reply_timeout,
            event_timeout: reply_timeout,
            hello: Hello {
                protocol: PROTOCOL_VERSION,
                daemon: String::new(),
                pid: 0,
                rig: String::new(),
                heartbeat_s: 0.0,
            },
        };
        let hello: Hello = c.call(json!({
            "cmd": "hello",
            "version": PROTOCOL_VERSION,
            "client": format!("glint {}", crate::VERSION),
        }))?;
        if !(hello.heartbeat_s.is_finite()
            && hello.heartbeat_s > 0.0
            && hello.heartbeat_s <= 3600.0)
        {
            return Err(ClientError::Mistyped {
                cmd: "hello".into(),
                reason: format!(
                    "heartbeat_s {} is not a number of seconds in (0, 3600]",
                    hello.heartbeat_s
                ),
            });
        }
        c.event_timeout = Duration::from_secs_f64(hello.heartbeat_s * HEARTBEATS_MISSED as f64)
            + Duration::from_millis(500);
        c.hello = hello;
        Ok(c)
    }

    fn lost(&self, reason: impl Into<String>) -> ClientError {
        ClientError::Lost {
            socket: self.socket.clone(),
            reason: reason.into(),
        }
    }

    /// Send a request and parse its reply's `result` as `T` (a reply of another shape is
    /// [`ClientError::Mistyped`]).
    pub fn call<T: DeserializeOwned>(&mut self, request: Value) -> Result<T, ClientError> {
        let cmd = request
            .get("cmd")
            .and_then(Value::as_str)
            .unwrap_or("?")
            .to_string();
        let v = self.request(request)?;
        serde_json::from_value(v).map_err(|e| ClientError::Mistyped {
            cmd,
            reason: crate::fsx::short_message(&e.to_string()),
        })
    }

    /// Send a request (an object with `cmd`) and wait for its reply's `result` (at most
    /// the reply timeout); events that arrive meanwhile are kept for
    /// [`Client::next_event`].
    pub fn request(&mut self, mut request: Value) -> Result<Value, ClientError> {
        let id = self.next_id;
        self.next_id += 1;
        let cmd = request
            .get("cmd")
            .and_then(Value::as_str)
            .unwrap_or("?")
            .to_string();
        request["id"] = id.into();
        if cmd == "follow" && request.get("heartbeat").is_none() {
            // A follower that may wait long for an event asks for heartbeats, so that a
            // silent daemon can be told from a long step (see `next_event`).
            request["heartbeat"] = true.into();
        }
        let mut line = request.to_string();
        line.push('\n');
        if let Err(e) = self.writer.write_all(line.as_bytes()) {
            // The daemon may have said why it closed (a refused client): read that first.
            let deadline = Instant::now() + Duration::from_secs(1).min(self.reply_timeout);
            if let Ok(Some(v)) = self.read_value(deadline, "").map(Some) {
                if let Some(err) = v.get("error").and_then(Value::as_str) {
                    return Err(ClientError::Refused(printable(err).into_owned()));
                }
            }
            return Err(self.lost(e.to_string()));
        }
        let deadline = Instant::now() + self.reply_timeout;
        let what = format!("the reply to `{cmd}`");
        loop {
            let v = self.read_value(deadline, &what)?;
            if v.get("event").is_some() {
                if v["event"] != "heartbeat" {
                    self.events.push_back(v);
                }
                continue;
            }
            let for_us = v.get("id").and_then(Value::as_u64) == Some(id);
            let ok = v.get("ok").and_then(Value::as_bool);
            match (for_us, ok) {
                (true, Some(true)) => return Ok(v.get("result").cloned().unwrap_or(Value::Null)),
                (_, Some(false)) if for_us || v.get("id").is_none_or(Value::is_null) => {
                    return Err(ClientError::Refused(
                        printable(
                            v.get("error")
                                .and_then(Value::as_str)
                                .unwrap_or("an error without a message"),
                        )
                        .into_owned(),
                    ))
                }
                (true, _) => {
                    return Err(ClientError::Mistyped {
                        cmd,
                        reason: "a reply without `ok: true` or `ok: false`".into(),
                    })
                }
                _ => continue,
            }
        }
    }

    /// The next event (kept ones first), waiting for it: at most [`HEARTBEATS_MISSED`]
    /// heartbeats' time without any line from the daemon. Heartbeats are not returned.
    pub fn next_event(&mut self) -> Result<Value, ClientError> {
        if let Some(e) = self.events.pop_front() {
            return Ok(e);
        }
        loop {
            let deadline = Instant::now() + self.event_timeout;
            let v = self.read_value(deadline, "an event or its heartbeat")?;
            match v.get("event") {
                Some(e) if e == "heartbeat" => continue,
                Some(_) => return Ok(v),
                None => continue,
            }
        }
    }

    /// One JSON line, read by `deadline` (`what`: what was awaited, for the error).
    fn read_value(&mut self, deadline: Instant, what: &str) -> Result<Value, ClientError> {
        let timeout = |c: &Client| ClientError::Timeout {
            socket: c.socket.clone(),
            what: what.to_string(),
            after: if what.starts_with("an event") {
                c.event_timeout
            } else {
                c.reply_timeout
            },
        };
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() && self.reader.buffer().is_empty() {
            return Err(timeout(self));
        }
        let _ = self
            .reader
            .get_ref()
            .set_read_timeout(Some(left.max(Duration::from_millis(1))));
        let mut buf = Vec::new();
        let n = match (&mut self.reader)
            .take(MAX_LINE as u64 + 1)
            .read_until(b'\n', &mut buf)
        {
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return Err(timeout(self))
            }
            Err(e) => return Err(self.lost(e.to_string())),
        };
        if n == 0 {
            return Err(self.lost("the connection closed (the daemon stopped or was killed)"));
        }
        if buf.len() > MAX_LINE + 1 {
            return Err(self.lost(format!("a line longer than {MAX_LINE} bytes")));
        }
        serde_json::from_slice(&buf)
            .map_err(|e| self.lost(format!("not a JSON line: {}", crate::fsx::json_error(&e))))
    }
}
