//! What the lamp controller answers: one pure function a preset, from the controller's
//! state and one command line (without its terminator) to one reply line (without its
//! terminator). No I/O and no clock here: the firmware ([`super::LampFirmware`]) puts the
//! replies on the wire, with their terminators and faults, and turns the state into light.
//!
//! - **glint**: Glint's own protocol (docs/design.md).
//! - **lumencor**: a Lumencor Spectra III in standard (not legacy) mode, as
//!   python-microscope's `microscope/controllers/lumencor.py` drives it, with one light
//!   channel (index 0, WHITE).
//! - **coolled**: a CoolLED pE-300, as python-microscope's `microscope/controllers/coolled.py`
//!   drives it: channels A, B and C, of which A is the lamp.

use crate::config::LampPreset;

/// One reply line, and whether it reports an error (no trailer follows an error).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reply {
    pub text: String,
    pub error: bool,
}

impl Reply {
    fn ok(text: impl Into<String>) -> Reply {
        Reply {
            text: text.into(),
            error: false,
        }
    }
    fn err(text: impl Into<String>) -> Reply {
        Reply {
            text: text.into(),
            error: true,
        }
    }
}

/// The light a controller's state asks of the lamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// The lamp is switched on (its warm-up runs from when it was switched on).
    pub on: bool,
    /// Output at full warm-up as a fraction of full intensity, 0..=1 (0 when off).
    pub fraction: f64,
}

/// Glint's controller: on or off, and a level 0..=1000.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GlintState {
    pub on: bool,
    pub level: u16,
}

impl Default for GlintState {
    fn default() -> Self {
        GlintState {
            on: false,
            level: 1000,
        }
    }
}

/// The Spectra III's one channel: on or off, intensity 0..=1000, and whether a command has
/// been received since power-up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LumencorState {
    pub on: bool,
    pub intensity: u16,
    pub powered_up: bool,
}

impl Default for LumencorState {
    fn default() -> Self {
        LumencorState {
            on: false,
            intensity: 1000,
            powered_up: true,
        }
    }
}

/// The Spectra III's maximum intensity (`GET MAXINT 0`).
pub const LUMENCOR_MAXINT: u16 = 1000;

/// A CoolLED channel: selected on the control pod (S) or not (X), on (N) or off (F), and
/// its intensity in percent.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CoolledChannel {
    pub name: char,
    pub selected: bool,
    pub on: bool,
    pub percent: u8,
}

/// The pE-300's three channels; A is the lamp and is selected on the control pod, B and C
/// are not (so they stay dark).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CoolledState {
    pub channels: [CoolledChannel; 3],
}

impl Default for CoolledState {
    fn default() -> Self {
        let ch = |name, selected| CoolledChannel {
            name,
            selected,
            on: false,
            percent: if selected { 100 } else { 0 },
        };
        CoolledState {
            channels: [ch('A', true), ch('B', false), ch('C', false)],
        }
    }
}

/// What CoolLED's controller says when a program opens its port.
pub const COOLLED_GREETING: &str = "CoolLED precisExcite, Hello, pleased to meet you";

/// A lamp controller of one of the presets, in its power-up state.
#[derive(Debug, Clone, PartialEq)]
pub enum Controller {
    Glint(GlintState),
    Lumencor(LumencorState),
    Coolled(CoolledState),
}

impl Controller {
    pub fn new(preset: LampPreset) -> Controller {
        match preset {
            LampPreset::Glint => Controller::Glint(GlintState::default()),
            LampPreset::Lumencor => Controller::Lumencor(LumencorState::default()),
            LampPreset::Coolled => Controller::Coolled(CoolledState::default()),
        }
    }

    pub fn preset(&self) -> LampPreset {
        match self {
            Controller::Glint(_) => LampPreset::Glint,
            Controller::Lumencor(_) => LampPreset::Lumencor,
            Controller::Coolled(_) => LampPreset::Coolled,
        }
    }

    /// Handle one command line: the reply, with the state changed as the command says.
    pub fn reply(&mut self, identity: &str, line: &str) -> Reply {
        match self {
            Controller::Glint(s) => glint_reply(s, identity, line),
            Controller::Lumencor(s) => lumencor_reply(s, line),
            Controller::Coolled(s) => coolled_reply(s, line),
        }
    }

    /// The reply of a controller too busy to handle a command (which it does not execute).
    /// A lumencor's power-up state ends with it all the same: the command was received.
    pub fn busy(&mut self) -> Reply {
        match self {
            Controller::Glint(_) => Reply::err("ERR 9 busy"),
            Controller::Lumencor(s) => {
                s.powered_up = false;
                Reply::err("E BUSY")
            }
            Controller::Coolled(_) => Reply::err("ERROR busy"),
        }
    }

    /// What the controller sends when a program opens its port, if anything.
    pub fn greeting(&self) -> Option<&'static str> {
        matches!(self, Controller::Coolled(_)).then_some(COOLLED_GREETING)
    }

    /// The light the state asks for.
    pub fn light(&self) -> Light {
        let (on, fraction) = match self {
            Controller::Glint(s) => (s.on, s.level as f64 / 1000.0),
            Controller::Lumencor(s) => (s.on, s.intensity as f64 / LUMENCOR_MAXINT as f64),
            Controller::Coolled(s) => {
                let a = &s.channels[0];
                (a.selected && a.on, a.percent as f64 / 100.0)
            }
        };
        Light {
            on,
            fraction: if on { fraction } else { 0.0 },
        }
    }
}

/// Glint's protocol (docs/design.md): `*IDN?`, `LEVEL n`, `ON`, `OFF`, `STATE?`.
pub fn glint_reply(s: &mut GlintState, identity: &str, line: &str) -> Reply {
    let mut parts = line.split_whitespace();
    match (parts.next(), parts.next(), parts.next()) {
        (Some("*IDN?"), None, _) => Reply::ok(identity),
        (Some("ON"), None, _) => {
            s.on = true;
            Reply::ok("OK")
        }
        (Some("OFF"), None, _) => {
            s.on = false;
            Reply::ok("OK")
        }
        (Some("STATE?"), None, _) => Reply::ok(if s.on {
            format!("ON {}", s.level)
        } else {
            "OFF".into()
        }),
        (Some("LEVEL"), Some(v), None) => match v.parse::<u16>() {
            Ok(l) if l <= 1000 => {
                s.level = l;
                Reply::ok("OK")
            }
            _ => Reply::err(format!("ERR 2 level must be 0..1000, got {v}")),
        },
        _ => Reply::err(format!("ERR 1 unknown command `{line}`")),
    }
}

/// A decimal number of at most `digits` digits and nothing else (no sign, no spaces).
fn decimal(s: &str, digits: usize) -> Option<u32> {
    if s.is_empty() || s.len() > digits || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    s.parse().ok()
}

/// The Spectra III in standard mode: `GET|SET <NAME> [args]`, answered `A <NAME> ...` or
/// `E <...>`. Commands this lamp does not have, and `SET` of what can only be read, are
/// `E UNKNOWNCMD` (an assumption: the manual is not to hand).
pub fn lumencor_reply(s: &mut LumencorState, line: &str) -> Reply {
    if std::mem::replace(&mut s.powered_up, false) {
        // python-microscope: the first command after power-up fails, whatever it is.
        return Reply::err("E UNKNOWNCMD");
    }
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let (verb, name, args) = match tokens.as_slice() {
        [verb, name, args @ ..] => (*verb, *name, args),
        _ => return Reply::err("E UNKNOWNCMD"),
    };
    let bad_args = || Reply::err(format!("E {name} ARGS"));
    let channel_ok = |c: &str| decimal(c, 3) == Some(0);
    let bit = |b: bool| if b { 1 } else { 0 };
    match (verb, name) {
        ("GET", "MODEL") => match args {
            [] => Reply::ok("A MODEL Spectra III"),
            _ => bad_args(),
        },
        ("GET", "CHMAP") => match args {
            [] => Reply::ok("A CHMAP WHITE"),
            _ => bad_args(),
        },
        ("GET", "MAXINT") => match args {
            [c] if channel_ok(c) => Reply::ok(format!("A MAXINT 0 {LUMENCOR_MAXINT}")),
            _ => bad_args(),
        },
        ("GET", "CHINT") => match args {
            [c] if channel_ok(c) => Reply::ok(format!("A CHINT 0 {}", s.intensity)),
            _ => bad_args(),
        },
        ("SET", "CHINT") => match args {
            [c, v] if channel_ok(c) => match decimal(v, 4) {
                Some(v) if v <= LUMENCOR_MAXINT as u32 => {
                    s.intensity = v as u16;
                    Reply::ok(format!("A CHINT 0 {v}"))
                }
                _ => bad_args(),
            },
            _ => bad_args(),
        },
        ("GET", "CH") | ("GET", "CHACT") => match args {
            [c] if channel_ok(c) => Reply::ok(format!("A {name} 0 {}", bit(s.on))),
            _ => bad_args(),
        },
        ("SET", "CH") => match args {
            [c, v] if channel_ok(c) && (*v == "0" || *v == "1") => {
                s.on = *v == "1";
                Reply::ok(format!("A CH 0 {v}"))
            }
            _ => bad_args(),
        },
        _ => Reply::err("E UNKNOWNCMD"),
    }
}

/// The channel status line, `CSS` then `<name><S|X><N|F><NNN>` a channel.
fn css_line(s: &CoolledState) -> String {
    let mut out = String::from("CSS");
    for c in &s.channels {
        out.push(c.name);
        out.push(if c.selected { 'S' } else { 'X' });
        out.push(if c.on { 'N' } else { 'F' });
        out.push_str(&format!("{:03}", c.percent));
    }
    out
}

/// The pE-300: `CSS?` reads every channel's status; `CSS` with 6-character groups sets the
/// channels named. Assumptions (the CoolLED manual is not to hand): selection is the
/// control pod's, so the S/X of a group must be S or X but changes nothing; a channel that
/// is not selected and is set on stays off (F); a malformed group, an unknown channel or an
/// intensity above 100 rejects the whole command, `ERROR <line>`, as does anything else.
pub fn coolled_reply(s: &mut CoolledState, line: &str) -> Reply {
    if line == "CSS?" {
        return Reply::ok(css_line(s));
    }
    let refuse = || Reply::err(format!("ERROR {line}"));
    let Some(groups) = line.strip_prefix("CSS") else {
        return refuse();
    };
    let groups = groups.as_bytes();
    if groups.is_empty() || groups.len() % 6 != 0 {
        return refuse();
    }
    let mut new = s.clone();
    for g in groups.chunks(6) {
        let Some(ch) = new.channels.iter_mut().find(|c| c.name as u8 == g[0]) else {
            return refuse();
        };
        let on = match (g[1], g[2]) {
            (b'S' | b'X', b'N') => true,
            (b'S' | b'X', b'F') => false,
            _ => return refuse(),
        };
        // g is ASCII up to here; the intensity must be three digits.
        let Some(pct) = std::str::from_utf8(&g[3..])
            .ok()
            .and_then(|p| decimal(p, 3).filter(|_| p.len() == 3))
            .filter(|p| *p <= 100)
        else {
            return refuse();
        };
        ch.on = on && ch.selected;
        ch.percent = pct as u8;
    }
    *s = new;
    Reply::ok(css_line(s))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn replies(c: &mut Controller, lines: &[&str]) -> Vec<String> {
        lines.iter().map(|l| c.reply("ID", l).text).collect()
    }

    #[test]
    fn glint_speaks_design_md() {
        let mut c = Controller::new(LampPreset::Glint);
        assert_eq!(c.reply("ID", "*IDN?"), Reply::ok("ID"));
        assert_eq!(c.reply("ID", "STATE?").text, "OFF");
        assert_eq!(c.reply("ID", "LEVEL 500").text, "OK");
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        assert_eq!(c.reply("ID", "ON"), Reply::ok("OK"));
        assert_eq!(c.reply("ID", "STATE?").text, "ON 500");
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 0.5
            }
        );
        assert_eq!(
            c.reply("ID", "LEVEL 1001"),
            Reply::err("ERR 2 level must be 0..1000, got 1001")
        );
        assert_eq!(
            c.reply("ID", "LEVEL -1").text,
            "ERR 2 level must be 0..1000, got -1"
        );
        assert_eq!(c.reply("ID", "LEVEL 0").text, "OK");
        assert_eq!(c.reply("ID", "LEVEL 1000").text, "OK");
        assert_eq!(
            c.reply("ID", "DANCE"),
            Reply::err("ERR 1 unknown command `DANCE`")
        );
        assert_eq!(c.reply("ID", "").text, "ERR 1 unknown command ``");
        assert_eq!(c.reply("ID", "ON 1").text, "ERR 1 unknown command `ON 1`");
        assert_eq!(c.reply("ID", "OFF"), Reply::ok("OK"));
        assert_eq!(c.reply("ID", "STATE?").text, "OFF");
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        assert_eq!(c.greeting(), None);
        assert_eq!(c.busy(), Reply::err("ERR 9 busy"));
    }

    #[test]
    fn lumencor_speaks_spectra_iii_standard_mode() {
        let mut c = Controller::new(LampPreset::Lumencor);
        // The power-up quirk: the first command fails whatever it is, once.
        assert_eq!(c.reply("ID", "GET MODEL"), Reply::err("E UNKNOWNCMD"));
        assert_eq!(
            replies(
                &mut c,
                &[
                    "GET MODEL",
                    "GET CHMAP",
                    "GET MAXINT 0",
                    "GET CHINT 0",
                    "SET CHINT 0 250",
                    "GET CHINT 0",
                    "GET CH 0",
                    "GET CHACT 0",
                ]
            ),
            [
                "A MODEL Spectra III",
                "A CHMAP WHITE",
                "A MAXINT 0 1000",
                "A CHINT 0 1000",
                "A CHINT 0 250",
                "A CHINT 0 250",
                "A CH 0 0",
                "A CHACT 0 0",
            ]
        );
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        assert_eq!(c.reply("ID", "SET CH 0 1"), Reply::ok("A CH 0 1"));
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 0.25
            }
        );
        assert_eq!(
            replies(&mut c, &["GET CH 0", "GET CHACT 0"]),
            ["A CH 0 1", "A CHACT 0 1"]
        );
        for (line, reply) in [
            ("SET CHINT 0 1001", "E CHINT ARGS"),
            ("SET CHINT 1 10", "E CHINT ARGS"),
            ("SET CHINT 0 -5", "E CHINT ARGS"),
            ("SET CHINT 0", "E CHINT ARGS"),
            ("GET CHINT 7", "E CHINT ARGS"),
            ("GET CHINT", "E CHINT ARGS"),
            ("SET CH 0 2", "E CH ARGS"),
            ("SET CH 1 1", "E CH ARGS"),
            ("GET CHACT X", "E CHACT ARGS"),
            ("GET MAXINT 3", "E MAXINT ARGS"),
            ("GET MODEL 0", "E MODEL ARGS"),
            ("GET TEMP", "E UNKNOWNCMD"),
            ("SET MODEL X", "E UNKNOWNCMD"),
            ("PUT CH 0 1", "E UNKNOWNCMD"),
            ("GET", "E UNKNOWNCMD"),
            ("", "E UNKNOWNCMD"),
            ("get model", "E UNKNOWNCMD"),
        ] {
            assert_eq!(c.reply("ID", line), Reply::err(reply), "{line}");
        }
        // Errors change nothing.
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 0.25
            }
        );
        assert_eq!(c.reply("ID", "SET CHINT 0 1000").text, "A CHINT 0 1000");
        assert_eq!(c.reply("ID", "SET CH 0 0").text, "A CH 0 0");
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        assert_eq!(c.greeting(), None);
        assert_eq!(c.busy(), Reply::err("E BUSY"));
    }

    #[test]
    fn lumencor_busy_first_ends_the_power_up_state() {
        let mut c = Controller::new(LampPreset::Lumencor);
        assert_eq!(c.busy().text, "E BUSY");
        assert_eq!(c.reply("ID", "GET MODEL").text, "A MODEL Spectra III");
    }

    #[test]
    fn lumencor_blank_line_first_as_a_driver_sends() {
        let mut c = Controller::new(LampPreset::Lumencor);
        assert_eq!(
            replies(&mut c, &["", "GET MODEL"]),
            ["E UNKNOWNCMD", "A MODEL Spectra III"]
        );
    }

    #[test]
    fn coolled_speaks_pe300() {
        let mut c = Controller::new(LampPreset::Coolled);
        assert_eq!(c.greeting(), Some(COOLLED_GREETING));
        assert_eq!(c.reply("ID", "CSS?"), Reply::ok("CSSASF100BXF000CXF000"));
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        assert_eq!(
            c.reply("ID", "CSSASN050"),
            Reply::ok("CSSASN050BXF000CXF000")
        );
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 0.5
            }
        );
        assert_eq!(c.reply("ID", "CSS?").text, "CSSASN050BXF000CXF000");
        // Several groups at once.
        assert_eq!(
            c.reply("ID", "CSSASN100CXF020").text,
            "CSSASN100BXF000CXF020"
        );
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 1.0
            }
        );
        assert_eq!(
            c.reply("ID", "CSSASF100CXF000").text,
            "CSSASF100BXF000CXF000"
        );
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        for bad in [
            "CSSASN101", // over 100 %
            "CSSASN05",  // short group
            "CSSASN0500",
            "CSSAQN050", // neither S nor X
            "CSSASY050", // neither N nor F
            "CSSDSN050", // no channel D
            "CSSASNabc",
            "CSSASN+50",
            "CSSASN050BSN05",
            "CSS",
            "css?",
            "CSS? ",
            "",
            "HELLO",
            "CSSASN0é0",
        ] {
            assert_eq!(
                c.reply("ID", bad),
                Reply::err(format!("ERROR {bad}")),
                "{bad}"
            );
        }
        // A rejected command changes no channel, not even its good groups.
        assert_eq!(
            c.reply("ID", "CSSASN050DSN050").text,
            "ERROR CSSASN050DSN050"
        );
        assert_eq!(c.reply("ID", "CSS?").text, "CSSASF100BXF000CXF000");
        assert_eq!(c.busy(), Reply::err("ERROR busy"));
    }

    #[test]
    fn coolled_unselected_channels_set_on_stay_off() {
        let mut c = Controller::new(LampPreset::Coolled);
        assert_eq!(
            c.reply("ID", "CSSBXN050CXN070").text,
            "CSSASF100BXF050CXF070"
        );
        // Selection is the control pod's: S in a group does not select B.
        assert_eq!(c.reply("ID", "CSSBSN050").text, "CSSASF100BXF050CXF070");
        // Light is channel A's alone.
        assert_eq!(
            c.light(),
            Light {
                on: false,
                fraction: 0.0
            }
        );
        // X for the selected A changes nothing either: it is switched on.
        assert_eq!(c.reply("ID", "CSSAXN030").text, "CSSASN030BXF050CXF070");
        assert_eq!(
            c.light(),
            Light {
                on: true,
                fraction: 0.3
            }
        );
    }
}
