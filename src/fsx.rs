//! Files from places Glint does not control: the one set of rules for reading and writing
//! them, so that every stage treats a session folder (or a rig's folder, or a user's
//! output folder) as a trust boundary in the same way.
//!
//! - Reads are size-capped and take regular files only: no device (`/dev/zero` reads
//!   forever), no FIFO (blocks), and, inside a session, no symbolic link.
//! - Paths named by a file Glint reads (a manifest's frame list) must be relative, made of
//!   plain names (no `..`, no `.`, no root), and resolve through no symbolic link.
//! - Output folders are real folders, never symbolic links, so a session cannot make Glint
//!   write outside it; output files are created new (`O_EXCL`, which never follows a link).
//! - Values quoted in error messages are cut to about 100 characters on one line.
//!
//! Everything here is `std` plus `O_NOFOLLOW`/`O_NONBLOCK` from libc: no crate offers
//! exactly "open a regular file without following links, capped", and the rules are short.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Component, Path, PathBuf};

/// Largest JSON or TOML file Glint reads (manifests, rigs, derived results): 64 MiB.
pub const MAX_TEXT_BYTES: u64 = 64 << 20;
/// Largest frame or photo file Glint reads: 2 GiB (a 16384² 16-bit RGB PNG stored
/// uncompressed is 1.6 GB).
pub const MAX_IMAGE_BYTES: u64 = 2 << 30;
/// Longest value quoted in an error message, in characters.
pub const QUOTE_CHARS: usize = 100;

fn invalid(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg)
}

/// Open `path` for reading if it is a regular file, following no symbolic link at its
/// last component and never blocking (a FIFO or device is refused, not waited on).
pub fn open_regular(path: &Path) -> io::Result<File> {
    let f = OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.raw_os_error() == Some(libc::ELOOP) {
                invalid("is a symbolic link; Glint reads only regular files here".into())
            } else {
                e
            }
        })?;
    let meta = f.metadata()?;
    if !meta.file_type().is_file() {
        return Err(invalid(format!(
            "is not a regular file ({}); Glint reads only regular files here",
            describe_type(&meta.file_type())
        )));
    }
    Ok(f)
}

fn describe_type(t: &fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a folder"
    } else if t.is_symlink() {
        "a symbolic link"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() || t.is_block_device() {
        "a device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a file"
    }
}

/// Read a regular file (see [`open_regular`]) of at most `cap` bytes.
pub fn read_capped(path: &Path, cap: u64) -> io::Result<Vec<u8>> {
    let f = open_regular(path)?;
    let len = f.metadata()?.len();
    if len > cap {
        return Err(invalid(format!(
            "is {} bytes, more than the {} bytes Glint reads from such a file",
            len, cap
        )));
    }
    let mut buf = Vec::with_capacity(len as usize);
    f.take(cap + 1).read_to_end(&mut buf)?;
    if buf.len() as u64 > cap {
        return Err(invalid(format!(
            "grew beyond the {cap} bytes Glint reads from such a file while being read"
        )));
    }
    Ok(buf)
}

/// [`read_capped`] as UTF-8 text.
pub fn read_text_capped(path: &Path, cap: u64) -> io::Result<String> {
    String::from_utf8(read_capped(path, cap)?).map_err(|e| {
        invalid(format!(
            "is not UTF-8 text (byte {})",
            e.utf8_error().valid_up_to()
        ))
    })
}

/// Check a relative path named inside a file (a manifest's frame) and join it to `dir`:
/// relative, plain names only (no `..`, `.`, root or empty parts), no NUL, at most 4096
/// bytes, and no symbolic link on the way from `dir` to the file (the file itself is
/// checked when opened with [`open_regular`]). The error says what is wrong, for the
/// caller to put after the path.
pub fn inside(dir: &Path, rel: &str) -> Result<PathBuf, String> {
    if rel.is_empty() {
        return Err("the path is empty".into());
    }
    if rel.len() > 4096 || rel.contains('\0') {
        return Err(format!(
            "{} is not a usable path (too long or has a NUL byte)",
            quote(rel)
        ));
    }
    let p = Path::new(rel);
    let mut joined = dir.to_path_buf();
    let comps: Vec<Component> = p.components().collect();
    for (i, c) in comps.iter().enumerate() {
        match c {
            Component::Normal(name) => {
                joined.push(name);
                if i + 1 < comps.len() {
                    match fs::symlink_metadata(&joined) {
                        Ok(m) if m.file_type().is_symlink() => {
                            return Err(format!(
                                "{} passes through a symbolic link ({}); a session's files must be inside it",
                                quote(rel),
                                quote(&name.to_string_lossy())
                            ))
                        }
                        _ => {}
                    }
                }
            }
            _ => {
                return Err(format!(
                    "{} must be a relative path inside the session (plain names, no `..`, `.` or leading `/`)",
                    quote(rel)
                ))
            }
        }
    }
    if rel.ends_with('/') {
        return Err(format!("{} names a folder, not a file", quote(rel)));
    }
    Ok(joined)
}

/// Make sure `path` is a real folder (created, with its parents, if missing): refuses a
/// symbolic link or a file in its place, so nothing is written through a link.
pub fn ensure_dir(path: &Path) -> io::Result<()> {
    match fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => Err(invalid(format!(
            "{} is a symbolic link; Glint writes results only into real folders (remove the link)",
            path.display()
        ))),
        Ok(m) if m.is_dir() => Ok(()),
        Ok(_) => Err(invalid(format!(
            "{} exists and is not a folder; move it away",
            path.display()
        ))),
        Err(e) if e.kind() == io::ErrorKind::NotFound => fs::create_dir_all(path),
        Err(e) => Err(e),
    }
}

/// Create `path` new with `bytes` (never replacing or following anything there), synced.
pub fn create_new(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let mut f = OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

/// A value for an error message: on one line, at most [`QUOTE_CHARS`] characters, control
/// characters escaped, in backticks.
pub fn quote(s: &str) -> String {
    let mut out = String::new();
    let mut n = 0;
    for c in s.chars() {
        if n >= QUOTE_CHARS {
            out.push('…');
            break;
        }
        if c.is_control() {
            let e: String = c.escape_default().collect();
            n += e.chars().count();
            out.push_str(&e);
        } else {
            out.push(c);
            n += 1;
        }
    }
    format!("`{out}`")
}

/// Text from outside (a daemon's reply, a file) made safe to print on a terminal: every
/// control character (C0, DEL, C1: escape sequences, newlines, carriage returns) and every
/// bidirectional-override character is shown escaped (`\u{1b}`), everything else as it is.
/// The one function the clients pass such text through before printing it.
pub fn printable(s: &str) -> std::borrow::Cow<'_, str> {
    if !s.chars().any(unsafe_char) {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        if unsafe_char(c) {
            out.push_str(&format!("\\u{{{:x}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    std::borrow::Cow::Owned(out)
}

/// A character a terminal may act on: a control character (C0, DEL, C1) or a
/// bidirectional override.
fn unsafe_char(c: char) -> bool {
    c.is_control()
        || matches!(c, '\u{200e}' | '\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
}

/// JSON text (as serde_json writes it) made safe to print: the characters [`printable`]
/// escapes that JSON leaves raw (C1 controls, bidirectional overrides; they can only be
/// inside strings) written as `\uXXXX` escapes, so it is still the same JSON.
pub fn printable_json(json: &str) -> std::borrow::Cow<'_, str> {
    if !json.chars().any(unsafe_char) {
        return std::borrow::Cow::Borrowed(json);
    }
    let mut out = String::with_capacity(json.len() + 8);
    for c in json.chars() {
        if unsafe_char(c) && c != '\n' {
            out.push_str(&format!("\\u{:04x}", c as u32));
        } else {
            out.push(c);
        }
    }
    std::borrow::Cow::Owned(out)
}

/// [`printable`] line by line, for text that is several lines by design (a job's summary):
/// its newlines kept, every other control character escaped.
pub fn printable_lines(s: &str) -> String {
    s.split('\n')
        .map(|l| printable(l).into_owned())
        .collect::<Vec<_>>()
        .join("\n")
}

/// Longest parser message Glint puts in an error, characters.
pub const MESSAGE_CHARS: usize = 300;

/// A parser's message (toml, serde_json) for an error: on one line (control characters
/// become spaces), every quoted value (between `"` or backticks) cut to [`QUOTE_CHARS`]
/// characters, and at most [`MESSAGE_CHARS`] in all: parsers quote a wrong value whole.
pub fn short_message(message: &str) -> String {
    let mut out = String::new();
    let mut open: Option<char> = None;
    let mut inside = 0;
    for c in message.trim().chars() {
        let c = if c.is_control() { ' ' } else { c };
        match open {
            Some(q) if c == q => {
                open = None;
                out.push(c);
            }
            Some(_) => {
                inside += 1;
                if inside <= QUOTE_CHARS {
                    out.push(c);
                } else if inside == QUOTE_CHARS + 1 {
                    out.push('…');
                }
            }
            None => {
                if c == '"' || c == '`' {
                    open = Some(c);
                    inside = 0;
                }
                out.push(c);
            }
        }
    }
    if out.chars().count() > MESSAGE_CHARS {
        out = out.chars().take(MESSAGE_CHARS).collect();
        out.push('…');
    }
    out
}

/// A serde_json error for a message: [`short_message`] of what it says, with where
/// (`at line L column C`) kept.
pub fn json_error(e: &serde_json::Error) -> String {
    let text = e.to_string();
    let at = format!(" at line {} column {}", e.line(), e.column());
    match text.strip_suffix(&at) {
        Some(what) if e.line() > 0 => format!("{}{at}", short_message(what)),
        _ => short_message(&text),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn printable_escapes_every_control_character() {
        assert_eq!(printable("ok"), "ok");
        assert_eq!(
            printable("a\x1b[31mb\nc\rd\u{9b}e\u{202e}"),
            "a\\u{1b}[31mb\\u{a}c\\u{d}d\\u{9b}e\\u{202e}"
        );
        assert_eq!(printable_lines("a\nb\x07"), "a\nb\\u{7}");
        let j = serde_json::json!({"a": "x\u{9b}\u{1b}\u{202e}"}).to_string();
        let safe = printable_json(&j);
        assert_eq!(safe, r#"{"a":"x\u009b\u001b\u202e"}"#);
        assert_eq!(
            serde_json::from_str::<serde_json::Value>(&safe).unwrap()["a"],
            "x\u{9b}\u{1b}\u{202e}"
        );
    }

    #[test]
    fn json_errors_quoting_a_huge_value_are_cut_to_one_short_line() {
        let v = format!("{{\"format\": \"{}\\nx\"}}", "A".repeat(20_000));
        let e = serde_json::from_str::<std::collections::BTreeMap<String, u32>>(&v).unwrap_err();
        assert!(e.to_string().len() > 20_000, "{e}");
        let m = json_error(&e);
        assert!(m.chars().count() <= MESSAGE_CHARS + 1, "{m}");
        assert!(!m.contains('\n') && m.contains("at line 1 column"), "{m}");
        // A value with a quote inside (the parser prints it raw) is cut all the same.
        let m = short_message(&format!("invalid type: string \"a\"{}\"", "b".repeat(5000)));
        assert!(m.chars().count() <= MESSAGE_CHARS + 1, "{m}");
    }

    #[test]
    fn inside_accepts_plain_names_and_refuses_escapes() {
        let d = tempfile::tempdir().unwrap();
        assert_eq!(
            inside(d.path(), "frames/a.png").unwrap(),
            d.path().join("frames/a.png")
        );
        for bad in [
            "/etc/passwd",
            "../x",
            "frames/../../x",
            "./a",
            "",
            "a/",
            "a\0b",
        ] {
            assert!(inside(d.path(), bad).is_err(), "{bad:?}");
        }
        std::os::unix::fs::symlink("/etc", d.path().join("frames")).unwrap();
        assert!(inside(d.path(), "frames/passwd")
            .unwrap_err()
            .contains("symbolic link"));
    }

    #[test]
    fn reads_refuse_devices_links_and_big_files() {
        let d = tempfile::tempdir().unwrap();
        assert!(read_capped(Path::new("/dev/zero"), 10)
            .unwrap_err()
            .to_string()
            .contains("device"));
        let f = d.path().join("f");
        fs::write(&f, b"0123456789").unwrap();
        assert_eq!(read_capped(&f, 10).unwrap().len(), 10);
        assert!(read_capped(&f, 9).is_err());
        let l = d.path().join("l");
        std::os::unix::fs::symlink(&f, &l).unwrap();
        assert!(read_capped(&l, 100)
            .unwrap_err()
            .to_string()
            .contains("symbolic link"));
    }

    #[test]
    fn output_folders_are_never_links() {
        let d = tempfile::tempdir().unwrap();
        ensure_dir(&d.path().join("a/b")).unwrap();
        ensure_dir(&d.path().join("a/b")).unwrap();
        std::os::unix::fs::symlink(d.path().join("a"), d.path().join("hdr")).unwrap();
        assert!(ensure_dir(&d.path().join("hdr")).is_err());
        create_new(&d.path().join("a/x"), b"1").unwrap();
        assert!(create_new(&d.path().join("a/x"), b"2").is_err());
        std::os::unix::fs::symlink("/tmp/nonexistent-glint", d.path().join("a/y")).unwrap();
        assert!(create_new(&d.path().join("a/y"), b"2").is_err());
    }

    #[test]
    fn quotes_are_short_and_on_one_line() {
        let q = quote(&"x\n".repeat(500));
        assert!(!q.contains('\n'));
        assert!(q.chars().count() < 120);
    }
}
