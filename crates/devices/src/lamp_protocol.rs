//! Lamp protocols: how a lamp controller spells the five things Glint asks of a lamp
//! (identify, level, on, off, state), as the rig's `[lamp.protocol]` describes it.
//!
//! A rig starts from a preset and overrides any part:
//!
//! - `glint`: the protocol of docs/design.md (`*IDN?`, `LEVEL n`, `ON`, `OFF`, `STATE?` →
//!   `ON n` / `OFF`, errors `ERR ...`), which the simulated lamp firmware speaks.
//! - `lumencor`: a Lumencor Spectra III light engine in standard (not legacy) mode, as
//!   python-microscope's `microscope/controllers/lumencor.py` drives it: `GET`/`SET` commands,
//!   replies `A ...` (done) or `E ...` (failed), one channel (index 0), intensity 0..1000
//!   (`GET MAXINT 0`), a blank line sent first (a freshly powered engine fails the first
//!   command), switch state read with `GET CHACT 0` and the level with `GET CHINT 0`.
//! - `coolled`: a CoolLED pE-300 series controller, as python-microscope's
//!   `microscope/controllers/coolled.py` drives it: 57600 baud, a greeting on connection that
//!   is drained, channel status `CSS?` → `CSSASN050BXF000CXF000` (per channel: name,
//!   selected S/X, on N/F, intensity in percent, three digits), set with `CSSASN050`; the
//!   lamp is channel A, and its level is sent with the switch-on command.
//!
//! Glint's levels are 0..1000; a protocol maps them linearly onto the device's range
//! (`level_range`) and the device's level read back maps back, so a lamp with a coarser range
//! reads back what it can represent. A lamp is verified in its own units.

use std::time::Duration;

use regex::{Regex, RegexBuilder};
use serde::{Deserialize, Serialize};

/// The presets of `[lamp.protocol] preset`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LampPreset {
    /// docs/design.md's protocol.
    #[default]
    Glint,
    /// Lumencor Spectra III (standard mode), after python-microscope's driver.
    Lumencor,
    /// CoolLED pE-300 series, after python-microscope's driver.
    Coolled,
}

impl LampPreset {
    pub const ALL: [LampPreset; 3] = [LampPreset::Glint, LampPreset::Lumencor, LampPreset::Coolled];

    pub fn name(self) -> &'static str {
        match self {
            LampPreset::Glint => "glint",
            LampPreset::Lumencor => "lumencor",
            LampPreset::Coolled => "coolled",
        }
    }

    /// The baud rate the device's manual names.
    pub fn baud(self) -> u32 {
        match self {
            LampPreset::Coolled => 57_600,
            _ => 115_200,
        }
    }
}

/// A line terminator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Terminator {
    /// Any of CR, LF and CRLF ends a line (receiving only).
    Auto,
    Lf,
    Cr,
    Crlf,
}

impl Terminator {
    pub fn bytes(self) -> &'static [u8] {
        match self {
            Terminator::Auto | Terminator::Lf => b"\n",
            Terminator::Cr => b"\r",
            Terminator::Crlf => b"\r\n",
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Terminator::Auto => "auto",
            Terminator::Lf => "lf",
            Terminator::Cr => "cr",
            Terminator::Crlf => "crlf",
        }
    }
}

/// What to do when the port is opened.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OnConnectSection {
    /// Read and discard what the device sends (a greeting) until it has been quiet this long.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drain_ms: Option<u64>,
    /// Send an empty line and discard its reply (devices whose first command fails).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub blank_line: Option<bool>,
}

/// Reply patterns (regular expressions, matched against a whole reply line without its
/// terminator; `(?P<level>...)` captures the level in the device's units).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RepliesSection {
    /// The reply to `identify`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub identity: Option<String>,
    /// The reply to `on`, `off` and `level` when the device did it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub success: Option<String>,
    /// A reply saying the device refused a command.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The reply to `state` when the lamp is on (may capture the level).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state_on: Option<String>,
    /// The reply to `state` when the lamp is off.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state_off: Option<String>,
    /// The reply to `level_query`, capturing the level.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level: Option<String>,
}

/// Per-command reply timeouts, ms (default: `lamp.reply_timeout_ms`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TimeoutsSection {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub identify: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub on: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub off: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state: Option<u64>,
}

/// `[lamp.protocol]` as written: a preset and what the rig changes of it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LampProtocolSection {
    pub preset: LampPreset,
    /// Appended to every command sent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub send_terminator: Option<Terminator>,
    /// What ends a reply line (`auto`: CR, LF or CRLF).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub receive_terminator: Option<Terminator>,
    /// The device sends every command back before its reply.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub echo: Option<bool>,
    /// A line the device sends after each reply (e.g. "OK"), skipped.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trailer: Option<String>,
    /// The device's levels for Glint's 0 and 1000: exactly two numbers.
    #[serde(
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::rig::exactly_opt"
    )]
    pub level_range: Option<[u32; 2]>,
    /// Write the level with at least this many digits (zero-padded).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level_digits: Option<u8>,
    /// Pause between the end of one command's reply and the next command, ms.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub command_gap_ms: Option<u64>,
    /// Longest reply line kept, bytes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_line_bytes: Option<usize>,
    pub on_connect: OnConnectSection,
    pub replies: RepliesSection,
    pub timeouts_ms: TimeoutsSection,
}

/// `[lamp.commands]`: command strings, each overriding the preset's (`{level}` is replaced
/// by the level in the device's units).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LampCommands {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub identify: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub on: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub off: Option<String>,
    /// Set the level (`{level}`); an empty string: the level goes with `on` instead.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state: Option<String>,
    /// Ask the level, when the state reply does not carry it; empty: none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level_query: Option<String>,
}

/// The five (six) things a driver sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CommandKind {
    Identify,
    On,
    Off,
    Level,
    State,
    LevelQuery,
}

/// Largest `max_line_bytes`.
pub const MAX_LINE_LIMIT: usize = 1 << 20;
/// Longest pause between commands, and longest drain, ms.
pub const MAX_PAUSE_MS: u64 = 60_000;
/// Largest device level.
pub const MAX_DEVICE_LEVEL: u32 = 1_000_000;

/// A protocol, resolved: every part known, patterns compiled.
#[derive(Debug, Clone)]
pub struct Protocol {
    pub preset: LampPreset,
    pub send_terminator: Terminator,
    pub receive_terminator: Terminator,
    pub echo: bool,
    pub trailer: Option<String>,
    pub level_range: [u32; 2],
    pub level_digits: u8,
    pub command_gap: Duration,
    pub max_line_bytes: usize,
    pub drain: Option<Duration>,
    pub blank_line: bool,
    pub identify: String,
    pub on: String,
    pub off: String,
    /// `None`: the level goes with `on`.
    pub level: Option<String>,
    pub state: String,
    pub level_query: Option<String>,
    pub identity: Regex,
    pub success: Regex,
    pub error: Regex,
    pub state_on: Regex,
    pub state_off: Regex,
    pub level_reply: Option<Regex>,
    pub timeouts: TimeoutsSection,
}

fn preset_parts(p: LampPreset) -> Preset {
    match p {
        LampPreset::Glint => Preset {
            drain_ms: None,
            blank_line: false,
            level_range: [0, 1000],
            level_digits: 0,
            identify: "*IDN?",
            on: "ON",
            off: "OFF",
            level: "LEVEL {level}",
            state: "STATE?",
            level_query: "",
            identity: r"^.+$",
            success: r"^OK$",
            error: r"^ERR",
            state_on: r"^ON (?P<level>\d+)$",
            state_off: r"^OFF$",
            level_reply: "",
        },
        LampPreset::Lumencor => Preset {
            drain_ms: None,
            blank_line: true,
            level_range: [0, 1000],
            level_digits: 0,
            identify: "GET MODEL",
            on: "SET CH 0 1",
            off: "SET CH 0 0",
            level: "SET CHINT 0 {level}",
            state: "GET CHACT 0",
            level_query: "GET CHINT 0",
            identity: r"^A MODEL .+$",
            success: r"^A \S+",
            error: r"^E\b",
            state_on: r"^A CHACT 0 1$",
            state_off: r"^A CHACT 0 0$",
            level_reply: r"^A CHINT 0 (?P<level>\d+)$",
        },
        LampPreset::Coolled => Preset {
            drain_ms: Some(1000),
            blank_line: false,
            level_range: [0, 100],
            level_digits: 3,
            identify: "CSS?",
            on: "CSSASN{level}",
            off: "CSSAXF000",
            level: "",
            state: "CSS?",
            level_query: "",
            identity: r"^CSS(?:[A-H][SX][NF]\d{3})+$",
            success: r"^CSS(?:[A-H][SX][NF]\d{3})+$",
            error: r"^ERROR\b",
            state_on: r"^CSSASN(?P<level>\d{3})",
            state_off: r"^CSSA[SX]F\d{3}",
            level_reply: "",
        },
    }
}

struct Preset {
    drain_ms: Option<u64>,
    blank_line: bool,
    level_range: [u32; 2],
    level_digits: u8,
    identify: &'static str,
    on: &'static str,
    off: &'static str,
    level: &'static str,
    state: &'static str,
    level_query: &'static str,
    identity: &'static str,
    success: &'static str,
    error: &'static str,
    state_on: &'static str,
    state_off: &'static str,
    level_reply: &'static str,
}

/// A problem with a protocol: the rig key and what is wrong.
pub type Problem = (String, String);

fn compile(key: &str, pattern: &str, problems: &mut Vec<Problem>) -> Option<Regex> {
    if pattern.is_empty() {
        problems.push((
            key.into(),
            "is empty, which would match every reply; give the pattern of the reply".into(),
        ));
        return None;
    }
    if pattern.len() > 1024 {
        problems.push((
            key.into(),
            format!("is {} bytes; at most 1024", pattern.len()),
        ));
        return None;
    }
    match RegexBuilder::new(pattern)
        .size_limit(1 << 20)
        .dfa_size_limit(1 << 20)
        .build()
    {
        Ok(r) => Some(r),
        Err(e) => {
            let first = e.to_string();
            let last = first.lines().last().unwrap_or("").trim().to_string();
            problems.push((
                key.into(),
                format!(
                    "{} is not a regular expression: {last}",
                    glint_format::fsx::quote(pattern)
                ),
            ));
            None
        }
    }
}

impl Protocol {
    /// The protocol of a preset, unchanged.
    pub fn preset(p: LampPreset) -> Protocol {
        Protocol::resolve(
            &LampProtocolSection {
                preset: p,
                ..Default::default()
            },
            &LampCommands::default(),
        )
        .expect("the presets are valid")
    }

    /// The protocol a rig's `[lamp.protocol]` and `[lamp.commands]` describe, or every
    /// problem with them (keys under `lamp.`).
    pub fn resolve(
        section: &LampProtocolSection,
        commands: &LampCommands,
    ) -> Result<Protocol, Vec<Problem>> {
        let p = preset_parts(section.preset);
        let mut problems = Vec::new();
        let pick = |o: &Option<String>, d: &str| o.clone().unwrap_or_else(|| d.to_string());
        let optional = |s: String| (!s.is_empty()).then_some(s);
        let r = &section.replies;
        let identity = compile(
            "lamp.protocol.replies.identity",
            &pick(&r.identity, p.identity),
            &mut problems,
        );
        let success = compile(
            "lamp.protocol.replies.success",
            &pick(&r.success, p.success),
            &mut problems,
        );
        let error = compile(
            "lamp.protocol.replies.error",
            &pick(&r.error, p.error),
            &mut problems,
        );
        let state_on = compile(
            "lamp.protocol.replies.state_on",
            &pick(&r.state_on, p.state_on),
            &mut problems,
        );
        let state_off = compile(
            "lamp.protocol.replies.state_off",
            &pick(&r.state_off, p.state_off),
            &mut problems,
        );
        let level_reply = optional(pick(&r.level, p.level_reply))
            .and_then(|s| compile("lamp.protocol.replies.level", &s, &mut problems));
        let level = optional(pick(&commands.level, p.level));
        let level_query = optional(pick(&commands.level_query, p.level_query));
        let on = pick(&commands.on, p.on);
        if level.is_none() && !on.contains("{level}") {
            problems.push((
                "lamp.commands.on".into(),
                format!(
                    "{} must contain `{{level}}` when lamp.commands.level is empty (the level goes with the switch-on command)",
                    glint_format::fsx::quote(&on)
                ),
            ));
        }
        if let Some(l) = &level {
            if !l.contains("{level}") {
                problems.push((
                    "lamp.commands.level".into(),
                    format!("{} must contain `{{level}}`", glint_format::fsx::quote(l)),
                ));
            }
        }
        if let Some(re) = &state_on {
            let captures = re.capture_names().any(|n| n == Some("level"));
            if !captures && level_query.is_none() {
                problems.push((
                    "lamp.protocol.replies.state_on".into(),
                    "captures no level (`(?P<level>\\d+)`) and there is no lamp.commands.level_query to ask it: Glint must read the level back".into(),
                ));
            }
        }
        if level_query.is_some() {
            match &level_reply {
                Some(re) if re.capture_names().any(|n| n == Some("level")) => {}
                Some(_) => problems.push((
                    "lamp.protocol.replies.level".into(),
                    "must capture the level: `(?P<level>\\d+)`".into(),
                )),
                None => {
                    // Empty (not a pattern that failed to compile, already named).
                    if pick(&r.level, p.level_reply).is_empty() {
                        problems.push((
                            "lamp.protocol.replies.level".into(),
                            "is needed with lamp.commands.level_query: the pattern of its reply, capturing `(?P<level>\\d+)`".into(),
                        ))
                    }
                }
            }
        }
        let level_range = section.level_range.unwrap_or(p.level_range);
        if level_range[0] >= level_range[1] || level_range[1] > MAX_DEVICE_LEVEL {
            problems.push((
                "lamp.protocol.level_range".into(),
                format!(
                    "must be [low, high] with low < high <= {MAX_DEVICE_LEVEL} (got [{}, {}])",
                    level_range[0], level_range[1]
                ),
            ));
        }
        let level_digits = section.level_digits.unwrap_or(p.level_digits);
        if level_digits > 9 {
            problems.push((
                "lamp.protocol.level_digits".into(),
                format!("must be 0..9 (got {level_digits})"),
            ));
        }
        if section.send_terminator == Some(Terminator::Auto) {
            problems.push((
                "lamp.protocol.send_terminator".into(),
                "must be \"lf\", \"cr\" or \"crlf\" (\"auto\" is for receiving)".into(),
            ));
        }
        let max_line_bytes = section.max_line_bytes.unwrap_or(4096);
        if !(16..=MAX_LINE_LIMIT).contains(&max_line_bytes) {
            problems.push((
                "lamp.protocol.max_line_bytes".into(),
                format!("must be 16..{MAX_LINE_LIMIT} (got {max_line_bytes})"),
            ));
        }
        let gap = section.command_gap_ms.unwrap_or(0);
        if gap > MAX_PAUSE_MS {
            problems.push((
                "lamp.protocol.command_gap_ms".into(),
                format!("must be at most {MAX_PAUSE_MS} ms (got {gap})"),
            ));
        }
        let drain = section.on_connect.drain_ms.or(p.drain_ms);
        if drain.is_some_and(|d| d > MAX_PAUSE_MS) {
            problems.push((
                "lamp.protocol.on_connect.drain_ms".into(),
                format!("must be at most {MAX_PAUSE_MS} ms"),
            ));
        }
        let t = &section.timeouts_ms;
        for (key, v) in [
            ("identify", t.identify),
            ("on", t.on),
            ("off", t.off),
            ("level", t.level),
            ("state", t.state),
        ] {
            if let Some(v) = v {
                if v == 0 || v > 60_000 {
                    problems.push((
                        format!("lamp.protocol.timeouts_ms.{key}"),
                        format!("must be 1..60000 ms (got {v})"),
                    ));
                }
            }
        }
        if let Some(tr) = &section.trailer {
            if tr.is_empty() || tr.len() > 256 || tr.chars().any(|c| c.is_control()) {
                problems.push((
                    "lamp.protocol.trailer".into(),
                    "must be one line of 1..256 printable characters".into(),
                ));
            }
        }
        if !problems.is_empty() {
            return Err(problems);
        }
        Ok(Protocol {
            preset: section.preset,
            send_terminator: section.send_terminator.unwrap_or(Terminator::Lf),
            receive_terminator: section.receive_terminator.unwrap_or(Terminator::Auto),
            echo: section.echo.unwrap_or(false),
            trailer: section.trailer.clone(),
            level_range,
            level_digits,
            command_gap: Duration::from_millis(gap),
            max_line_bytes,
            drain: drain.filter(|d| *d > 0).map(Duration::from_millis),
            blank_line: section.on_connect.blank_line.unwrap_or(p.blank_line),
            identify: pick(&commands.identify, p.identify),
            on,
            off: pick(&commands.off, p.off),
            level,
            state: pick(&commands.state, p.state),
            level_query,
            identity: identity.expect("no problem"),
            success: success.expect("no problem"),
            error: error.expect("no problem"),
            state_on: state_on.expect("no problem"),
            state_off: state_off.expect("no problem"),
            level_reply,
            timeouts: section.timeouts_ms.clone(),
        })
    }

    /// The command strings with the keys they are set by, for checks.
    pub fn commands(&self) -> Vec<(&'static str, &str)> {
        let mut v = vec![
            ("lamp.commands.identify", self.identify.as_str()),
            ("lamp.commands.on", self.on.as_str()),
            ("lamp.commands.off", self.off.as_str()),
            ("lamp.commands.state", self.state.as_str()),
        ];
        if let Some(l) = &self.level {
            v.push(("lamp.commands.level", l));
        }
        if let Some(l) = &self.level_query {
            v.push(("lamp.commands.level_query", l));
        }
        v
    }

    /// Glint's level (0..1000) in the device's units.
    pub fn to_device(&self, level: u16) -> u32 {
        let [lo, hi] = self.level_range;
        let l = f64::from(level.min(1000));
        (f64::from(lo) + l * f64::from(hi - lo) / 1000.0).round() as u32
    }

    /// A device level in Glint's units (0..1000; beyond the range clamps).
    pub fn from_device(&self, d: u32) -> u16 {
        let [lo, hi] = self.level_range;
        let d = d.clamp(lo, hi);
        (f64::from(d - lo) * 1000.0 / f64::from(hi - lo)).round() as u16
    }

    /// A command with `{level}` replaced by the device's level, zero-padded as the
    /// protocol says.
    pub fn with_level(&self, command: &str, device_level: u32) -> String {
        let digits = usize::from(self.level_digits);
        command.replace("{level}", &format!("{device_level:0digits$}"))
    }

    /// The reply timeout of a command.
    pub fn timeout(&self, kind: CommandKind, default: Duration) -> Duration {
        let t = &self.timeouts;
        let ms = match kind {
            CommandKind::Identify => t.identify,
            CommandKind::On => t.on,
            CommandKind::Off => t.off,
            CommandKind::Level => t.level,
            CommandKind::State | CommandKind::LevelQuery => t.state,
        };
        ms.map(Duration::from_millis).unwrap_or(default)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_resolves() {
        for p in LampPreset::ALL {
            let proto = Protocol::preset(p);
            assert_eq!(proto.preset, p);
        }
    }

    #[test]
    fn levels_scale_onto_the_device_range() {
        let c = Protocol::preset(LampPreset::Coolled);
        assert_eq!(c.to_device(800), 80);
        assert_eq!(c.to_device(805), 81);
        assert_eq!(c.from_device(81), 810);
        assert_eq!(c.with_level(&c.on, c.to_device(50)), "CSSASN005");
        let g = Protocol::preset(LampPreset::Glint);
        assert_eq!(
            g.with_level(g.level.as_deref().unwrap(), g.to_device(700)),
            "LEVEL 700"
        );
        let l = Protocol::preset(LampPreset::Lumencor);
        assert!(l.level_reply.as_ref().unwrap().is_match("A CHINT 0 500"));
        assert!(l.state_on.is_match("A CHACT 0 1"));
        assert!(c.state_on.is_match("CSSASN050BXF000CXF000"));
        assert!(c.state_off.is_match("CSSAXF000BXF000CXF000"));
    }

    #[test]
    fn an_empty_level_reply_pattern_with_a_level_query_is_a_problem() {
        // Was: `replies.level = ""` with a level query (lumencor) resolved without the
        // pattern, so every level read back was "a reply the protocol does not know".
        let section = LampProtocolSection {
            preset: LampPreset::Lumencor,
            replies: RepliesSection {
                level: Some(String::new()),
                ..Default::default()
            },
            ..Default::default()
        };
        let problems = Protocol::resolve(&section, &LampCommands::default()).unwrap_err();
        assert!(
            problems
                .iter()
                .any(|(k, m)| k == "lamp.protocol.replies.level" && m.contains("level_query")),
            "{problems:?}"
        );
    }

    #[test]
    fn problems_name_their_keys() {
        let section = LampProtocolSection {
            replies: RepliesSection {
                state_on: Some("^ON$".into()),
                success: Some("(".into()),
                ..Default::default()
            },
            level_range: Some([10, 5]),
            send_terminator: Some(Terminator::Auto),
            ..Default::default()
        };
        let commands = LampCommands {
            level: Some("LEVEL".into()),
            ..Default::default()
        };
        let section = LampProtocolSection {
            replies: RepliesSection {
                state_off: Some(String::new()),
                ..section.replies
            },
            ..section
        };
        let keys: Vec<String> = Protocol::resolve(&section, &commands)
            .unwrap_err()
            .into_iter()
            .map(|(k, _)| k)
            .collect();
        for k in [
            "lamp.protocol.replies.success",
            "lamp.protocol.replies.state_on",
            "lamp.commands.level",
            "lamp.protocol.level_range",
            "lamp.protocol.send_terminator",
            "lamp.protocol.replies.state_off",
        ] {
            assert!(keys.iter().any(|x| x == k), "{k} in {keys:?}");
        }
    }
}
