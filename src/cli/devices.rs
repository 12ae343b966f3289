//! `glint devices`: the cameras (V4L2) and serial ports of this machine, described well
//! enough to write a rig's `[camera]` and `[lamp]` sections from.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Result;
use clap::Args;
use glint::devices;

#[derive(Args)]
pub struct DevicesArgs {
    /// Devices to describe: /dev/video nodes, /dev/v4l/by-id links, serial ports
    /// [default: every /dev/video* node and every serial port].
    #[arg(value_name = "PATH")]
    paths: Vec<PathBuf>,
    /// Print the description as JSON.
    #[arg(long)]
    json: bool,
    /// Talk to the lamp of this rig file over its `[lamp.protocol]`: open lamp.port, do
    /// the protocol's connection steps, identify the lamp and read its state (it is not
    /// switched on). A way to try a protocol written for a new controller, e.g. against
    /// `glint-mock lamp --link PATH --preset P`.
    #[arg(long, value_name = "RIG")]
    lamp: Option<PathBuf>,
    /// With --lamp: also switch the lamp on at lamp.level, read it back, and switch it off
    /// again (read back), as a capture does.
    #[arg(long, requires = "lamp")]
    switch: bool,
}

/// What `--lamp` found.
#[derive(Debug, serde::Serialize)]
struct LampReport {
    port: String,
    preset: &'static str,
    baud: u32,
    identity: Option<String>,
    /// `on <level>` / `off`, as read back at first.
    state: Option<String>,
    /// With --switch: the state read back after switching on, and after switching off.
    switched_on: Option<String>,
    switched_off: Option<String>,
    error: Option<String>,
}

/// Talk to a rig's lamp; an error names what to fix.
fn probe_lamp(rig: &Path, switch: bool) -> Result<LampReport> {
    use glint::devices::Lamp;
    let loaded = glint::rig::load(rig)?;
    let l = &loaded.rig.lamp;
    let port = match (&l.backend, &l.port) {
        (glint::rig::LampBackend::Serial, Some(p)) => p.clone(),
        _ => anyhow::bail!(
            "{}: the lamp is not on a serial port (lamp.backend = \"serial\" with lamp.port); nothing to talk to",
            rig.display()
        ),
    };
    let mut report = LampReport {
        port: port.clone(),
        preset: l.protocol.preset.name(),
        baud: l.baud(),
        identity: None,
        state: None,
        switched_on: None,
        switched_off: None,
        error: None,
    };
    let run = |report: &mut LampReport| -> std::result::Result<(), devices::DeviceError> {
        let policy = devices::serial_lamp::LampPolicy::from_rig(l)?;
        let mut lamp = devices::serial_lamp::SerialLamp::open(&port, l.baud(), policy)?;
        report.identity = Some(lamp.identify()?);
        report.state = Some(lamp.state()?.to_string());
        if switch {
            let on = lamp.switch_on(l.level);
            // Whatever happened, switch it off again.
            let off = lamp.switch_off();
            report.switched_on = Some(on?.to_string());
            report.switched_off = Some(off?.to_string());
        }
        Ok(())
    };
    if let Err(e) = run(&mut report) {
        report.error = Some(e.to_string());
    }
    Ok(report)
}

/// A serial port, by its kernel name and stable names.
#[derive(Debug, Clone, serde::Serialize)]
struct SerialPort {
    path: PathBuf,
    by_id: Vec<PathBuf>,
    /// `usb VID:PID maker product`, `pci`, `bluetooth`, or empty.
    kind: String,
    /// Why a path named on the command line is not a serial port.
    #[serde(skip_serializing_if = "Option::is_none")]
    error: Option<String>,
}

/// The kernel's class of a character device (`tty`, `video4linux`, `mem`, ...), from sysfs;
/// none for a path that is not a character device or that sysfs does not know (a
/// pseudo-terminal).
fn char_class(path: &Path) -> Option<String> {
    use std::os::unix::fs::{FileTypeExt, MetadataExt};
    let md = std::fs::metadata(path).ok()?;
    if !md.file_type().is_char_device() {
        return None;
    }
    let (major, minor) = (libc::major(md.rdev()), libc::minor(md.rdev()));
    let real = std::fs::canonicalize(format!("/sys/dev/char/{major}:{minor}")).ok()?;
    let class = real.parent()?.file_name()?.to_string_lossy().into_owned();
    Some(class)
}

/// Why `path`, named on the command line and not a camera, is not a serial port (none if it
/// may be one).
fn not_a_port(path: &Path) -> Option<String> {
    use std::os::unix::fs::FileTypeExt;
    let what = match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Some("no such file; `glint devices` without paths lists the serial ports present".into())
        }
        Err(e) => return Some(format!("cannot be read: {e}")),
        Ok(m) if m.is_dir() => "a directory",
        Ok(m) if m.is_file() => "a regular file",
        Ok(m) if !m.file_type().is_char_device() => "not a character device",
        Ok(_) => match char_class(path) {
            Some(c) if c != "tty" => {
                return Some(format!(
                    "a character device of the kernel's `{c}` class, neither a camera nor a serial port"
                ))
            }
            _ => return None,
        },
    };
    Some(format!(
        "{what}, not a device: name a serial port (lamp.port) or a /dev/video node (camera.device)"
    ))
}

/// The symbolic links in `dir` with the real path each points to.
fn links_in(dir: &str) -> Vec<(PathBuf, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut out: Vec<(PathBuf, PathBuf)> = entries
        .flatten()
        .filter_map(|e| {
            let link = e.path();
            let real = std::fs::canonicalize(&link).ok()?;
            Some((link, real))
        })
        .collect();
    out.sort();
    out
}

fn names_for(links: &[(PathBuf, PathBuf)], path: &Path) -> Vec<PathBuf> {
    let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    links
        .iter()
        .filter(|(_, r)| *r == real)
        .map(|(l, _)| l.clone())
        .collect()
}

/// /dev/video0, /dev/video1, ... in numeric order.
fn video_nodes() -> Vec<PathBuf> {
    let mut nodes: Vec<(u32, PathBuf)> = std::fs::read_dir("/dev")
        .map(|d| {
            d.flatten()
                .filter_map(|e| {
                    let name = e.file_name().into_string().ok()?;
                    let n = name.strip_prefix("video")?.parse().ok()?;
                    Some((n, e.path()))
                })
                .collect()
        })
        .unwrap_or_default();
    nodes.sort();
    nodes.into_iter().map(|(_, p)| p).collect()
}

fn is_video(path: &Path) -> bool {
    let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    real.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.starts_with("video"))
        || path.starts_with("/dev/v4l")
        || char_class(path).is_some_and(|c| c == "video4linux")
}

fn serial_ports(only: Option<&[PathBuf]>) -> Vec<SerialPort> {
    let links = links_in("/dev/serial/by-id");
    let listed = serialport::available_ports().unwrap_or_default();
    let describe = |path: &Path| {
        let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        let kind = listed
            .iter()
            .find(|p| Path::new(&p.port_name) == real)
            .map(|p| match &p.port_type {
                serialport::SerialPortType::UsbPort(u) => format!(
                    "usb {:04x}:{:04x} {} {}",
                    u.vid,
                    u.pid,
                    u.manufacturer.as_deref().unwrap_or(""),
                    u.product.as_deref().unwrap_or("")
                )
                .trim_end()
                .to_string(),
                serialport::SerialPortType::PciPort => "pci".into(),
                serialport::SerialPortType::BluetoothPort => "bluetooth".into(),
                serialport::SerialPortType::Unknown => String::new(),
            })
            .unwrap_or_default();
        SerialPort {
            path: path.to_path_buf(),
            by_id: names_for(&links, path),
            kind,
            error: None,
        }
    };
    match only {
        Some(paths) => paths
            .iter()
            .map(|p| SerialPort {
                error: not_a_port(p),
                ..describe(p)
            })
            .collect(),
        None => {
            let mut paths: Vec<PathBuf> =
                listed.iter().map(|p| PathBuf::from(&p.port_name)).collect();
            for (_, real) in &links {
                if !paths.contains(real) {
                    paths.push(real.clone());
                }
            }
            paths.sort();
            paths.iter().map(|p| describe(p)).collect()
        }
    }
}

pub fn cmd_devices(a: DevicesArgs) -> Result<ExitCode> {
    if let Some(rig) = &a.lamp {
        let r = probe_lamp(rig, a.switch)?;
        if a.json {
            println!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({ "lamp": r }))?
            );
        } else {
            println!(
                "Lamp of {} on {} (protocol preset {}, {} baud):",
                rig.display(),
                r.port,
                r.preset,
                r.baud
            );
            for (what, v) in [
                ("identity", &r.identity),
                ("state", &r.state),
                ("after switching on", &r.switched_on),
                ("after switching off", &r.switched_off),
            ] {
                if let Some(v) = v {
                    println!("  {what}: {v}");
                }
            }
            if let Some(e) = &r.error {
                println!("  error: {e}");
            }
        }
        return Ok(if r.error.is_some() {
            ExitCode::FAILURE
        } else {
            ExitCode::SUCCESS
        });
    }
    let (video, serial): (Vec<PathBuf>, Vec<PathBuf>) =
        a.paths.iter().cloned().partition(|p| is_video(p));
    let only_serial = (!a.paths.is_empty()).then_some(serial.as_slice());
    let ports = if a.paths.is_empty() || !serial.is_empty() {
        serial_ports(only_serial)
    } else {
        Vec::new()
    };
    let video = if a.paths.is_empty() {
        video_nodes()
    } else {
        video
    };
    let cameras = cameras::describe_all(&video);
    // A path the user named that is not what it should be is an error (after the listing).
    let status = if !a.paths.is_empty()
        && (cameras::any_failed(&cameras) || ports.iter().any(|p| p.error.is_some()))
    {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    };
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "v4l2_built": devices::V4L2_BUILT,
                "cameras": cameras::to_json(&cameras),
                "serial_ports": ports,
            }))?
        );
        return Ok(status);
    }
    cameras::print(&cameras, &video);
    if a.paths.is_empty() || !serial.is_empty() {
        println!("Serial ports (lamp.port):");
        if ports.is_empty() {
            println!("  none found");
        }
        for p in &ports {
            if let Some(e) = &p.error {
                println!("  {}: {e}", p.path.display());
                continue;
            }
            println!(
                "  {}{}{}",
                p.path.display(),
                if p.kind.is_empty() {
                    String::new()
                } else {
                    format!("  {}", p.kind)
                },
                p.by_id
                    .iter()
                    .map(|l| format!("\n      stable name: {}", l.display()))
                    .collect::<String>()
            );
        }
        if ports.iter().any(|p| !p.by_id.is_empty()) {
            println!("  (prefer the stable name under /dev/serial/by-id: /dev/ttyUSB numbers change between plug-ins)");
        }
    }
    Ok(status)
}

#[cfg(not(feature = "v4l2"))]
mod cameras {
    use std::path::PathBuf;

    pub struct Nothing;

    pub fn describe_all(_: &[PathBuf]) -> Vec<Nothing> {
        Vec::new()
    }

    pub fn to_json(_: &[Nothing]) -> serde_json::Value {
        serde_json::Value::Null
    }

    pub fn any_failed(_: &[Nothing]) -> bool {
        false
    }

    pub fn print(_: &[Nothing], _: &[PathBuf]) {
        println!(
            "Cameras (V4L2): not listed: {}.",
            glint::devices::V4L2_MISSING
        );
    }
}

#[cfg(feature = "v4l2")]
mod cameras {
    use std::path::PathBuf;

    use glint::devices::v4l2::{self, ControlInfo, DeviceReport, FormatInfo};
    use glint::rig::PixelFormat;

    pub struct Camera {
        report: DeviceReport,
        suggested: Option<String>,
    }

    /// Some camera could not be described (no such device, not a camera, no access).
    pub fn any_failed(cams: &[Camera]) -> bool {
        cams.iter().any(|c| c.report.error.is_some())
    }

    pub fn describe_all(paths: &[PathBuf]) -> Vec<Camera> {
        let links = super::links_in("/dev/v4l/by-id");
        paths
            .iter()
            .map(|p| {
                let mut report = v4l2::describe(p);
                report.by_id = super::names_for(&links, p);
                let suggested = suggest(&report);
                Camera { report, suggested }
            })
            .collect()
    }

    pub fn to_json(cams: &[Camera]) -> serde_json::Value {
        cams.iter()
            .map(|c| {
                let mut v = serde_json::to_value(&c.report).unwrap_or_default();
                v["suggested_camera_section"] = c.suggested.clone().into();
                v
            })
            .collect()
    }

    /// Glint's order of preference among the formats a camera offers: measurement first
    /// (more bits, then no chroma subsampling), the lossy format last.
    fn rank(f: PixelFormat) -> u8 {
        match f {
            PixelFormat::Y16 => 0,
            PixelFormat::Y12 => 1,
            PixelFormat::Y10 => 2,
            PixelFormat::GREY => 3,
            PixelFormat::RGB3 | PixelFormat::BGR3 => 4,
            PixelFormat::YUYV => 5,
            PixelFormat::MJPG => 9,
        }
    }

    /// A `[camera]` section for the camera: its best format at its largest size and the
    /// highest frame rate there; exposure limits from exposure_time_absolute.
    fn suggest(r: &DeviceReport) -> Option<String> {
        if !r.capture {
            return None;
        }
        let (f, pf): (&FormatInfo, PixelFormat) = r
            .formats
            .iter()
            .filter_map(|f| Some((f, PixelFormat::from_fourcc(f.code)?)))
            .min_by_key(|(_, pf)| rank(*pf))?;
        let z = f.sizes.iter().max_by_key(|z| {
            let (w, h) = z.max.unwrap_or((z.width, z.height));
            w as u64 * h as u64
        })?;
        let (w, h) = z.max.unwrap_or((z.width, z.height));
        let fps = z
            .intervals
            .iter()
            .filter_map(|i| match i {
                v4l2::IntervalInfo::Discrete { num, den } if *num > 0 => {
                    Some(*den as f64 / *num as f64)
                }
                v4l2::IntervalInfo::Stepwise { min, .. } if min.0 > 0 => {
                    Some(min.1 as f64 / min.0 as f64)
                }
                _ => None,
            })
            .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))));
        let exp = r
            .controls
            .iter()
            .find(|k| k.name == "exposure_time_absolute");
        let device = r.by_id.first().unwrap_or(&r.path);
        let mut s = format!(
            "[camera]\nbackend = \"v4l2\"\ndevice = \"{}\"\npixel_format = \"{pf}\"\nwidth = {w}\nheight = {h}\nbit_depth = {}\n",
            device.display(),
            pf.bit_depth()
        );
        if pf.lossy() {
            s += "allow_lossy = true              # MJPG is lossy and processed in the camera: not measurements\n";
        }
        if let Some(fps) = fps {
            s += &format!("fps = {:.1}\n", fps);
        }
        match exp {
            Some(k) => s += &format!(
                "min_exposure_us = {}               # exposure_time_absolute {}..{} (units of 100 µs)\nmax_exposure_us = {}\n",
                k.min.max(1) * 100,
                k.min,
                k.max,
                k.max * 100
            ),
            None => s += "# no exposure_time_absolute control: Glint cannot set this camera's exposures\n",
        }
        if let Some(g) = r.controls.iter().find(|k| k.name == "gain") {
            s += &format!("\n[camera.controls]\ngain = {}                        # lowest gain: least noise\n", g.min);
        }
        Some(s)
    }

    fn control_line(k: &ControlInfo) -> String {
        let range = match k.kind {
            "int" | "int64" => format!(
                "{}..{}{}",
                k.min,
                k.max,
                if k.step > 1 {
                    format!(" step {}", k.step)
                } else {
                    String::new()
                }
            ),
            "bool" => "0/1".into(),
            "menu" | "intmenu" => format!("{}..{}", k.min, k.max),
            _ => String::new(),
        };
        let mut s = format!(
            "    {:<34} {:<7} {:<20} default {:<6} now {}",
            k.name,
            k.kind,
            range,
            k.default,
            k.value.map_or("-".to_string(), |v| v.to_string())
        );
        if !k.flags.is_empty() {
            s += &format!("  ({})", k.flags.join(", "));
        }
        for (v, l) in &k.menu {
            s += &format!("\n        {v}: {l}");
        }
        s
    }

    pub fn print(cams: &[Camera], asked: &[PathBuf]) {
        println!("Cameras (V4L2, camera.device):");
        if cams.is_empty() {
            println!(
                "  none found{}",
                if asked.is_empty() {
                    " (no /dev/video* nodes)"
                } else {
                    ""
                }
            );
        }
        for c in cams {
            let r = &c.report;
            print!("  {}", r.path.display());
            for l in &r.by_id {
                print!("\n      stable name: {}", l.display());
            }
            println!();
            if let Some(e) = &r.error {
                if r.driver.is_empty() {
                    println!("    cannot be read: {e}");
                    continue;
                }
            }
            println!("    {} (driver {}, bus {})", r.card, r.driver, r.bus);
            if !r.capture {
                println!("    not a video capture node ({}); a camera's other nodes carry metadata — use its capture node", r.capabilities);
                continue;
            }
            if let Some(e) = &r.error {
                println!("    problem: {e}");
            }
            println!("    formats (camera.pixel_format, width x height, fps):");
            print!("{}", v4l2::formats_text(&r.formats, "      "));
            println!("    controls (names for [camera.controls]; Glint itself switches off automatic exposure, gain, white balance and dynamic frame rate):");
            for k in &r.controls {
                println!("{}", control_line(k));
            }
            if let Some(s) = &c.suggested {
                println!("    suggested rig section:");
                for line in s.lines() {
                    println!("      {line}");
                }
            }
            println!();
        }
    }
}
