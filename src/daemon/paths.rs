//! Where the daemon lives on disk, and the socket's security.
//!
//! Defaults follow the XDG base directories and `/run` (systemd's `RuntimeDirectory=` and
//! `StateDirectory=` set `$RUNTIME_DIRECTORY` and `$STATE_DIRECTORY`, which win):
//!
//! | | root | another user |
//! | --- | --- | --- |
//! | socket | `/run/glint/glint.sock` | `$XDG_RUNTIME_DIR/glint/glint.sock`, else `/tmp/glint-UID/glint.sock` |
//! | state | `/var/lib/glint` | `$XDG_STATE_HOME/glint`, else `~/.local/state/glint` |
//!
//! The socket sits in a folder only its owner can enter (mode 0700, or 0750 with the
//! group of `--group`), owned by the daemon's user; a folder that exists with another
//! owner or wider modes is refused rather than trusted. A lock file beside the socket
//! (`flock`, released by the kernel when the daemon dies however it dies) tells a second
//! daemon apart from a stale socket left by a crash, which is removed.

use std::fs::{self, File, OpenOptions};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

fn env_path(key: &str) -> Option<PathBuf> {
    std::env::var_os(key)
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .filter(|p| p.is_absolute())
}

fn euid() -> u32 {
    // SAFETY: geteuid has no preconditions and cannot fail.
    unsafe { libc::geteuid() }
}

/// The socket clients use by default: `$GLINT_SOCKET`, else the daemon's default.
pub fn client_socket() -> PathBuf {
    env_path("GLINT_SOCKET").unwrap_or_else(default_socket)
}

/// The daemon's default socket.
pub fn default_socket() -> PathBuf {
    let dir = env_path("RUNTIME_DIRECTORY")
        .or_else(|| (euid() == 0).then(|| PathBuf::from("/run/glint")))
        .or_else(|| env_path("XDG_RUNTIME_DIR").map(|d| d.join("glint")))
        .unwrap_or_else(|| PathBuf::from(format!("/tmp/glint-{}", euid())));
    dir.join("glint.sock")
}

/// The daemon's default state folder (journal, lock).
pub fn default_state_dir() -> PathBuf {
    env_path("STATE_DIRECTORY")
        .or_else(|| (euid() == 0).then(|| PathBuf::from("/var/lib/glint")))
        .or_else(|| env_path("XDG_STATE_HOME").map(|d| d.join("glint")))
        .or_else(|| env_path("HOME").map(|h| h.join(".local/state/glint")))
        .unwrap_or_else(|| PathBuf::from(format!("/tmp/glint-{}-state", euid())))
}

/// The daemon's folders, socket, locks and group that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum PathsError {
    #[error("--group: not a group name")]
    NotAGroupName,
    #[error("--group {name}: no such group (see /etc/group)")]
    NoSuchGroup { name: String },
    /// `op` says what was being done to `path` ("creating", "checking", "removing").
    #[error("{op} {}", .path.display())]
    Io {
        op: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("creating the socket folder {}", .dir.display())]
    SocketDir {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("giving {} to the group", .path.display())]
    Group {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("making {} owner-only", .dir.display())]
    OwnerOnly {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("opening the lock {}", .path.display())]
    OpenLock {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{} is not a folder (a link or a file); give --socket in a folder of your own", .dir.display())]
    NotAFolder { dir: PathBuf },
    #[error("the socket folder {} belongs to uid {uid}, not to this user ({euid}); remove it or give another --socket", .dir.display())]
    NotOwned { dir: PathBuf, uid: u32, euid: u32 },
    /// `holder`: the pid the lock file names, if any.
    #[error("another glint daemon already serves {what}{}; stop it first (`glint daemon stop`)", if .holder.is_empty() { String::new() } else { format!(" (pid {})", crate::fsx::quote(.holder)) })]
    Locked { what: String, holder: String },
    #[error("{} exists and is not a socket; remove it or give another --socket", .path.display())]
    NotASocket { path: PathBuf },
}

fn io(op: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> PathsError {
    let path = path.to_path_buf();
    move |source| PathsError::Io { op, path, source }
}

/// A group by name: its gid.
pub fn group_id(name: &str) -> Result<u32, PathsError> {
    let c = std::ffi::CString::new(name).map_err(|_| PathsError::NotAGroupName)?;
    // SAFETY: getgrnam reads a NUL-terminated name; the result is read at once, before any
    // other call that could reuse its static buffer.
    let g = unsafe { libc::getgrnam(c.as_ptr()) };
    if g.is_null() {
        return Err(PathsError::NoSuchGroup { name: name.into() });
    }
    // SAFETY: g is non-null and points to a valid struct group.
    Ok(unsafe { (*g).gr_gid })
}

/// Make (or check) the socket's folder: a real folder owned by this user, mode 0700 (0750
/// and the group `gid` with `--group`). Its parent is created as needed.
pub fn socket_dir(dir: &Path, gid: Option<u32>) -> Result<(), PathsError> {
    let mode = if gid.is_some() { 0o750 } else { 0o700 };
    match fs::symlink_metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if let Some(parent) = dir.parent() {
                fs::create_dir_all(parent).map_err(io("creating", parent))?;
            }
            fs::DirBuilder::new()
                .mode(mode)
                .create(dir)
                .map_err(|source| PathsError::SocketDir {
                    dir: dir.into(),
                    source,
                })?;
        }
        Err(e) => return Err(io("checking", dir)(e)),
        Ok(m) if !m.is_dir() => return Err(PathsError::NotAFolder { dir: dir.into() }),
        Ok(m) if m.uid() != euid() => {
            return Err(PathsError::NotOwned {
                dir: dir.into(),
                uid: m.uid(),
                euid: euid(),
            })
        }
        Ok(_) => {}
    }
    if let Some(g) = gid {
        std::os::unix::fs::chown(dir, None, Some(g)).map_err(|source| PathsError::Group {
            path: dir.into(),
            source,
        })?;
    }
    fs::set_permissions(dir, fs::Permissions::from_mode(mode)).map_err(|source| {
        PathsError::OwnerOnly {
            dir: dir.into(),
            source,
        }
    })?;
    Ok(())
}

/// An exclusive lock on `path` (created), held while the returned file is open. `Err`
/// names the daemon that holds it.
pub fn lock(path: &Path, what: &str) -> Result<File, PathsError> {
    let f = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .map_err(|source| PathsError::OpenLock {
            path: path.into(),
            source,
        })?;
    use std::os::fd::AsRawFd;
    // SAFETY: flock on a valid open descriptor.
    if unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        let holder = crate::fsx::read_text_capped(path, 64).unwrap_or_default();
        return Err(PathsError::Locked {
            what: what.into(),
            holder: holder.trim().into(),
        });
    }
    let _ = f.set_len(0);
    use std::io::Write;
    let _ = (&f).write_all(std::process::id().to_string().as_bytes());
    Ok(f)
}

/// Remove a socket left by a daemon that died (the caller holds the lock, so no daemon
/// serves it). Anything there that is not a socket is refused, not removed.
pub fn remove_stale_socket(path: &Path) -> Result<(), PathsError> {
    use std::os::unix::fs::FileTypeExt;
    match fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io("checking", path)(e)),
        Ok(m) if m.file_type().is_socket() => {
            tracing::warn!(
                "removing the stale socket {} (its daemon is gone)",
                path.display()
            );
            fs::remove_file(path).map_err(io("removing", path))
        }
        Ok(_) => Err(PathsError::NotASocket { path: path.into() }),
    }
}

/// Whether a peer may use the daemon: the daemon's own user, root, or (with `--group`) a
/// member of the group (its primary group, or a supplementary one read from
/// `/proc/PID/status`).
pub fn peer_allowed(uid: u32, gid: u32, pid: Option<i32>, group: Option<u32>) -> bool {
    if uid == euid() || uid == 0 {
        return true;
    }
    let Some(g) = group else { return false };
    if gid == g {
        return true;
    }
    let Some(pid) = pid else { return false };
    let Ok(status) =
        crate::fsx::read_text_capped(Path::new(&format!("/proc/{pid}/status")), 1 << 20)
    else {
        return false;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("Groups:"))
        .is_some_and(|gs| gs.split_whitespace().any(|x| x.parse() == Ok(g)))
}
