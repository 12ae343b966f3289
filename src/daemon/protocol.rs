//! The daemon's wire protocol: JSON lines over a Unix socket (documented for client
//! writers in `docs/daemon-protocol.md`).
//!
//! Three kinds of line: a client's request (`{"id": 1, "cmd": "status"}`), the daemon's
//! reply to it (`{"id": 1, "ok": true, "result": ...}` or `{"id": 1, "ok": false, "error":
//! "..."}`), and events the daemon pushes to followers (`{"seq": 17, "event": "frame",
//! "job": 3, ...}`). A line is at most [`MAX_LINE`] bytes; anything malformed, oversized or
//! unknown gets an error reply and the connection carries on. The first request must be
//! `hello`, naming the protocol version the client speaks.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

/// The protocol version this daemon speaks.
pub const PROTOCOL_VERSION: u32 = 1;

/// Longest line either side sends, bytes (the newline not counted). A request is a few
/// hundred bytes; a job's final event with its summary is some tens of kilobytes.
pub const MAX_LINE: usize = 1 << 20;

/// How often the daemon sends a follower a `heartbeat` event while it has nothing else to
/// send (a long warm-up, a queued job waiting): a client that hears nothing, not even
/// this, for [`HEARTBEATS_MISSED`] of them knows the daemon is gone or hung.
pub const HEARTBEAT: std::time::Duration = std::time::Duration::from_secs(5);

/// Heartbeats a follower may miss before it gives up on the daemon.
pub const HEARTBEATS_MISSED: u32 = 3;

/// How long a client waits for the reply to a request [default; `GLINT_REPLY_TIMEOUT`
/// seconds sets another]: the daemon answers every request at once (a job's paths are
/// checked on a blocking thread, within a second or so on a healthy disk).
pub const REPLY_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// Longest request line the daemon reads, bytes: requests are small.
pub const MAX_REQUEST: usize = 64 * 1024;

/// Most samples a job may ask a fit for: a queue that anyone on the socket can fill should
/// not hold a fit of millions of samples (100 000 is 250 times the default at 640x480).
pub const MAX_SAMPLES: usize = 100_000;

/// What a job does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JobKind {
    /// Capture, HDR, calibration, fit, validation, report: what `glint run` does.
    Run,
    /// The capture alone (`glint capture`).
    Capture,
    /// The stages after the capture on an existing session.
    Process,
}

impl JobKind {
    pub fn name(self) -> &'static str {
        match self {
            JobKind::Run => "run",
            JobKind::Capture => "capture",
            JobKind::Process => "process",
        }
    }
}

/// A job as a client asks for it: the options `glint run` takes. Paths are absolute (the
/// daemon does not know the client's working directory).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    pub kind: JobKind,
    /// `process`: the session to process.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<PathBuf>,
    /// `run`, `capture`: where to write the session (new or empty) [default: the daemon's
    /// sessions folder, `<rig name>-<UTC time>-job<id>`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub out: Option<PathBuf>,
    /// Hold the lens at an earlier calibration (a camera.json); only the pose is fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<PathBuf>,
    /// Samples for the fit [default: by the image's size, as `glint run`'s].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub samples: Option<usize>,
    /// Where the fit's samples lie (`cross`, `line`, `perpendicular`, `rect`, `random`)
    /// [default: cross].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strategy: Option<crate::fit::sample::Strategy>,
    /// The speed/accuracy chart of `glint bench fit` for the report.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bench_chart: Option<PathBuf>,
    /// How long the job waits for an operator (a person asked through a client) before it
    /// fails, seconds [default: the daemon's `--operator-timeout`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator_timeout_s: Option<f64>,
    /// `process`: work on a session that is not complete, with a warning.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub allow_incomplete: bool,
}

impl JobSpec {
    pub fn new(kind: JobKind) -> Self {
        JobSpec {
            kind,
            session: None,
            out: None,
            intrinsics: None,
            samples: None,
            strategy: None,
            bench_chart: None,
            operator_timeout_s: None,
            allow_incomplete: false,
        }
    }

    /// Everything wrong with the spec, in one line each (empty when it can be queued).
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut path = |key: &str, p: &Option<PathBuf>| {
            if let Some(p) = p {
                let s = p.to_string_lossy();
                if !p.is_absolute() {
                    out.push(format!(
                        "{key}: {} is not an absolute path (the daemon does not know the client's working directory)",
                        crate::fsx::quote(&s)
                    ));
                } else if s.len() > 4096 || s.contains(['\0', '\n', '\r']) {
                    out.push(format!(
                        "{key}: not a usable path (at most 4096 bytes, one line)"
                    ));
                }
            }
        };
        path("session", &self.session);
        path("out", &self.out);
        path("intrinsics", &self.intrinsics);
        path("bench_chart", &self.bench_chart);
        match self.kind {
            JobKind::Process => {
                if self.session.is_none() {
                    out.push("a process job needs `session` (the session to process)".into());
                }
                if self.out.is_some() {
                    out.push(
                        "a process job writes into its session; `out` is for run and capture"
                            .into(),
                    );
                }
            }
            JobKind::Run | JobKind::Capture => {
                if self.session.is_some() {
                    out.push(format!(
                        "a {} job captures a new session; give `out`, not `session`",
                        self.kind.name()
                    ));
                }
            }
        }
        if let Some(p) = self
            .samples
            .and_then(|k| crate::fit::sample::count_problem(k, Some(MAX_SAMPLES)))
        {
            out.push(format!("samples: {p}"));
        }
        if let Some(crate::fit::sample::Strategy::UserLine(_)) = self.strategy {
            out.push(
                "strategy: cross, line, perpendicular, rect or random (a line of pixels is for glint fit --line)"
                    .into(),
            );
        }
        if let Some(t) = self.operator_timeout_s {
            if !(t.is_finite() && t > 0.0 && t <= 7.0 * 86400.0) {
                out.push(format!(
                    "operator_timeout_s: must be more than 0 and at most a week (got {t})"
                ));
            }
        }
        out
    }
}

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JobState {
    Queued,
    Running,
    Complete,
    Failed,
    /// Stopped by `abort` (or the daemon's SIGTERM): lamp off, session `failed`.
    Aborted,
    /// The daemon died while it ran (killed, power cut); found so at the next start.
    Interrupted,
}

impl JobState {
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Complete => "complete",
            JobState::Failed => "failed",
            JobState::Aborted => "aborted",
            JobState::Interrupted => "interrupted",
        }
    }

    /// The job has ended (it never runs again by itself).
    pub fn ended(self) -> bool {
        !matches!(self, JobState::Queued | JobState::Running)
    }
}

/// A job with everything known about it: what `jobs` lists and the journal keeps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    pub id: u64,
    pub spec: JobSpec,
    pub state: JobState,
    /// Who asked for it (the client's uid and pid).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub by: Option<String>,
    pub queued: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ended: Option<String>,
    /// The session the job writes or processes (known once it starts).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session: Option<PathBuf>,
    /// Why it did not complete, in one line.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The summary `glint run --json` (or `glint capture --json`) prints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub summary: Option<Value>,
    /// The one-screen summary `glint run` prints.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub summary_text: Option<String>,
}

impl Job {
    /// A job just queued: nothing known of it yet but what was asked, by whom, and when.
    pub fn queued(id: u64, spec: JobSpec, by: Option<String>, queued: String) -> Job {
        Job {
            id,
            spec,
            state: JobState::Queued,
            by,
            queued,
            started: None,
            ended: None,
            session: None,
            error: None,
            summary: None,
            summary_text: None,
        }
    }
}

/// A request, as parsed from the `cmd` field and the rest of the line.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "cmd", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Request {
    /// The first request: the protocol version the client speaks.
    Hello {
        version: u32,
        #[serde(default)]
        client: Option<String>,
    },
    /// The daemon, its devices, the queue and the running job.
    Status,
    /// The queue and the history.
    Jobs,
    /// Queue a job; the reply carries its id.
    Add { job: JobSpec },
    /// Remove a queued job.
    Remove { job: u64 },
    /// Move a queued job to position `to` (0: next to run).
    Move { job: u64, to: usize },
    /// Abort the running job (at its next frame; lamp off; session `failed: aborted`);
    /// with `job`, only if that one is running.
    Abort {
        #[serde(default)]
        job: Option<u64>,
    },
    /// Run queued jobs, one at a time in order.
    QueueStart,
    /// Start no new job once the current one ends.
    QueueStop,
    /// Stream events: with `job`, that job's from its start (replayed) then live ones until
    /// it ends; without, every event from now on.
    Follow {
        #[serde(default)]
        job: Option<u64>,
        /// Also send a `heartbeat` event every [`HEARTBEAT`] while following.
        #[serde(default)]
        heartbeat: bool,
    },
    /// Stop streaming events to this connection.
    Unfollow,
    /// The operator did what `job` asked (the `operator` event).
    OperatorDone { job: u64 },
    /// Abort the running job, switch the lamp off, and exit.
    Shutdown,
}

/// Why a request line is not a request (the `error` of the reply to it).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RequestError {
    #[error("not a JSON request: {detail}")]
    NotJson { detail: String },
    #[error("a request is a JSON object with `cmd`")]
    NotAnObject,
    #[error("`id` must be a number or a short string")]
    BadId,
    #[error("bad request: `{cmd}` takes no field {}", crate::fsx::quote(.field))]
    ExtraField { cmd: String, field: String },
    #[error("bad request: {detail}")]
    Bad { detail: String },
    #[error("`cmd` must be a string")]
    CmdNotAString,
    #[error("a request needs `cmd` (e.g. {{\"id\": 1, \"cmd\": \"status\"}})")]
    NoCmd,
}

/// A parsed request line: its id (echoed in the reply) and the request, or why it is not
/// one.
pub struct Incoming {
    pub id: Value,
    pub request: Result<Request, RequestError>,
}

/// Parse one request line. Never fails: a bad line is an `Err` request to answer.
pub fn parse_request(line: &str) -> Incoming {
    let value: Value = match serde_json::from_str(line) {
        Ok(v) => v,
        Err(e) => {
            return Incoming {
                id: Value::Null,
                request: Err(RequestError::NotJson {
                    detail: crate::fsx::json_error(&e),
                }),
            }
        }
    };
    let Value::Object(mut map) = value else {
        return Incoming {
            id: Value::Null,
            request: Err(RequestError::NotAnObject),
        };
    };
    let id = match map.remove("id") {
        Some(v @ (Value::Number(_) | Value::String(_))) if v.to_string().len() <= 100 => v,
        Some(Value::Null) | None => Value::Null,
        Some(_) => {
            return Incoming {
                id: Value::Null,
                request: Err(RequestError::BadId),
            }
        }
    };
    // serde ignores extra fields of the requests that have none; refuse them as the
    // others' are refused.
    if let Some(Value::String(cmd)) = map.get("cmd") {
        const NO_FIELDS: [&str; 6] = [
            "status",
            "jobs",
            "queue-start",
            "queue-stop",
            "unfollow",
            "shutdown",
        ];
        if let Some(k) = NO_FIELDS
            .contains(&cmd.as_str())
            .then(|| map.keys().find(|k| *k != "cmd"))
            .flatten()
        {
            return Incoming {
                id,
                request: Err(RequestError::ExtraField {
                    cmd: cmd.clone(),
                    field: k.clone(),
                }),
            };
        }
    }
    let request = match map.get("cmd") {
        Some(Value::String(_)) => {
            serde_json::from_value(Value::Object(map)).map_err(|e| RequestError::Bad {
                detail: crate::fsx::short_message(&e.to_string()),
            })
        }
        Some(_) => Err(RequestError::CmdNotAString),
        None => Err(RequestError::NoCmd),
    };
    Incoming { id, request }
}

/// The reply to a request that succeeded.
pub fn ok(id: &Value, result: Value) -> String {
    json!({ "id": id, "ok": true, "result": result }).to_string()
}

/// The reply to a request that did not.
pub fn error(id: &Value, message: &str) -> String {
    json!({ "id": id, "ok": false, "error": message }).to_string()
}

/// An event line: `fields` (an object with `event`) with `seq` (and `job`) added.
pub fn event_line(seq: u64, job: Option<u64>, mut fields: Value) -> String {
    if let Value::Object(m) = &mut fields {
        m.insert("seq".into(), seq.into());
        if let Some(j) = job {
            m.insert("job".into(), j.into());
        }
    }
    fields.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_parse_with_their_id_and_every_bad_line_is_an_error_to_answer() {
        let r = parse_request(r#"{"id": 7, "cmd": "abort", "job": 3}"#);
        assert_eq!(r.id, json!(7));
        assert_eq!(r.request, Ok(Request::Abort { job: Some(3) }));
        let r = parse_request(r#"{"id": 8, "cmd": "follow", "job": 3, "heartbeat": true}"#);
        assert_eq!(
            r.request,
            Ok(Request::Follow {
                job: Some(3),
                heartbeat: true
            })
        );
        let r = parse_request(
            r#"{"id": "a", "cmd": "add", "job": {"kind": "process", "session": "/s"}}"#,
        );
        assert!(matches!(r.request, Ok(Request::Add { .. })));
        for (line, says) in [
            ("nonsense", "not a JSON request"),
            ("[1]", "a JSON object"),
            (r#"{"id": 1}"#, "needs `cmd`"),
            (r#"{"cmd": 5}"#, "must be a string"),
            (
                r#"{"id": [1], "cmd": "status"}"#,
                "number or a short string",
            ),
            (r#"{"cmd": "status", "extra": 1}"#, "takes no field `extra`"),
            (r#"{"cmd": "abort", "extra": 1}"#, "unknown field"),
            (r#"{"cmd": "frobnicate"}"#, "unknown variant"),
        ] {
            let e = parse_request(line).request.unwrap_err().to_string();
            assert!(e.contains(says), "{line}: {e}");
        }
        let bad = JobSpec {
            out: Some("relative".into()),
            samples: Some(3),
            ..JobSpec::new(JobKind::Run)
        };
        let p = bad.problems();
        assert!(p[0].contains("not an absolute path"), "{p:?}");
        assert!(p[1].contains("samples"), "{p:?}");
        // The fit's sampling by name; a line of pixels is glint fit's alone.
        let job = |strategy: &str| {
            serde_json::from_value::<JobSpec>(json!({"kind": "run", "strategy": strategy}))
        };
        let rect = job("rect").unwrap();
        assert_eq!(rect.strategy, Some(crate::fit::sample::Strategy::Rect));
        assert!(rect.problems().is_empty());
        assert!(job("zigzag").is_err());
        let line = serde_json::from_value::<JobSpec>(
            json!({"kind": "run", "strategy": {"user-line": [0.0, 0.0, 10.0, 10.0]}}),
        )
        .unwrap();
        assert!(line.problems()[0].contains("strategy"));
    }
}
