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
    read_open(open_regular(path)?, cap)
}

/// Read an open file of at most `cap` bytes (checked before reading, and again while
/// reading, for a file that grows).
fn read_open(f: File, cap: u64) -> io::Result<Vec<u8>> {
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
    utf8(read_capped(path, cap)?)
}

fn utf8(bytes: Vec<u8>) -> io::Result<String> {
    String::from_utf8(bytes).map_err(|e| {
        invalid(format!(
            "is not UTF-8 text (byte {})",
            e.utf8_error().valid_up_to()
        ))
    })
}

/// A file Glint reads below a folder it trusts no further than the folder itself: `root`
/// (a session folder, a rig's folder, the folder of a file the user named) as given, and
/// `rel`, plain names below it. This is the one way Glint reads a file it did not just
/// write: frames, every stage's results (`hdr/`, `calib/`, `fit/`, `validation/`), camera
/// profiles beside the rig, files named on the command line. [`Within::read`] walks from
/// `root` one name at a time (`openat` with `O_NOFOLLOW`), so no symbolic link on the way
/// is followed, even one made while Glint reads; the file must be a regular file and at
/// most the cap given for its kind ([`MAX_TEXT_BYTES`], [`MAX_IMAGE_BYTES`]). A hard link
/// is a regular file like any other (it can only name a file on the same file system that
/// its maker could read, and its contents are checked as any file's are).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Within {
    root: PathBuf,
    rel: PathBuf,
}

impl Within {
    /// `rel` (plain names: no `..`, `.`, root or empty part; checked when read) below `root`.
    pub fn new(root: impl Into<PathBuf>, rel: impl Into<PathBuf>) -> Within {
        Within {
            root: root.into(),
            rel: rel.into(),
        }
    }

    /// A file the user named (a command-line argument): its own folder is the root, so the
    /// file itself must be a regular file, not a link, and the folders above it are the
    /// user's choice.
    pub fn file(path: &Path) -> Within {
        Within::last(path, 1)
    }

    /// `path` with its last `n` components as the part that must be real folders and a
    /// regular file (a camera profile beside the rig: `profiles/NAME`, `n` = 2).
    pub fn last(path: &Path, n: usize) -> Within {
        let comps: Vec<Component> = path.components().collect();
        let k = comps.len().saturating_sub(n);
        let root: PathBuf = comps[..k].iter().collect();
        let rel: PathBuf = comps[k..].iter().collect();
        Within::new(root, rel)
    }

    /// The file's path, for messages and for writing beside it.
    pub fn path(&self) -> PathBuf {
        if self.root.as_os_str().is_empty() {
            self.rel.clone()
        } else {
            self.root.join(&self.rel)
        }
    }

    /// Whether there is something at the file's place, following no link: a link on the
    /// way, or in the file's place, counts (reading it is then refused, naming the link),
    /// so that a stage says "cannot read" rather than "missing, run the stage first".
    pub fn is_there(&self) -> bool {
        let mut p = self.root.clone();
        for c in self.rel.components() {
            p.push(c);
            match fs::symlink_metadata(&p) {
                Ok(m) if m.file_type().is_symlink() => return true,
                Ok(_) => {}
                Err(_) => return false,
            }
        }
        true
    }

    /// Open the file for reading (see [`Within`]): every folder below the root through no
    /// link, the file itself a regular file (no link, FIFO or device), never blocking.
    pub fn open(&self) -> io::Result<File> {
        use std::ffi::CString;
        use std::os::fd::{AsRawFd, FromRawFd};
        use std::os::unix::ffi::OsStrExt;
        let mut names = Vec::new();
        for c in self.rel.components() {
            match c {
                Component::Normal(n) => names.push(n),
                _ => {
                    return Err(invalid(format!(
                        "{} must be a relative path of plain names (no `..`, `.` or leading `/`)",
                        quote(&self.rel.to_string_lossy())
                    )))
                }
            }
        }
        let Some((_, folders)) = names.split_last() else {
            return Err(invalid("the path is empty".into()));
        };
        let root = if self.root.as_os_str().is_empty() {
            Path::new(".")
        } else {
            &self.root
        };
        let mut at = OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_DIRECTORY | libc::O_CLOEXEC)
            .open(root)?;
        for (i, name) in names.iter().enumerate() {
            let last = i == folders.len();
            let c = CString::new(name.as_bytes())
                .map_err(|_| invalid("a name with a NUL byte".into()))?;
            let flags = libc::O_RDONLY
                | libc::O_NOFOLLOW
                | libc::O_CLOEXEC
                | if last {
                    libc::O_NONBLOCK
                } else {
                    libc::O_DIRECTORY
                };
            // SAFETY: `at` is an open folder and `c` a NUL-terminated name; the descriptor
            // returned (if any) is owned by the File made from it.
            let fd = unsafe { libc::openat(at.as_raw_fd(), c.as_ptr(), flags) };
            if fd < 0 {
                let e = io::Error::last_os_error();
                let so_far: PathBuf = names[..=i].iter().collect();
                return Err(self.explain(&so_far, last, e));
            }
            // SAFETY: `fd` is a descriptor just opened and owned by nothing else.
            at = unsafe { File::from_raw_fd(fd) };
        }
        let meta = at.metadata()?;
        if !meta.file_type().is_file() {
            return Err(invalid(format!(
                "is not a regular file ({}); Glint reads only regular files here",
                describe_type(&meta.file_type())
            )));
        }
        Ok(at)
    }

    /// What an `openat` error on the way to the file means: a link (named, with where it
    /// points, and what to do), something other than a folder, or the error as it is.
    fn explain(&self, so_far: &Path, last: bool, e: io::Error) -> io::Error {
        let code = e.raw_os_error();
        if code != Some(libc::ELOOP) && code != Some(libc::ENOTDIR) {
            return e;
        }
        let place = self.root.join(so_far);
        let Ok(meta) = fs::symlink_metadata(&place) else {
            return e;
        };
        let to = fs::read_link(&place)
            .map(|t| format!(" to {}", quote(&t.to_string_lossy())))
            .unwrap_or_default();
        let named = quote(&so_far.to_string_lossy());
        match (meta.file_type().is_symlink(), last) {
            (true, true) => invalid(format!(
                "is a symbolic link{to}; Glint reads only regular files here, never through a link: put the file itself in its place"
            )),
            (true, false) => invalid(format!(
                "{named} is a symbolic link{to}; Glint reads the files below {} only through real folders, never a link: put the folder itself in its place, or remove the link and re-run the stage that writes it",
                quote(&self.root.to_string_lossy())
            )),
            (false, _) => invalid(format!(
                "{named} is not a folder ({}); move it away",
                describe_type(&meta.file_type())
            )),
        }
    }

    /// Read the file (see [`Within::open`]): at most `cap` bytes.
    pub fn read(&self, cap: u64) -> io::Result<Vec<u8>> {
        read_open(self.open()?, cap)
    }

    /// [`Within::read`] as UTF-8 text.
    pub fn read_text(&self, cap: u64) -> io::Result<String> {
        utf8(self.read(cap)?)
    }
}

impl From<&Path> for Within {
    /// A file the user named ([`Within::file`]).
    fn from(p: &Path) -> Within {
        Within::file(p)
    }
}

impl From<&PathBuf> for Within {
    fn from(p: &PathBuf) -> Within {
        Within::file(p)
    }
}

impl From<&Within> for Within {
    fn from(w: &Within) -> Within {
        w.clone()
    }
}

/// Why a relative path named inside a file may not be followed ([`inside`]); the path,
/// quoted, and what is wrong with it, for the caller to put after the file's name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NotInside {
    #[error("the path is empty")]
    Empty,
    #[error("{} is not a usable path (too long or has a NUL byte)", quote(.rel))]
    Unusable { rel: String },
    #[error("{} passes through a symbolic link ({}); a session's files must be inside it", quote(.rel), quote(.link))]
    Link { rel: String, link: String },
    #[error("{} must be a relative path inside the session (plain names, no `..`, `.` or leading `/`)", quote(.rel))]
    NotRelative { rel: String },
    #[error("{} names a folder, not a file", quote(.rel))]
    Folder { rel: String },
}

/// Check a relative path named inside a file (a manifest's frame) and join it to `dir`:
/// relative, plain names only (no `..`, `.`, root or empty parts), no NUL, at most 4096
/// bytes, and no symbolic link on the way from `dir` to the file (the file itself is
/// checked when opened with [`open_regular`]). The error says what is wrong, for the
/// caller to put after the path.
pub fn inside(dir: &Path, rel: &str) -> Result<PathBuf, NotInside> {
    if rel.is_empty() {
        return Err(NotInside::Empty);
    }
    if rel.len() > 4096 || rel.contains('\0') {
        return Err(NotInside::Unusable { rel: rel.into() });
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
                            return Err(NotInside::Link {
                                rel: rel.into(),
                                link: name.to_string_lossy().into_owned(),
                            })
                        }
                        _ => {}
                    }
                }
            }
            _ => return Err(NotInside::NotRelative { rel: rel.into() }),
        }
    }
    if rel.ends_with('/') {
        return Err(NotInside::Folder { rel: rel.into() });
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
            .to_string()
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
    fn within_reads_through_real_folders_only() {
        let d = tempfile::tempdir().unwrap();
        let s = d.path().join("s");
        fs::create_dir_all(s.join("hdr")).unwrap();
        fs::write(s.join("hdr/a.json"), b"{}").unwrap();
        let w = Within::new(&s, "hdr/a.json");
        assert_eq!(w.read(10).unwrap(), b"{}");
        assert!(w.is_there() && !Within::new(&s, "hdr/b.json").is_there());
        assert!(w.read(1).unwrap_err().to_string().contains("more than"));
        // A hard link is a regular file.
        fs::hard_link(s.join("hdr/a.json"), s.join("hdr/h.json")).unwrap();
        assert_eq!(Within::new(&s, "hdr/h.json").read(10).unwrap(), b"{}");
        // The folder moved out and linked back: refused, naming the link and the fix.
        fs::rename(s.join("hdr"), d.path().join("x")).unwrap();
        std::os::unix::fs::symlink(d.path().join("x"), s.join("hdr")).unwrap();
        assert!(w.is_there());
        let e = w.read(10).unwrap_err().to_string();
        assert!(
            e.contains("`hdr` is a symbolic link") && e.contains("put the folder itself"),
            "{e}"
        );
        // The file a link; a file where a folder should be; plain names only.
        fs::remove_file(s.join("hdr")).unwrap();
        fs::create_dir(s.join("hdr")).unwrap();
        std::os::unix::fs::symlink(d.path().join("x/a.json"), s.join("hdr/a.json")).unwrap();
        let e = w.read(10).unwrap_err().to_string();
        assert!(e.contains("is a symbolic link"), "{e}");
        fs::write(s.join("fit"), b"").unwrap();
        let e = Within::new(&s, "fit/fit.json").read(10).unwrap_err();
        assert!(e.to_string().contains("`fit` is not a folder"), "{e}");
        for bad in ["../x/a.json", "/etc/passwd", "hdr/../../x/a.json"] {
            assert!(Within::new(&s, bad).read(10).is_err(), "{bad}");
        }
        assert_eq!(
            Within::new(&s, "nothing").read(10).unwrap_err().kind(),
            io::ErrorKind::NotFound
        );
        // A device is refused, and a file the user named is read from its own folder.
        assert!(Within::file(Path::new("/dev/zero")).read(10).is_err());
        assert_eq!(
            Within::file(&d.path().join("x/a.json")).read(10).unwrap(),
            b"{}"
        );
        assert_eq!(
            Within::last(&s.join("profiles/p.json"), 2),
            Within::new(&s, "profiles/p.json")
        );
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
