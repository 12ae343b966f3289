//! # glint-sim-v4l2: a simulated V4L2 camera for any Linux program
//!
//! Loaded with `LD_PRELOAD`, this library makes one path (env `GLINT_SIM_V4L2_DEVICE`,
//! compared by the file it resolves to, so `/dev/v4l/by-id/...` symbolic links work) behave
//! as a V4L2 video capture device: a UVC webcam with mmap streaming. The camera behind it is
//! the simulated lab of `glint-mock`, which `glint-mock v4l2 --rig RIG -- CMD` runs and
//! serves on a Unix socket (env `GLINT_SIM_V4L2_SOCKET`). It is the same idea as libcamera's
//! V4L2 compatibility layer: the interception set is its set (`open`, `open64`, `openat`,
//! `openat64`, `__open_2`, `__open64_2`, `close`, `ioctl`, `mmap`, `mmap64`, `munmap`),
//! plus `syscall` (the `v4l` crate issues `ioctl` as `syscall(SYS_ioctl, ...)`) and `poll`,
//! `ppoll`, `select` (frames become ready in the launcher, not in the kernel).
//!
//! Opening the device opens the placeholder file the launcher made there (so the program
//! holds a real descriptor that `fstat`, `fcntl` and `close` accept) and connects to the
//! launcher; that descriptor then answers V4L2 ioctls (see [`device`]). Everything else
//! goes to the real functions (`dlsym(RTLD_NEXT)`).
//!
//! ## Rules that keep the hooks safe
//! - The C functions are variadic; they are defined here with fixed integer arguments,
//!   which receive them correctly on x86-64 and aarch64 (SysV: the same registers).
//! - Nothing the library does for another path or descriptor allocates or locks beyond one
//!   short table lookup, skipped entirely while no simulated file is open; calls made from
//!   inside (the socket, `memfd_create`) reach the hooks only as forwarded calls.
//! - The table of open simulated files is never locked while a hook runs another hook.
//! - No panic unwinds out of a hook (that would abort the program): every simulated path
//!   runs under `catch_unwind` and a panic becomes EIO.
//! - A child forked while a simulated file is open does not inherit it (the connection to
//!   the launcher belongs to the parent): in the child the descriptor is the placeholder
//!   file it is, and the table is empty and unlocked, whichever thread held it at the fork.
//!
//! ## The socket protocol (one request line, one reply line; `OK ...` or `ERR <errno>`)
//! `STATE` (the device: `formats=`, `sizes=`, `intervals=`, `fmt=`, `width=`, `height=`,
//! `interval=`, `ctrl.<hex id>=<value>`), `SET key=value ...`, `CLAIM`/`RELEASE` (buffers),
//! `STREAMON`, `STREAMOFF`, `POLL <ms>` (`OK 1` when a frame is ready), `DQBUF <nonblock>`
//! (`FRAME seq= ts= error= bytes=N` then N bytes). The launcher answers `ERR 19` (ENODEV)
//! to everything once the camera is unplugged.

mod abi;
mod device;
mod link;

use std::cell::UnsafeCell;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Once};

use libc::{c_char, c_int, c_long, c_ulong, c_void, nfds_t, off_t, pollfd, size_t};

use device::{Readiness, SimFile};

/// Resolve the next definition of a C function (the real one), once.
macro_rules! real {
    ($name:literal: $ty:ty) => {{
        static PTR: AtomicUsize = AtomicUsize::new(0);
        let mut p = PTR.load(Ordering::Relaxed);
        if p == 0 {
            // SAFETY: dlsym with a NUL-terminated name.
            p = unsafe {
                libc::dlsym(
                    libc::RTLD_NEXT,
                    concat!($name, "\0").as_ptr() as *const c_char,
                )
            } as usize;
            PTR.store(p, Ordering::Relaxed);
        }
        // SAFETY: the symbol has the C signature `$ty`; null becomes None.
        unsafe { std::mem::transmute::<usize, Option<$ty>>(p) }
    }};
}

type OpenFn = unsafe extern "C" fn(*const c_char, c_int, libc::mode_t) -> c_int;
type OpenatFn = unsafe extern "C" fn(c_int, *const c_char, c_int, libc::mode_t) -> c_int;
type Open2Fn = unsafe extern "C" fn(*const c_char, c_int) -> c_int;
type CloseFn = unsafe extern "C" fn(c_int) -> c_int;
type IoctlFn = unsafe extern "C" fn(c_int, c_ulong, *mut c_void) -> c_int;
type SyscallFn =
    unsafe extern "C" fn(c_long, c_long, c_long, c_long, c_long, c_long, c_long) -> c_long;
type MmapFn = unsafe extern "C" fn(*mut c_void, size_t, c_int, c_int, c_int, off_t) -> *mut c_void;
type MunmapFn = unsafe extern "C" fn(*mut c_void, size_t) -> c_int;
type PollFn = unsafe extern "C" fn(*mut pollfd, nfds_t, c_int) -> c_int;
type PpollFn = unsafe extern "C" fn(
    *mut pollfd,
    nfds_t,
    *const libc::timespec,
    *const libc::sigset_t,
) -> c_int;
type SelectFn = unsafe extern "C" fn(
    c_int,
    *mut libc::fd_set,
    *mut libc::fd_set,
    *mut libc::fd_set,
    *mut libc::timeval,
) -> c_int;

fn set_errno(e: c_int) {
    // SAFETY: the calling thread's errno.
    unsafe { *libc::__errno_location() = e };
}

fn missing(name: &str) -> c_int {
    let _ = name;
    set_errno(libc::ENOSYS);
    -1
}

/// Run a hook's simulated path; a panic in it becomes `fallback` with errno EIO rather
/// than an unwind across the C boundary.
fn guarded<R>(fallback: R, f: impl FnOnce() -> R) -> R {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|_| {
        set_errno(libc::EIO);
        fallback
    })
}

/// The real `mmap`, for the library's own mappings of its buffers.
pub(crate) fn real_mmap(
    addr: *mut c_void,
    len: size_t,
    prot: c_int,
    flags: c_int,
    fd: c_int,
    off: off_t,
) -> *mut c_void {
    match real!("mmap": MmapFn) {
        // SAFETY: the C function, with the caller's arguments.
        Some(real) => unsafe { real(addr, len, prot, flags, fd, off) },
        None => libc::MAP_FAILED,
    }
}

/// The real `munmap`.
pub(crate) fn real_munmap(addr: *mut c_void, len: size_t) {
    if let Some(real) = real!("munmap": MunmapFn) {
        // SAFETY: unmapping a mapping this library made.
        unsafe { real(addr, len) };
    }
}

// ---------------------------------------------------------------------------------------
// The table of open simulated files: a spin lock around a short list, so that a fork can
// take it (no thread is then half-way through it) and the child can reset it.

type Entry = (c_int, Arc<Mutex<SimFile>>);

struct Table {
    locked: AtomicBool,
    entries: UnsafeCell<Vec<Entry>>,
}

// SAFETY: `entries` is only reached through `with`, under `locked`.
unsafe impl Sync for Table {}

struct Unlock<'a>(&'a AtomicBool);

impl Drop for Unlock<'_> {
    fn drop(&mut self) {
        self.0.store(false, Ordering::Release);
    }
}

impl Table {
    fn acquire(&self) {
        while self
            .locked
            .compare_exchange_weak(false, true, Ordering::Acquire, Ordering::Relaxed)
            .is_err()
        {
            std::thread::yield_now();
        }
    }

    fn with<R>(&self, f: impl FnOnce(&mut Vec<Entry>) -> R) -> R {
        self.acquire();
        let _unlock = Unlock(&self.locked);
        // SAFETY: the lock is held until `_unlock` drops.
        f(unsafe { &mut *self.entries.get() })
    }
}

static TABLE: Table = Table {
    locked: AtomicBool::new(false),
    entries: UnsafeCell::new(Vec::new()),
};
/// How many simulated files are open: while 0, no hook touches the table.
static OPEN: AtomicUsize = AtomicUsize::new(0);

fn lookup(fd: c_int) -> Option<Arc<Mutex<SimFile>>> {
    if fd < 0 || OPEN.load(Ordering::Acquire) == 0 {
        return None;
    }
    TABLE.with(|t| t.iter().find(|(f, _)| *f == fd).map(|(_, s)| Arc::clone(s)))
}

fn remove(fd: c_int) -> Option<Arc<Mutex<SimFile>>> {
    if fd < 0 || OPEN.load(Ordering::Acquire) == 0 {
        return None;
    }
    TABLE.with(|t| {
        let i = t.iter().position(|(f, _)| *f == fd)?;
        OPEN.fetch_sub(1, Ordering::AcqRel);
        Some(t.swap_remove(i).1)
    })
}

fn insert(fd: c_int, file: SimFile) {
    static AT_FORK: Once = Once::new();
    AT_FORK.call_once(|| {
        // SAFETY: registering plain functions.
        unsafe { libc::pthread_atfork(Some(fork_prepare), Some(fork_parent), Some(fork_child)) };
    });
    let file = Arc::new(Mutex::new(file));
    TABLE.with(|t| {
        t.push((fd, file));
        OPEN.fetch_add(1, Ordering::AcqRel);
    });
}

extern "C" fn fork_prepare() {
    TABLE.acquire();
}

extern "C" fn fork_parent() {
    TABLE.locked.store(false, Ordering::Release);
}

extern "C" fn fork_child() {
    // The entries are the parent's: forgotten, not dropped (dropping would talk to, or
    // close, what the parent still uses; the child's copies of the descriptors stay open
    // as ordinary files).
    // SAFETY: the lock is held (taken in fork_prepare) and this is the only thread.
    let entries = unsafe { std::mem::take(&mut *TABLE.entries.get()) };
    std::mem::forget(entries);
    OPEN.store(0, Ordering::Release);
    TABLE.locked.store(false, Ordering::Release);
}

// ---------------------------------------------------------------------------------------
// Which path is the simulated device: compared by (device, inode) after following links.

fn device_id() -> Option<(u64, u64)> {
    // SAFETY: getenv's result is read at once; stat fills the struct it is given.
    unsafe {
        let p = libc::getenv(c"GLINT_SIM_V4L2_DEVICE".as_ptr());
        if p.is_null() || *p == 0 {
            return None;
        }
        let mut st: libc::stat = std::mem::zeroed();
        if libc::fstatat(libc::AT_FDCWD, p, &mut st, 0) != 0 {
            return None;
        }
        Some((st.st_dev, st.st_ino))
    }
}

fn is_device(dirfd: c_int, path: *const c_char) -> bool {
    if path.is_null() {
        return false;
    }
    let Some(id) = device_id() else {
        return false;
    };
    // SAFETY: path is the caller's NUL-terminated string; fstatat fills `st`.
    unsafe {
        let mut st: libc::stat = std::mem::zeroed();
        libc::fstatat(dirfd, path, &mut st, 0) == 0 && (st.st_dev, st.st_ino) == id
    }
}

/// Open the simulated device: the placeholder file, and a connection to the launcher.
fn open_device(
    dirfd: c_int,
    path: *const c_char,
    flags: c_int,
    real: impl FnOnce(c_int) -> c_int,
) -> c_int {
    guarded(-1, || open_device_inner(dirfd, path, flags, real))
}

fn open_device_inner(
    dirfd: c_int,
    path: *const c_char,
    flags: c_int,
    real: impl FnOnce(c_int) -> c_int,
) -> c_int {
    let socket = std::env::var("GLINT_SIM_V4L2_SOCKET").unwrap_or_default();
    let link = match link::Link::connect(&socket) {
        Ok(l) => l,
        Err(_) => {
            set_errno(libc::ENODEV);
            return -1;
        }
    };
    let _ = (dirfd, path);
    let fd = real(flags & !(libc::O_CREAT | libc::O_TRUNC | libc::O_EXCL));
    if fd < 0 {
        return fd;
    }
    let mut file = SimFile::new(link, fd);
    // A camera that is gone cannot be opened.
    if let Readiness::Error { gone: true } = file.poll(0) {
        drop(file);
        if let Some(close) = real!("close": CloseFn) {
            // SAFETY: closing the descriptor just opened.
            unsafe { close(fd) };
        }
        set_errno(libc::ENODEV);
        return -1;
    }
    insert(fd, file);
    fd
}

// ---------------------------------------------------------------------------------------
// open and friends.

/// `open`, `open64`: the simulated device, else the real function.
unsafe fn open_hook(
    real: Option<OpenFn>,
    name: &str,
    path: *const c_char,
    flags: c_int,
    mode: libc::mode_t,
) -> c_int {
    let Some(real) = real else {
        return missing(name);
    };
    if is_device(libc::AT_FDCWD, path) {
        return open_device(libc::AT_FDCWD, path, flags, |f| real(path, f, mode));
    }
    real(path, flags, mode)
}

/// `__open_2`, `__open64_2` (the fortified `open` without a mode).
unsafe fn open2_hook(
    real: Option<Open2Fn>,
    name: &str,
    path: *const c_char,
    flags: c_int,
) -> c_int {
    let Some(real) = real else {
        return missing(name);
    };
    if is_device(libc::AT_FDCWD, path) {
        return open_device(libc::AT_FDCWD, path, flags, |f| real(path, f));
    }
    real(path, flags)
}

/// `openat`, `openat64`.
unsafe fn openat_hook(
    real: Option<OpenatFn>,
    name: &str,
    dirfd: c_int,
    path: *const c_char,
    flags: c_int,
    mode: libc::mode_t,
) -> c_int {
    let Some(real) = real else {
        return missing(name);
    };
    if is_device(dirfd, path) {
        return open_device(dirfd, path, flags, |f| real(dirfd, path, f, mode));
    }
    real(dirfd, path, flags, mode)
}

/// # Safety
/// C `open`.
#[no_mangle]
pub unsafe extern "C" fn open(path: *const c_char, flags: c_int, mode: libc::mode_t) -> c_int {
    open_hook(real!("open": OpenFn), "open", path, flags, mode)
}

/// # Safety
/// C `open64`.
#[no_mangle]
pub unsafe extern "C" fn open64(path: *const c_char, flags: c_int, mode: libc::mode_t) -> c_int {
    open_hook(real!("open64": OpenFn), "open64", path, flags, mode)
}

/// # Safety
/// C `__open_2` (the fortified `open` without a mode).
#[no_mangle]
pub unsafe extern "C" fn __open_2(path: *const c_char, flags: c_int) -> c_int {
    open2_hook(real!("__open_2": Open2Fn), "__open_2", path, flags)
}

/// # Safety
/// C `__open64_2`.
#[no_mangle]
pub unsafe extern "C" fn __open64_2(path: *const c_char, flags: c_int) -> c_int {
    open2_hook(real!("__open64_2": Open2Fn), "__open64_2", path, flags)
}

/// # Safety
/// C `openat`.
#[no_mangle]
pub unsafe extern "C" fn openat(
    dirfd: c_int,
    path: *const c_char,
    flags: c_int,
    mode: libc::mode_t,
) -> c_int {
    openat_hook(
        real!("openat": OpenatFn),
        "openat",
        dirfd,
        path,
        flags,
        mode,
    )
}

/// # Safety
/// C `openat64`.
#[no_mangle]
pub unsafe extern "C" fn openat64(
    dirfd: c_int,
    path: *const c_char,
    flags: c_int,
    mode: libc::mode_t,
) -> c_int {
    openat_hook(
        real!("openat64": OpenatFn),
        "openat64",
        dirfd,
        path,
        flags,
        mode,
    )
}

/// # Safety
/// C `close`.
#[no_mangle]
pub unsafe extern "C" fn close(fd: c_int) -> c_int {
    let Some(real) = real!("close": CloseFn) else {
        return missing("close");
    };
    // Dropped after the table's lock is released: dropping closes the socket and the
    // buffers' memfds through this very hook.
    guarded((), || drop(remove(fd)));
    real(fd)
}

// ---------------------------------------------------------------------------------------
// ioctl, and syscall for programs that issue ioctl, openat and close as raw system calls.

fn sim_ioctl(file: &Mutex<SimFile>, req: c_ulong, arg: *mut c_void) -> c_int {
    guarded(-1, || {
        let mut f = file.lock().unwrap_or_else(|e| e.into_inner());
        // SAFETY: `arg` is what the program passed with `req`.
        match unsafe { f.ioctl(req as u32, arg) } {
            Ok(()) => 0,
            Err(e) => {
                set_errno(e);
                -1
            }
        }
    })
}

/// # Safety
/// C `ioctl` (glibc: `int ioctl(int, unsigned long, ...)`).
#[no_mangle]
pub unsafe extern "C" fn ioctl(fd: c_int, req: c_ulong, arg: *mut c_void) -> c_int {
    if let Some(file) = lookup(fd) {
        return sim_ioctl(&file, req, arg);
    }
    match real!("ioctl": IoctlFn) {
        Some(real) => real(fd, req, arg),
        None => missing("ioctl"),
    }
}

/// # Safety
/// C `syscall` (`long syscall(long number, ...)`, at most six arguments).
#[no_mangle]
pub unsafe extern "C" fn syscall(
    n: c_long,
    a1: c_long,
    a2: c_long,
    a3: c_long,
    a4: c_long,
    a5: c_long,
    a6: c_long,
) -> c_long {
    let Some(real) = real!("syscall": SyscallFn) else {
        return missing("syscall") as c_long;
    };
    match n {
        libc::SYS_ioctl => {
            if let Some(file) = lookup(a1 as c_int) {
                return sim_ioctl(&file, a2 as c_ulong, a3 as *mut c_void) as c_long;
            }
        }
        libc::SYS_openat => {
            let (dirfd, path) = (a1 as c_int, a2 as *const c_char);
            if is_device(dirfd, path) {
                return open_device(dirfd, path, a3 as c_int, |f| {
                    real(n, a1, a2, f as c_long, a4, 0, 0) as c_int
                }) as c_long;
            }
        }
        libc::SYS_close => {
            guarded((), || drop(remove(a1 as c_int)));
        }
        _ => {}
    }
    real(n, a1, a2, a3, a4, a5, a6)
}

// ---------------------------------------------------------------------------------------
// mmap: a buffer's offset maps the memfd that holds it.

unsafe fn sim_mmap(
    addr: *mut c_void,
    len: size_t,
    prot: c_int,
    flags: c_int,
    fd: c_int,
    off: off_t,
) -> Option<*mut c_void> {
    let file = lookup(fd)?;
    let target = file
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .mmap_target(off, len);
    let Some(memfd) = target else {
        set_errno(libc::EINVAL);
        return Some(libc::MAP_FAILED);
    };
    let real = real!("mmap": MmapFn)?;
    Some(real(addr, len, prot, flags, memfd, 0))
}

/// `mmap` and `mmap64`: the simulated device's buffers, else the real function.
unsafe fn mmap_hook(
    real: Option<MmapFn>,
    addr: *mut c_void,
    len: size_t,
    prot: c_int,
    flags: c_int,
    fd: c_int,
    off: off_t,
) -> *mut c_void {
    if let Some(p) = guarded(Some(libc::MAP_FAILED), || {
        sim_mmap(addr, len, prot, flags, fd, off)
    }) {
        return p;
    }
    match real {
        Some(real) => real(addr, len, prot, flags, fd, off),
        None => {
            set_errno(libc::ENOSYS);
            libc::MAP_FAILED
        }
    }
}

/// # Safety
/// C `mmap`.
#[no_mangle]
pub unsafe extern "C" fn mmap(
    addr: *mut c_void,
    len: size_t,
    prot: c_int,
    flags: c_int,
    fd: c_int,
    off: off_t,
) -> *mut c_void {
    mmap_hook(real!("mmap": MmapFn), addr, len, prot, flags, fd, off)
}

/// # Safety
/// C `mmap64` (the same as `mmap` on 64-bit Linux).
#[no_mangle]
pub unsafe extern "C" fn mmap64(
    addr: *mut c_void,
    len: size_t,
    prot: c_int,
    flags: c_int,
    fd: c_int,
    off: off_t,
) -> *mut c_void {
    mmap_hook(real!("mmap64": MmapFn), addr, len, prot, flags, fd, off)
}

/// # Safety
/// C `munmap`. A buffer's mapping is an ordinary shared mapping: forwarded as it is.
#[no_mangle]
pub unsafe extern "C" fn munmap(addr: *mut c_void, len: size_t) -> c_int {
    match real!("munmap": MunmapFn) {
        Some(real) => real(addr, len),
        None => missing("munmap"),
    }
}

// ---------------------------------------------------------------------------------------
// poll, ppoll, select.

/// Poll a set that holds simulated files: the others are polled for real, in slices,
/// while the launcher is asked about the simulated ones. `None`: no simulated file.
unsafe fn sim_poll(fds: *mut pollfd, nfds: nfds_t, timeout_ms: i64) -> Option<c_int> {
    if fds.is_null() || nfds == 0 || OPEN.load(Ordering::Acquire) == 0 {
        return None;
    }
    let set = std::slice::from_raw_parts_mut(fds, nfds as usize);
    let files: Vec<Option<Arc<Mutex<SimFile>>>> = set.iter().map(|p| lookup(p.fd)).collect();
    if files.iter().all(Option::is_none) {
        return None;
    }
    let real = real!("poll": PollFn)?;
    let start = std::time::Instant::now();
    let only_one = set.len() == 1;
    loop {
        let elapsed = start.elapsed().as_millis() as i64;
        let left = if timeout_ms < 0 {
            -1
        } else {
            (timeout_ms - elapsed).max(0)
        };
        let mut ready = 0;
        // The real descriptors, without waiting.
        let mut others: Vec<pollfd> = Vec::new();
        let mut where_: Vec<usize> = Vec::new();
        for (i, (p, f)) in set.iter_mut().zip(&files).enumerate() {
            p.revents = 0;
            if f.is_none() {
                others.push(*p);
                where_.push(i);
            }
        }
        if !others.is_empty() {
            let n = real(others.as_mut_ptr(), others.len() as nfds_t, 0);
            if n < 0 {
                return Some(n);
            }
            for (o, &i) in others.iter().zip(&where_) {
                set[i].revents = o.revents;
            }
        }
        // The simulated ones: a lone device waits in the launcher (in slices, so the
        // file is not held for long: another thread may QBUF or close it); else a look.
        let wait = if only_one {
            if left < 0 {
                100
            } else {
                left.min(100) as i32
            }
        } else {
            0
        };
        for (p, f) in set.iter_mut().zip(&files) {
            let Some(f) = f else { continue };
            let r = f.lock().unwrap_or_else(|e| e.into_inner()).poll(wait);
            p.revents = match r {
                Readiness::Ready => p.events & (libc::POLLIN | libc::POLLRDNORM),
                Readiness::NotYet => 0,
                Readiness::Error { gone: false } => libc::POLLERR,
                Readiness::Error { gone: true } => libc::POLLERR | libc::POLLHUP,
            };
        }
        ready += set.iter().filter(|p| p.revents != 0).count();
        if ready > 0 || left == 0 {
            return Some(ready as c_int);
        }
        if only_one {
            continue; // it waited in the launcher
        }
        let slice = if left < 0 { 5 } else { left.min(5) };
        std::thread::sleep(std::time::Duration::from_millis(slice as u64));
    }
}

/// # Safety
/// C `poll`.
#[no_mangle]
pub unsafe extern "C" fn poll(fds: *mut pollfd, nfds: nfds_t, timeout: c_int) -> c_int {
    if let Some(n) = guarded(Some(-1), || sim_poll(fds, nfds, timeout as i64)) {
        return n;
    }
    match real!("poll": PollFn) {
        Some(real) => real(fds, nfds, timeout),
        None => missing("poll"),
    }
}

fn timespec_ms(ts: *const libc::timespec) -> i64 {
    if ts.is_null() {
        return -1;
    }
    // SAFETY: a caller's non-null timespec.
    let t = unsafe { &*ts };
    if t.tv_sec < 0 || !(0..1_000_000_000).contains(&t.tv_nsec) {
        return 0; // EINVAL for the kernel; here an immediate look
    }
    t.tv_sec
        .saturating_mul(1000)
        .saturating_add((t.tv_nsec + 999_999) / 1_000_000)
}

/// # Safety
/// C `ppoll` (the signal mask is not applied while a simulated file is polled).
#[no_mangle]
pub unsafe extern "C" fn ppoll(
    fds: *mut pollfd,
    nfds: nfds_t,
    timeout: *const libc::timespec,
    sigmask: *const libc::sigset_t,
) -> c_int {
    if let Some(n) = guarded(Some(-1), || sim_poll(fds, nfds, timespec_ms(timeout))) {
        return n;
    }
    match real!("ppoll": PpollFn) {
        Some(real) => real(fds, nfds, timeout, sigmask),
        None => missing("ppoll"),
    }
}

/// # Safety
/// C `select`: a set holding a simulated file is answered through [`poll`]'s path
/// (POLLERR counts as readable and as an exception, as the kernel reports it).
#[no_mangle]
pub unsafe extern "C" fn select(
    nfds: c_int,
    readfds: *mut libc::fd_set,
    writefds: *mut libc::fd_set,
    exceptfds: *mut libc::fd_set,
    timeout: *mut libc::timeval,
) -> c_int {
    let Some(real) = real!("select": SelectFn) else {
        return missing("select");
    };
    let has_sim = OPEN.load(Ordering::Acquire) > 0
        && (0..nfds.clamp(0, libc::FD_SETSIZE as c_int)).any(|fd| {
            [readfds, writefds, exceptfds]
                .iter()
                .any(|s| !s.is_null() && libc::FD_ISSET(fd, *s))
                && lookup(fd).is_some()
        });
    if !has_sim {
        return real(nfds, readfds, writefds, exceptfds, timeout);
    }
    let mut polls: Vec<pollfd> = Vec::new();
    for fd in 0..nfds.clamp(0, libc::FD_SETSIZE as c_int) {
        let mut events = 0;
        if !readfds.is_null() && libc::FD_ISSET(fd, readfds) {
            events |= libc::POLLIN;
        }
        if !writefds.is_null() && libc::FD_ISSET(fd, writefds) {
            events |= libc::POLLOUT;
        }
        if !exceptfds.is_null() && libc::FD_ISSET(fd, exceptfds) {
            events |= libc::POLLPRI;
        }
        if events != 0 {
            polls.push(pollfd {
                fd,
                events,
                revents: 0,
            });
        }
    }
    let ms = if timeout.is_null() {
        -1
    } else {
        let t = &*timeout;
        t.tv_sec
            .max(0)
            .saturating_mul(1000)
            .saturating_add(t.tv_usec.clamp(0, 999_999) / 1000)
            .min(c_int::MAX as i64)
    };
    let n = poll(polls.as_mut_ptr(), polls.len() as nfds_t, ms as c_int);
    if n < 0 {
        return n;
    }
    for s in [readfds, writefds, exceptfds] {
        if !s.is_null() {
            libc::FD_ZERO(s);
        }
    }
    let mut count = 0;
    for p in &polls {
        let err = p.revents & (libc::POLLERR | libc::POLLHUP) != 0;
        let mut hit = |s: *mut libc::fd_set, on: bool| {
            if on && !s.is_null() {
                libc::FD_SET(p.fd, s);
                count += 1;
            }
        };
        hit(
            readfds,
            p.events & libc::POLLIN != 0 && (p.revents & libc::POLLIN != 0 || err),
        );
        hit(
            writefds,
            p.events & libc::POLLOUT != 0 && (p.revents & libc::POLLOUT != 0 || err),
        );
        hit(
            exceptfds,
            p.events & libc::POLLPRI != 0 && p.revents & libc::POLLPRI != 0,
        );
    }
    count
}

// ---------------------------------------------------------------------------------------
// stat and the sysfs entry: tools that check what a device node is before opening it
// (v4l2-ctl, v4l2-compliance: `stat`, then /sys/dev/char/MAJOR:MINOR/uevent) see a video
// character device. Programs that use statx (Rust's std::fs::metadata) see the placeholder
// as the regular file it is.

/// The device number the simulated device reports: V4L2's major 81, an unlikely minor.
const SIM_MAJOR: u32 = 81;
const SIM_MINOR: u32 = 250;

fn dress_as_device(st: *mut libc::stat) {
    // SAFETY: the caller's stat buffer, filled by a successful stat.
    unsafe {
        if (*st).st_dev == 0 && (*st).st_ino == 0 {
            return;
        }
        if device_id() == Some(((*st).st_dev, (*st).st_ino)) {
            (*st).st_mode = ((*st).st_mode & !libc::S_IFMT) | libc::S_IFCHR;
            (*st).st_rdev = libc::makedev(SIM_MAJOR, SIM_MINOR);
            (*st).st_size = 0;
        }
    }
}

type StatFn = unsafe extern "C" fn(*const c_char, *mut libc::stat) -> c_int;
type FstatFn = unsafe extern "C" fn(c_int, *mut libc::stat) -> c_int;

/// `stat`, `stat64`: the simulated device's placeholder dressed as a video device.
unsafe fn stat_hook(real: Option<StatFn>, path: *const c_char, st: *mut libc::stat) -> c_int {
    let r = match real {
        Some(real) => real(path, st),
        None => libc::fstatat(libc::AT_FDCWD, path, st, 0),
    };
    if r == 0 {
        dress_as_device(st);
    }
    r
}

/// `fstat`, `fstat64`.
unsafe fn fstat_hook(real: Option<FstatFn>, fd: c_int, st: *mut libc::stat) -> c_int {
    let r = match real {
        Some(real) => real(fd, st),
        None => libc::fstatat(fd, c"".as_ptr(), st, libc::AT_EMPTY_PATH),
    };
    if r == 0 && lookup(fd).is_some() {
        dress_as_device(st);
    }
    r
}

/// # Safety
/// C `stat`.
#[no_mangle]
pub unsafe extern "C" fn stat(path: *const c_char, st: *mut libc::stat) -> c_int {
    stat_hook(real!("stat": StatFn), path, st)
}

/// # Safety
/// C `stat64` (the same struct on 64-bit Linux).
#[no_mangle]
pub unsafe extern "C" fn stat64(path: *const c_char, st: *mut libc::stat) -> c_int {
    stat_hook(real!("stat64": StatFn), path, st)
}

/// # Safety
/// C `fstat`.
#[no_mangle]
pub unsafe extern "C" fn fstat(fd: c_int, st: *mut libc::stat) -> c_int {
    fstat_hook(real!("fstat": FstatFn), fd, st)
}

/// # Safety
/// C `fstat64`.
#[no_mangle]
pub unsafe extern "C" fn fstat64(fd: c_int, st: *mut libc::stat) -> c_int {
    fstat_hook(real!("fstat64": FstatFn), fd, st)
}

type FopenFn = unsafe extern "C" fn(*const c_char, *const c_char) -> *mut libc::FILE;

/// The sysfs uevent of the simulated device, as a readable stream, if `path` names it.
fn sim_uevent(path: *const c_char, mode: *const c_char) -> Option<*mut libc::FILE> {
    if path.is_null() || device_id().is_none() {
        return None;
    }
    // SAFETY: the caller's NUL-terminated path.
    let p = unsafe { std::ffi::CStr::from_ptr(path) }.to_bytes();
    let want = format!("/sys/dev/char/{SIM_MAJOR}:{SIM_MINOR}/uevent");
    if p != want.as_bytes() {
        return None;
    }
    let text = format!("MAJOR={SIM_MAJOR}\nMINOR={SIM_MINOR}\nDEVNAME=video{SIM_MINOR}\n");
    // SAFETY: a fresh memfd, written and rewound, then handed to a FILE.
    unsafe {
        let fd = libc::memfd_create(c"glint-sim-v4l2-uevent".as_ptr(), libc::MFD_CLOEXEC);
        if fd < 0 {
            return None;
        }
        libc::write(fd, text.as_ptr() as *const c_void, text.len());
        libc::lseek(fd, 0, libc::SEEK_SET);
        let f = libc::fdopen(fd, mode);
        if f.is_null() {
            libc::close(fd);
            return None;
        }
        Some(f)
    }
}

/// `fopen`, `fopen64`: the simulated device's sysfs uevent, else the real function.
unsafe fn fopen_hook(
    real: Option<FopenFn>,
    path: *const c_char,
    mode: *const c_char,
) -> *mut libc::FILE {
    if let Some(f) = sim_uevent(path, mode) {
        return f;
    }
    match real {
        Some(real) => real(path, mode),
        None => {
            set_errno(libc::ENOSYS);
            std::ptr::null_mut()
        }
    }
}

/// # Safety
/// C `fopen`.
#[no_mangle]
pub unsafe extern "C" fn fopen(path: *const c_char, mode: *const c_char) -> *mut libc::FILE {
    fopen_hook(real!("fopen": FopenFn), path, mode)
}

/// # Safety
/// C `fopen64`.
#[no_mangle]
pub unsafe extern "C" fn fopen64(path: *const c_char, mode: *const c_char) -> *mut libc::FILE {
    fopen_hook(real!("fopen64": FopenFn), path, mode)
}
