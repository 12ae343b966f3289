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

use anyhow::{anyhow, bail, Context, Result};

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

/// A group by name: its gid.
pub fn group_id(name: &str) -> Result<u32> {
    let c = std::ffi::CString::new(name).map_err(|_| anyhow!("--group: not a group name"))?;
    // SAFETY: getgrnam reads a NUL-terminated name; the result is read at once, before any
    // other call that could reuse its static buffer.
    let g = unsafe { libc::getgrnam(c.as_ptr()) };
    if g.is_null() {
        bail!("--group {name}: no such group (see /etc/group)");
    }
    // SAFETY: g is non-null and points to a valid struct group.
    Ok(unsafe { (*g).gr_gid })
}

/// Make (or check) the socket's folder: a real folder owned by this user, mode 0700 (0750
/// and the group `gid` with `--group`). Its parent is created as needed.
pub fn socket_dir(dir: &Path, gid: Option<u32>) -> Result<()> {
    let mode = if gid.is_some() { 0o750 } else { 0o700 };
    match fs::symlink_metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if let Some(parent) = dir.parent() {
                fs::create_dir_all(parent)
                    .with_context(|| format!("creating {}", parent.display()))?;
            }
            fs::DirBuilder::new()
                .mode(mode)
                .create(dir)
                .with_context(|| format!("creating the socket folder {}", dir.display()))?;
        }
        Err(e) => return Err(e).with_context(|| format!("checking {}", dir.display())),
        Ok(m) if !m.is_dir() => bail!(
            "{} is not a folder (a link or a file); give --socket in a folder of your own",
            dir.display()
        ),
        Ok(m) if m.uid() != euid() => bail!(
            "the socket folder {} belongs to uid {}, not to this user ({}); remove it or give another --socket",
            dir.display(),
            m.uid(),
            euid()
        ),
        Ok(_) => {}
    }
    if let Some(g) = gid {
        std::os::unix::fs::chown(dir, None, Some(g))
            .with_context(|| format!("giving {} to the group", dir.display()))?;
    }
    fs::set_permissions(dir, fs::Permissions::from_mode(mode))
        .with_context(|| format!("making {} owner-only", dir.display()))?;
    Ok(())
}

/// An exclusive lock on `path` (created), held while the returned file is open. `Err`
/// names the daemon that holds it.
pub fn lock(path: &Path, what: &str) -> Result<File> {
    let f = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .open(path)
        .with_context(|| format!("opening the lock {}", path.display()))?;
    use std::os::fd::AsRawFd;
    // SAFETY: flock on a valid open descriptor.
    if unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        let holder = crate::fsx::read_text_capped(path, 64).unwrap_or_default();
        let holder = holder.trim();
        bail!(
            "another glint daemon already serves {what}{}; stop it first (`glint daemon stop`)",
            if holder.is_empty() {
                String::new()
            } else {
                format!(" (pid {})", crate::fsx::quote(holder))
            }
        );
    }
    let _ = f.set_len(0);
    use std::io::Write;
    let _ = (&f).write_all(std::process::id().to_string().as_bytes());
    Ok(f)
}

/// Remove a socket left by a daemon that died (the caller holds the lock, so no daemon
/// serves it). Anything there that is not a socket is refused, not removed.
pub fn remove_stale_socket(path: &Path) -> Result<()> {
    use std::os::unix::fs::FileTypeExt;
    match fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e).with_context(|| format!("checking {}", path.display())),
        Ok(m) if m.file_type().is_socket() => {
            tracing::warn!(
                "removing the stale socket {} (its daemon is gone)",
                path.display()
            );
            fs::remove_file(path).with_context(|| format!("removing {}", path.display()))
        }
        Ok(_) => bail!(
            "{} exists and is not a socket; remove it or give another --socket",
            path.display()
        ),
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
