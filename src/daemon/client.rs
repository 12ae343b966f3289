//! A synchronous client of the daemon (what `glint trigger`, `jobs`, `follow`, `abort`,
//! `queue` and `daemon status|stop` use): connect, say hello, send requests, read replies
//! and events. Plain `std` sockets: a client has one conversation and no need of tokio.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use super::protocol::{MAX_LINE, PROTOCOL_VERSION};

/// What went wrong talking to the daemon, in one line each.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot reach the glint daemon at {}: {reason}", .socket.display())]
    Connect { socket: PathBuf, reason: String },
    #[error("lost the glint daemon at {}: {reason}", .socket.display())]
    Lost { socket: PathBuf, reason: String },
    #[error("the daemon says: {0}")]
    Refused(String),
}

/// A connection to the daemon, past `hello`.
pub struct Client {
    socket: PathBuf,
    writer: UnixStream,
    reader: BufReader<UnixStream>,
    next_id: u64,
    /// Events read while waiting for a reply.
    events: VecDeque<Value>,
    /// What the daemon said to `hello`.
    pub hello: Value,
}

impl Client {
    /// Connect to the daemon at `socket` and say hello.
    pub fn connect(socket: &Path) -> Result<Client, ClientError> {
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
        let reader = BufReader::new(stream.try_clone().map_err(|e| ClientError::Connect {
            socket: socket.into(),
            reason: e.to_string(),
        })?);
        let mut c = Client {
            socket: socket.into(),
            writer: stream,
            reader,
            next_id: 1,
            events: VecDeque::new(),
            hello: Value::Null,
        };
        c.hello = c.request(json!({
            "cmd": "hello",
            "version": PROTOCOL_VERSION,
            "client": format!("glint {}", crate::VERSION),
        }))?;
        Ok(c)
    }

    fn lost(&self, reason: impl Into<String>) -> ClientError {
        ClientError::Lost {
            socket: self.socket.clone(),
            reason: reason.into(),
        }
    }

    /// Send a request (an object with `cmd`) and wait for its reply's `result`; events
    /// that arrive meanwhile are kept for [`Client::next_event`].
    pub fn request(&mut self, mut request: Value) -> Result<Value, ClientError> {
        let id = self.next_id;
        self.next_id += 1;
        request["id"] = id.into();
        let mut line = request.to_string();
        line.push('\n');
        if let Err(e) = self.writer.write_all(line.as_bytes()) {
            // The daemon may have said why it closed (a refused client): read that first.
            let _ = self
                .reader
                .get_ref()
                .set_read_timeout(Some(std::time::Duration::from_secs(1)));
            if let Ok(v) = self.read_value() {
                if let Some(err) = v.get("error").and_then(Value::as_str) {
                    return Err(ClientError::Refused(err.to_string()));
                }
            }
            return Err(self.lost(e.to_string()));
        }
        loop {
            let v = self.read_value()?;
            if v.get("event").is_some() {
                self.events.push_back(v);
                continue;
            }
            let for_us = v.get("id").and_then(Value::as_u64) == Some(id);
            let ok = v.get("ok").and_then(Value::as_bool);
            match (for_us, ok) {
                (true, Some(true)) => return Ok(v.get("result").cloned().unwrap_or(Value::Null)),
                (_, Some(false)) if for_us || v.get("id").is_none_or(Value::is_null) => {
                    return Err(ClientError::Refused(
                        v.get("error")
                            .and_then(Value::as_str)
                            .unwrap_or("an error without a message")
                            .to_string(),
                    ))
                }
                _ => continue,
            }
        }
    }

    /// The next event (kept ones first), waiting for it.
    pub fn next_event(&mut self) -> Result<Value, ClientError> {
        if let Some(e) = self.events.pop_front() {
            return Ok(e);
        }
        loop {
            let v = self.read_value()?;
            if v.get("event").is_some() {
                return Ok(v);
            }
        }
    }

    fn read_value(&mut self) -> Result<Value, ClientError> {
        let mut buf = Vec::new();
        let n = (&mut self.reader)
            .take(MAX_LINE as u64 + 1)
            .read_until(b'\n', &mut buf)
            .map_err(|e| self.lost(e.to_string()))?;
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
