//! `glint report SESSION`: one self-contained page, `report/index.html`, with the capture,
//! the HDR merge, the calibration, the fit and its validation, and every figure; the
//! figures are copied beside the page, so the folder `report/` can be moved or mailed on
//! its own. The folder is written whole under a temporary name and then swapped in, so a
//! reader never sees half a report.
//!
//! The page is built from the stages' own files (manifest.json, hdr/summary.json,
//! calib/camera.json, fit/fit.json, validation/validation.json); stages that have not run
//! are named as missing, with the command that runs them.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::calib::run::CameraFile;
use crate::fit::file::{FitFile, Param};
use crate::plan::FrameKind;
use crate::session::{self, SessionError};
use glint_format::stage::hdr::Summary as HdrSummary;
use glint_format::stage::validation::ValidationFile;

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error(transparent)]
    Session(#[from] SessionError),
    /// fit.json unusable (the message names it).
    #[error(transparent)]
    Fit(#[from] crate::fit::run::FitError),
    /// hdr/summary.json unusable (the message names it).
    #[error(transparent)]
    Summary(#[from] crate::fit::run::SummaryError),
    /// calib/camera.json unusable (the message names it).
    #[error(transparent)]
    Camera(#[from] crate::calib::run::RunError),
    /// A stage's file is there but unusable (the message names it).
    #[error("{0}")]
    Input(String),
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> ReportError {
    ReportError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Options of `glint report`.
#[derive(Debug, Clone, Default)]
pub struct ReportOptions {
    /// The speed/accuracy chart of `glint bench fit` to include, if it exists.
    pub bench_chart: Option<PathBuf>,
    /// Report on a session that is not complete (the page says so at the top).
    pub allow_incomplete: bool,
}

/// What was written.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Written {
    pub index: PathBuf,
    /// Files of the report folder, relative to it.
    pub files: Vec<String>,
    /// Stages whose results were missing.
    pub missing: Vec<String>,
    /// Warnings (an incomplete session).
    #[serde(default)]
    pub warnings: Vec<String>,
}

/// Escape text for HTML.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A stage's JSON file: None when it is not there (the stage has not run); an error naming
/// the file when it is there but unreadable or not JSON (size-capped, a regular file).
fn read_json(dir: &Path, rel: &str) -> Result<Option<Value>, ReportError> {
    let file = crate::fsx::Within::new(dir, rel);
    let path = &file.path();
    if !file.is_there() {
        return Ok(None);
    }
    let bytes = file
        .read(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| file_err(path, format!("cannot read ({e})")))?;
    serde_json::from_slice(&bytes).map(Some).map_err(|e| {
        file_err(
            path,
            format!(
                "not JSON ({}); re-run the stage that writes it",
                crate::fsx::json_error(&e)
            ),
        )
    })
}

/// fit.json read and checked against the session as every stage does
/// ([`crate::fit::file::load`]), through its one type.
fn load_fit(dir: &Path, m: &session::Manifest) -> Result<FitFile, ReportError> {
    Ok(crate::fit::file::load(
        dir,
        &crate::fit::file::Facts::of(m),
    )?)
}

/// validation.json (already read as JSON: `v`) through its one type; with `check`, its
/// format must be `glint-validation`.
fn validation_file(dir: &Path, v: Value, check: bool) -> Result<ValidationFile, ReportError> {
    let bad = || {
        file_err(
            &dir.join("validation/validation.json"),
            "not a glint-validation file; re-run glint validate",
        )
    };
    let v: ValidationFile = serde_json::from_value(v).map_err(|_| bad())?;
    if check && v.format != crate::validate::FORMAT {
        return Err(bad());
    }
    Ok(v)
}

/// hdr/summary.json, read and checked as the fit reads it, through its one type.
fn load_summary(dir: &Path) -> Result<HdrSummary, ReportError> {
    Ok(crate::fit::run::load_hdr_summary(
        &crate::fsx::Within::new(dir, "hdr/summary.json"),
    )?)
}

/// calib/camera.json, read and checked as every stage reads it, through its one type.
fn load_camera(dir: &Path) -> Result<CameraFile, ReportError> {
    let (c, _) =
        crate::calib::run::load_camera_file(crate::fsx::Within::new(dir, "calib/camera.json"))?;
    Ok(c)
}

/// The session's results as JSON, for scripts (`glint report --json`): each stage's key
/// figures, null where the stage has not run. `hdr`: its summary.json; `calibration`: the
/// model fitted, intrinsics, RMS, the first view's camera centre with its sd, and OpenCV's
/// arrays; `fit`: the chosen model and its candidate (kd, ks, ks/kd, n with sd and 95%
/// interval, reduced chi2, BIC, warnings) and the fit's warnings; `validation`: the chosen
/// model and every model's pixel figures (RMSE, noise RMSE, PSNR, SSIM).
pub fn results(dir: &Path) -> Result<Value, ReportError> {
    let fit = match crate::fsx::Within::new(dir, "fit/fit.json").is_there() {
        true => Some(load_fit(dir, &session::open(dir, true)?)?),
        false => None,
    };
    let hdr = match read_json(dir, "hdr/summary.json")? {
        Some(v) => Some(serde_json::from_value::<HdrSummary>(v).map_err(|e| {
            file_err(
                &dir.join("hdr/summary.json"),
                format!(
                    "not a glint hdr summary ({}); re-run glint hdr",
                    crate::fsx::json_error(&e)
                ),
            )
        })?),
        None => None,
    };
    let calibration = match read_json(dir, "calib/camera.json")? {
        Some(v) => {
            let c: CameraFile = serde_json::from_value(v).map_err(|e| {
                file_err(
                    &dir.join("calib/camera.json"),
                    format!(
                        "not a glint-camera file ({}); re-run glint calibrate",
                        crate::fsx::json_error(&e)
                    ),
                )
            })?;
            Some(calibration_results(&c))
        }
        None => None,
    };
    let validation = match read_json(dir, "validation/validation.json")? {
        Some(v) => Some(validation_results(&validation_file(dir, v, false)?)),
        None => None,
    };
    Ok(serde_json::json!({
        "hdr": hdr,
        "calibration": calibration,
        "fit": fit.as_ref().map(fit_results),
        "validation": validation,
    }))
}

/// The calibration's key figures for [`results`].
fn calibration_results(c: &CameraFile) -> Value {
    let cal = &c.calibration;
    let view = cal.views.first();
    serde_json::json!({
        "fit": cal.fit,
        "intrinsics": cal.intrinsics,
        "parameters": cal.parameters,
        "rms_px": cal.rms_px,
        "camera_centre": view.map(|v| v.camera_centre),
        "camera_centre_sd": view.map(|v| v.camera_centre_sd),
        "length_unit": c.length_unit,
        "camera_matrix": c.camera_matrix,
        "dist_coeffs": c.dist_coeffs,
        "uncertainty_includes": cal.uncertainty_includes,
        "warnings": cal.warnings,
    })
}

/// The fit's key figures for [`results`].
fn fit_results(f: &FitFile) -> Value {
    let candidate = f.candidates.iter().find(|c| c.model == f.chosen).map(|c| {
        serde_json::json!({
            "model": c.model, "kd": c.kd, "ks": c.ks,
            "ks_over_kd": c.ks_over_kd, "n": c.n,
            "reduced_chi2": c.reduced_chi2, "bic": c.bic,
            "warnings": c.warnings,
        })
    });
    serde_json::json!({
        "chosen": f.chosen,
        "candidate": candidate,
        "camera_refined": f.camera_refined,
        "warnings": f.warnings,
    })
}

/// The validation's key figures for [`results`].
fn validation_results(v: &ValidationFile) -> Value {
    let models: Vec<Value> = v
        .models
        .iter()
        .map(|m| {
            let p = &m.pixels;
            serde_json::json!({
                "model": m.model, "chosen": m.chosen,
                "rmse": p.rmse, "noise_rmse": p.noise_rmse,
                "psnr_db": p.psnr_db, "ssim": p.ssim,
            })
        })
        .collect();
    serde_json::json!({
        "chosen": v.chosen,
        "models": models,
        "warnings": v.warnings,
    })
}

/// Largest figure the report copies.
const MAX_FIGURE_BYTES: u64 = 256 << 20;

/// Significant digits for a table.
fn sig(x: Option<f64>, digits: usize) -> String {
    match x {
        Some(x) if x.is_finite() && x != 0.0 => {
            let mag = x.abs().log10().floor() as i64;
            if !(-4..7).contains(&mag) {
                return format!("{x:.*e}", digits.saturating_sub(1));
            }
            let d = (digits as i64 - 1 - mag).clamp(0, 12) as usize;
            format!("{x:.d$}")
        }
        Some(0.0) => "0".into(),
        _ => "–".into(),
    }
}

/// A value and its standard deviation: the sd to two significant digits, the value to
/// the same decimal place, and a common power of ten for large or small values. Returns
/// the text ("1.193 ± 0.011" or "(8.008 ± 0.034)") and the power of ten, if any.
pub fn value_sd(value: f64, sd: f64) -> (String, Option<i32>) {
    if !value.is_finite() {
        return ("–".into(), None);
    }
    let e = if value != 0.0 && !(1e-3..1e5).contains(&value.abs()) {
        Some(value.abs().log10().floor() as i32)
    } else {
        None
    };
    let k = 10f64.powi(e.unwrap_or(0));
    let (v, d) = (value / k, sd / k);
    let places = if d.is_finite() && d > 0.0 {
        (1 - d.log10().floor() as i32).clamp(0, 12) as usize
    } else {
        4
    };
    let text = if d.is_finite() {
        format!("{v:.places$} ± {d:.places$}")
    } else {
        format!("{v:.places$}")
    };
    match e {
        Some(_) => (format!("({text})"), e),
        None => (text, None),
    }
}

/// value ± sd of a parameter (`{value, sd}`), as HTML.
fn pm(p: &Param) -> String {
    let (t, e) = value_sd(p.value.unwrap_or(f64::NAN), p.sd.unwrap_or(f64::NAN));
    match e {
        Some(e) => format!("{t} × 10<sup>{e}</sup>"),
        None => t,
    }
}

const STYLE: &str = "body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{margin-bottom:.2em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.6em 0;font-size:.92em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}tr.chosen{background:#eef7ee;font-weight:600}
.summary{background:#f6f8fa;border:1px solid #d0d7de;border-radius:6px;padding:.8em 1.2em}
.warn{color:#9a6700}.incomplete{background:#fde8e8;border:2px solid #b00;color:#800;padding:.6em 1em;font-size:1.1em}.missing{color:#b00}figure{margin:1em 0}figcaption{font-size:.9em;color:#555}
img{max-width:100%;border:1px solid #ddd}img.half{max-width:640px}.muted{color:#666;font-size:.9em}";

/// Every stage's file, read through its one type and checked as the stage after it checks
/// it; None for a stage that has not run.
struct Stages {
    manifest: session::Manifest,
    hdr: Option<HdrSummary>,
    cam: Option<CameraFile>,
    fit: Option<FitFile>,
    val: Option<ValidationFile>,
}

impl Stages {
    fn read(dir: &Path, allow_incomplete: bool) -> Result<Stages, ReportError> {
        let manifest = session::open(dir, allow_incomplete)?;
        // Each file read as JSON first (an error naming it), then through its type.
        let hdr = match read_json(dir, "hdr/summary.json")? {
            Some(_) => Some(load_summary(dir)?),
            None => None,
        };
        let cam = match read_json(dir, "calib/camera.json")? {
            Some(_) => Some(load_camera(dir)?),
            None => None,
        };
        let fit = match read_json(dir, "fit/fit.json")? {
            Some(_) => Some(load_fit(dir, &manifest)?),
            None => None,
        };
        let val = match read_json(dir, "validation/validation.json")? {
            Some(v) => Some(validation_file(dir, v, true)?),
            None => None,
        };
        Ok(Stages {
            manifest,
            hdr,
            cam,
            fit,
            val,
        })
    }

    /// The results' channels: a monochrome camera's have one, kd, ks and ks/kd one value
    /// each (the fit's "channels", else the session's).
    fn channels(&self) -> usize {
        self.fit
            .as_ref()
            .map_or(self.manifest.channels() as usize, |f| f.channels)
    }
}

/// How the tables name the channels.
struct Channels {
    /// 3 (R, G, B) or 1 (mono).
    n: usize,
    mono: bool,
    /// "(R, G, B)" or "(mono)".
    cols: &'static str,
    /// The channel ks/kd is shown for (G, or mono's one) and its name.
    g: usize,
    g_name: &'static str,
}

impl Channels {
    fn new(n: usize) -> Self {
        let mono = n == 1;
        Channels {
            n,
            mono,
            cols: if mono { "(mono)" } else { "(R, G, B)" },
            g: if mono { 0 } else { 1 },
            g_name: if mono { "(mono)" } else { "(G)" },
        }
    }
}

/// The figures copied into the report (name in report/, bytes).
struct Figures {
    copies: Vec<(&'static str, Vec<u8>)>,
    /// Why the rig could not be sketched, if it could not.
    sketch_problem: Option<String>,
}

impl Figures {
    /// Only figures Glint wrote: a fixed list, each a regular file inside the session
    /// reached through no symbolic link, size-capped. One missing is left out (its stage
    /// has not run); one there but unreadable (a link, a device, too big) is an error. And
    /// the rig's geometry, drawn here from the rig the session recorded and the camera the
    /// calibration found (and the fit's refinement of it, where there is one).
    fn gather(dir: &Path, opts: &ReportOptions, st: &Stages) -> Result<Figures, ReportError> {
        let within = |rel: &str| crate::fsx::Within::new(dir, rel);
        let mut figures: Vec<(crate::fsx::Within, &'static str)> = vec![
            (within("validation/compare.png"), "compare.png"),
            (within("validation/difference.png"), "difference.png"),
            (within("validation/profile.svg"), "profile.svg"),
            (within("validation/brdf.svg"), "brdf.svg"),
            (within("hdr/response.svg"), "response.svg"),
            (within("calib/corners.png"), "corners.png"),
        ];
        if let Some(b) = &opts.bench_chart {
            // The bench chart: a file of the user's.
            figures.push((crate::fsx::Within::file(b), "fit_bench.svg"));
        }
        let mut copies: Vec<(&'static str, Vec<u8>)> = Vec::new();
        for (src, n) in &figures {
            if !src.is_there() {
                continue;
            }
            let bytes = src.read(MAX_FIGURE_BYTES).map_err(|e| {
                file_err(
                    &src.path(),
                    format!("cannot read ({e}); re-run the stage that writes it"),
                )
            })?;
            copies.push((n, bytes));
        }
        let mut sketch_problem = None;
        if let (Some(rig), Some(c)) = (&st.manifest.rig, &st.cam) {
            if let Some(camera) = c.calibration.views.first().map(|v| v.camera_centre) {
                let sketch = crate::sketch::RigSketch {
                    geometry: &rig.geometry,
                    reference: rig.reference.as_ref(),
                    camera,
                    axis: c.rotations.first().map(|r| r[2]),
                    refined: st
                        .fit
                        .as_ref()
                        .and_then(|f| f.camera_refined.as_ref())
                        .map(|r| r.centre_mm),
                };
                match crate::sketch::rig_svg(&sketch) {
                    Ok(svg) => copies.push(("rig.svg", svg.into_bytes())),
                    Err(e) => sketch_problem = Some(e.to_string()),
                }
            }
        }
        Ok(Figures {
            copies,
            sketch_problem,
        })
    }

    fn has(&self, n: &str) -> bool {
        self.copies.iter().any(|(c, _)| *c == n)
    }

    /// A figure with its caption, where it is there.
    fn fig(&self, h: &mut String, n: &str, caption: &str) {
        if self.has(n) {
            // Photos of the whole frame and single plots at half width; row figures full.
            let class = if matches!(n, "corners.png" | "response.svg" | "fit_bench.svg") {
                " class=\"half\""
            } else {
                ""
            };
            let _ = writeln!(
                h,
                "<figure><a href=\"{n}\"><img{class} src=\"{n}\" alt=\"{}\"></a><figcaption>{caption} <a href=\"{n}\">Full size</a>.</figcaption></figure>",
                esc(caption)
            );
        }
    }
}

/// A number as a JSON file prints it (`1000.0`, `null`).
fn json_num(x: Option<f64>) -> String {
    serde_json::to_string(&x).expect("a number serialises")
}

/// Write `report/` for a session.
pub fn write(dir: &Path, opts: &ReportOptions) -> Result<Written, ReportError> {
    let st = Stages::read(dir, opts.allow_incomplete)?;
    let warnings_out: Vec<String> = session::incomplete_warning(&st.manifest)
        .into_iter()
        .collect();
    let figs = Figures::gather(dir, opts, &st)?;
    let ch = Channels::new(st.channels());
    let mut missing = Vec::new();
    let mut h = String::new();
    header(&mut h, dir, &st.manifest);
    summary(&mut h, &st, &ch);
    capture(&mut h, &st.manifest);
    hdr_section(&mut h, &mut missing, dir, st.hdr.as_ref(), &figs);
    calibration_section(&mut h, &mut missing, dir, st.cam.as_ref(), &figs);
    fit_section(&mut h, &mut missing, dir, st.fit.as_ref(), &ch);
    validation_section(&mut h, &mut missing, dir, st.val.as_ref(), &figs);
    if figs.has("fit_bench.svg") {
        h.push_str("<h2>Speed against accuracy</h2>\n");
        figs.fig(&mut h, "fit_bench.svg", "Fit time against error by sample count and sampling strategy (glint bench fit, on simulated tiles).");
    }
    h.push_str("<h2>Files</h2>\n<p class=\"muted\">In the session: <code>manifest.json</code>, <code>frames/</code>, <code>hdr/</code>, <code>calib/camera.json</code>, <code>fit/fit.json</code>, <code>fit/samples.csv</code>, <code>validation/validation.json</code>. This page and its figures are in <code>report/</code>.</p>\n</body></html>\n");
    let (index, files) = write_folder(dir, &h, &figs.copies)?;
    Ok(Written {
        index,
        files,
        missing,
        warnings: warnings_out,
    })
}

/// The page's head, its title, and the session's state where it is not complete (first
/// and prominently).
fn header(h: &mut String, dir: &Path, m: &session::Manifest) {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| dir.display().to_string());
    let _ = writeln!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Glint report: {}</title><style>{STYLE}</style></head><body>\n<h1>Glint report: {}</h1>\n<p class=\"muted\">Session <code>{}</code>, captured {}; report written {} by glint {}.</p>",
        esc(&name),
        esc(&name),
        esc(&dir.display().to_string()),
        esc(&m.created),
        esc(&session::timestamp(std::time::SystemTime::now())),
        env!("CARGO_PKG_VERSION")
    );
    if m.state != session::State::Complete {
        let _ = writeln!(
            h,
            "<p class=\"incomplete\"><b>Incomplete session: state {}</b>{}. Every result below comes from an unfinished capture ({} frames); re-capture before relying on it.</p>",
            esc(session::State::as_str(m.state)),
            m.failure
                .as_deref()
                .map(|f| format!(" ({})", esc(f)))
                .unwrap_or_default(),
            m.frames.len()
        );
    }
}

/// The summary box: the chosen model, the simulated lab's truth, the validation's figures.
fn summary(h: &mut String, st: &Stages, ch: &Channels) {
    h.push_str("<div class=\"summary\">");
    match &st.fit {
        Some(f) => {
            summary_chosen(h, f, ch);
            summary_truth(h, f, &st.manifest, ch);
            if let Some(cv) = st.val.as_ref().and_then(|v| v.chosen()) {
                let _ = write!(
                    h,
                    "<p>Validation: PSNR <b>{} dB</b>, RMSE {} against {} from noise alone (pixel values, every exposure); relative radiance error {}%; SSIM {}.</p>",
                    sig(cv.pixels.psnr_db, 4),
                    sig(cv.pixels.rmse, 3),
                    sig(cv.pixels.noise_rmse, 3),
                    sig(cv.radiance.relative_error.map(|x| 100.0 * x), 3),
                    sig(cv.pixels.ssim, 4),
                );
            }
        }
        None => h.push_str("<p class=\"missing\">No fit yet.</p>"),
    }
    h.push_str("</div>\n");
}

/// Entry `i` of a list of parameters (an empty one past its end).
fn at(p: &[Param], i: usize) -> Param {
    p.get(i).copied().unwrap_or_default()
}

/// The values of a list of parameters per channel, value ± sd, joined by `sep`.
fn per_channel(p: &[Param], n: usize, sep: &str) -> String {
    (0..n).map(|i| pm(&at(p, i))).collect::<Vec<_>>().join(sep)
}

/// The summary's chosen model: its parameters, and in absolute terms where the rig has a
/// reference standard.
fn summary_chosen(h: &mut String, f: &FitFile, ch: &Channels) {
    let chosen = f.chosen.as_str();
    let cols = ch.cols;
    let _ = write!(h, "<p><b>Chosen model: {}</b>", esc(chosen));
    if let Some(c) = f.candidates.iter().find(|c| c.model == f.chosen) {
        let _ = write!(h, "<br>kd {cols} = {}", per_channel(&c.kd, ch.n, ", "));
        if chosen != "lambert" {
            let n = c.n.unwrap_or_default();
            let _ = write!(
                h,
                "<br>ks {cols} = {}<br>n = {} (95%: {} to {})<br>ks/kd {} = {}",
                per_channel(&c.ks, ch.n, ", "),
                sig(n.value, 4),
                sig(n.ci95[0], 4),
                sig(n.ci95[1], 4),
                ch.g_name,
                pm(&at(&c.ks_over_kd, ch.g))
            );
            if let Some(a) = &c.alpha {
                let _ = write!(
                    h,
                    "<br>α (roughness) = {} (95%: {} to {})",
                    sig(a.value, 4),
                    sig(a.ci95[0], 4),
                    sig(a.ci95[1], 4)
                );
            }
        }
        match &c.absolute {
            Some(abs) if f.units.as_deref() == Some("absolute") => {
                summary_absolute(h, f, abs, chosen, ch)
            }
            _ => h.push_str("<br><span class=\"muted\">kd and ks are in the radiance's relative units (lamp intensity and camera gain included: the rig has no [reference] standard to take them out); their ratios and n are absolute. Intervals include the calibration's and the response curve's uncertainty where fit.json says so.</span>"),
        }
    }
    h.push_str("</p>");
}

/// The summary's absolute reflectance of the chosen model.
fn summary_absolute(
    h: &mut String,
    f: &FitFile,
    abs: &crate::fit::file::Absolute,
    chosen: &str,
    ch: &Channels,
) {
    let cols = ch.cols;
    let _ = write!(
        h,
        "<br><b>albedo {cols} = {}</b>",
        per_channel(&abs.albedo, ch.n, ", ")
    );
    if !abs.f0.is_empty() {
        let _ = write!(h, "<br>F0 {cols} = {}", per_channel(&abs.f0, ch.n, ", "));
    } else if chosen != "lambert" {
        let _ = write!(
            h,
            "<br>ks {cols} = {} sr⁻¹",
            per_channel(&abs.ks_per_sr, ch.n, ", ")
        );
    }
    let (reflectance, pixels, sd) = match &f.reference {
        Some(r) => (
            r.reflectance
                .iter()
                .map(|x| sig(*x, 4))
                .collect::<Vec<_>>()
                .join(", "),
            r.pixels.to_string(),
            sig(
                r.factor_relative_sd
                    .iter()
                    .filter_map(|x| x.total)
                    .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
                    .map(|x| 100.0 * x),
                2,
            ),
        ),
        None => (String::new(), "null".into(), String::new()),
    };
    let _ = write!(
        h,
        "<br><span class=\"muted\">Absolute: the reference standard (reflectance {reflectance}, {pixels} pixels) gives the factor the lamp and camera put on the radiance, known to ±{sd}%; kd and ks above it are in the radiance's relative units. Albedo = π kd, ks in sr⁻¹ (docs/design.md's f_r). Intervals include the factor's, the calibration's and the response curve's uncertainty.</span>",
    );
}

/// The simulated lab's true tile (where the rig is simulated), against the chosen model.
fn summary_truth(h: &mut String, f: &FitFile, m: &session::Manifest, ch: &Channels) {
    let Some(rig) = &m.rig else {
        return;
    };
    let (Some(truth), Some(sim)) = (
        rig.mock.as_ref().map(|x| &x.tile),
        crate::devices::mock::simulated_tile(rig),
    ) else {
        return;
    };
    let model = sim.model.as_str();
    let (mono, g_name, cols) = (ch.mono, ch.g_name, ch.cols);
    let lobe = model != "lambert";
    // A mono camera sees the mean of the three bands: kd = mean(kd), ks = mean(ks), the
    // same n.
    let mean = |v: [f64; 3]| (v[0] + v[1] + v[2]) / 3.0;
    let (kd_seen, ks_seen) = if mono {
        (mean(truth.kd), mean(truth.ks))
    } else {
        (truth.kd[1], truth.ks[1])
    };
    let _ = write!(
        h,
        "<p>Simulated lab: the true tile is {}{}{}; the chosen model {}.</p>",
        esc(model),
        if mono {
            format!(
                " (as the mono camera sees it, the mean of the three bands: kd = {})",
                sig(Some(kd_seen), 4)
            )
        } else {
            String::new()
        },
        if model == "ggx" {
            format!(
                ", α = {} (n = {}), F0 {g_name} = {}",
                sig(truth.alpha, 4),
                sig(truth.alpha.map(crate::fit::model::ggx::exponent), 4),
                sig(Some(ks_seen), 4)
            )
        } else if lobe {
            format!(
                ", n = {}, ks/kd {g_name} = {}",
                sig(Some(truth.n), 4),
                sig(Some(ks_seen / kd_seen), 4)
            )
        } else {
            String::new()
        },
        if model == f.chosen {
            "matches"
        } else {
            "<b>does not match</b>"
        }
    );
    if f.units.as_deref() == Some("absolute") {
        let albedo: Vec<String> = if mono {
            vec![sig(Some(std::f64::consts::PI * mean(truth.kd)), 4)]
        } else {
            (0..3)
                .map(|i| sig(Some(std::f64::consts::PI * truth.kd[i]), 4))
                .collect()
        };
        let _ = write!(
            h,
            "<p>Its true albedo {cols} is π kd = {}.</p>",
            albedo.join(", ")
        );
    }
}

/// The capture: state, rig, camera, lamp, frames, exposures, time.
fn capture(h: &mut String, m: &session::Manifest) {
    h.push_str("<h2>Capture</h2>\n<table>");
    let row = |h: &mut String, k: &str, v: String| {
        let _ = write!(h, "<tr><th>{}</th><td>{}</td></tr>", esc(k), esc(&v));
    };
    row(h, "state", session::State::as_str(m.state).into());
    if let Some(f) = &m.failure {
        row(h, "failure", f.clone());
    }
    if let Some(rig) = &m.rig {
        row(
            h,
            "rig",
            format!("{} ({})", rig.rig.name, rig.rig.description),
        );
    }
    if let Some(c) = &m.camera {
        row(
            h,
            "camera",
            format!(
                "{}, {}x{}, {}-bit, {}",
                c.model,
                c.width,
                c.height,
                c.bit_depth,
                if c.channels == 1 { "mono" } else { "RGB" }
            ),
        );
    }
    row(h, "lamp", m.lamp_identity.as_deref().unwrap_or("–").into());
    let count = |k: FrameKind| m.frames.iter().filter(|f| f.kind == k).count();
    row(
        h,
        "frames",
        format!(
            "{} tile, {} dark, {} grid",
            count(FrameKind::Tile),
            count(FrameKind::Dark),
            count(FrameKind::Grid)
        ),
    );
    let mut exposures: Vec<f64> = m
        .frames
        .iter()
        .filter(|f| f.kind == FrameKind::Tile)
        .map(|f| f.exposure_us())
        .collect();
    exposures.dedup();
    row(
        h,
        "exposures (µs)",
        exposures
            .iter()
            .map(|e| format!("{e}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    let mut verified: Vec<(String, usize)> = Vec::new();
    for f in &m.frames {
        let k = serde_json::to_value(f.exposure_verified_by)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_default();
        match verified.iter_mut().find(|(n, _)| *n == k) {
            Some(e) => e.1 += 1,
            None => verified.push((k, 1)),
        }
    }
    row(
        h,
        "exposure verified by",
        verified
            .iter()
            .map(|(k, n)| format!("{k} ({n})"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    row(
        h,
        "time",
        format!("{} to {}", m.created, m.finished.as_deref().unwrap_or("?")),
    );
    h.push_str("</table>\n");
}

/// The HDR merge: the response, the radiance's range and noise, what was saturated or too
/// dark.
fn hdr_section(
    h: &mut String,
    missing: &mut Vec<String>,
    dir: &Path,
    hdr: Option<&HdrSummary>,
    figs: &Figures,
) {
    h.push_str("<h2>HDR merge</h2>\n");
    let Some(s) = hdr else {
        not_yet(h, missing, "hdr", "Not merged yet", dir);
        return;
    };
    let total = [s.samples_measured, s.samples_saturated, s.samples_too_dark]
        .iter()
        .filter_map(|x| x.map(|x| x as f64))
        .sum::<f64>()
        .max(1.0);
    let src = match s.response.kind.as_deref() {
        Some("recovered") => "recovered from this session".to_string(),
        Some(k) => format!("{k} {}", s.response.path.as_deref().unwrap_or("")),
        None => "?".into(),
    };
    let share = |x: Option<u64>| x.map(|x| 100.0 * x as f64 / total);
    let _ = writeln!(
        h,
        "<table><tr><th>response</th><td>{} ({})</td></tr><tr><th>radiance range</th><td>{} to {}</td></tr><tr><th>median relative sd</th><td>{}%</td></tr><tr><th>saturated in every exposure</th><td>{}%</td></tr><tr><th>too dark in every exposure</th><td>{}%</td></tr></table>",
        esc(s.model.as_deref().unwrap_or("?")),
        esc(&src),
        sig(s.radiance_min, 4),
        sig(s.radiance_max, 4),
        sig(s.median_relative_sd.map(|x| 100.0 * x), 3),
        sig(share(s.samples_saturated), 3),
        sig(share(s.samples_too_dark), 3),
    );
    warnings(h, &s.warnings);
    figs.fig(h, "response.svg", "The camera's response curve: ln relative exposure against pixel value, per channel, over its valid range, with its 95% band; below, the band's half-width in percent of exposure (on the curve's own scale it is too narrow to see). The band is what the fit's response draws carry into every interval (the coefficients' covariance, the curve's misfit to its data beyond their noise, and a wiggle repeating every exposure step, which a bracket cannot see, as large as that misfit) plus the allowance for the curve's top above 0.8 of full scale, where a fitted curve is weakest.");
}

/// The calibration: its parameters, RMS, the camera's centre, the grid photo and the rig
/// sketch.
fn calibration_section(
    h: &mut String,
    missing: &mut Vec<String>,
    dir: &Path,
    cam: Option<&CameraFile>,
    figs: &Figures,
) {
    h.push_str("<h2>Calibration</h2>\n");
    let Some(c) = cam else {
        not_yet(h, missing, "calibrate", "Not calibrated yet", dir);
        return;
    };
    let cal = &c.calibration;
    h.push_str("<table><tr><th>parameter</th><th>value</th><th>sd</th></tr>");
    for p in &cal.parameters {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&p.name),
            sig(Some(p.value), 6),
            sig(Some(p.sd), 2)
        );
    }
    h.push_str("</table>\n");
    if let Some(v) = cal.views.first() {
        let (cc, sd) = (v.camera_centre, v.camera_centre_sd);
        // Files written before the centre's sd was stored have none.
        let pm = |i: usize| {
            if sd[i] > 0.0 {
                format!("{} ± {}", sig(Some(cc[i]), 5), sig(Some(sd[i]), 2))
            } else {
                sig(Some(cc[i]), 5)
            }
        };
        let _ = writeln!(
            h,
            "<p>RMS reprojection error {} px; camera centre ({}, {}, {}) {} in the grid's frame.</p>",
            sig(Some(cal.rms_px), 3),
            pm(0),
            pm(1),
            pm(2),
            esc(&c.length_unit)
        );
        if let Some(u) = &cal.uncertainty_includes {
            let _ = writeln!(
                h,
                "<p class=\"muted\">The standard deviations include {}.</p>",
                esc(u)
            );
        }
    }
    warnings(h, &cal.warnings);
    figs.fig(h, "corners.png", "The grid photo: detected corners (green), reprojected (red), residuals drawn 50 times longer (yellow).");
    figs.fig(h, "rig.svg", "The rig to scale, from above and from the side in the plane of incidence: the grid (its dark squares grey), the tile (blue), the reference standard (white, where the rig has one), the camera where the calibration put it (a triangle; a circle where the fit refined it with the highlight; the thin line its optical axis to where it meets the grid) and the lamp where the rig file says it is (orange), and the mirror point of the lamp on the tile's top face (red), where the highlight must be, with the light's angle from the normal there. A mirror point off the tile, or far from where the photographs show the highlight, means a lamp position or a tile outline measured wrong.");
    if let Some(e) = &figs.sketch_problem {
        let _ = writeln!(
            h,
            "<p class=\"muted\">No sketch of the rig: {}.</p>",
            esc(e)
        );
    }
}

/// The fit: the sampling, and every candidate's parameters and scores.
fn fit_section(
    h: &mut String,
    missing: &mut Vec<String>,
    dir: &Path,
    fit: Option<&FitFile>,
    ch: &Channels,
) {
    h.push_str("<h2>Reflectance fit</h2>\n");
    let Some(f) = fit else {
        not_yet(h, missing, "fit", "Not fitted yet", dir);
        return;
    };
    let s = &f.sampling;
    let method = f.solver.method.as_str();
    let _ = writeln!(
        h,
        "<p>{} samples ({} sampling, {} asked for) out of {} tile pixels; {} for fitting, {} held out to choose the model. Solver: {}.</p>",
        s.used,
        esc(s.strategy.word().unwrap_or("?")),
        s.requested,
        s.tile_pixels,
        s.fitting_half,
        s.held_out_half,
        esc(if method.is_empty() { "?" } else { method })
    );
    let absolute = f.units.as_deref() == Some("absolute");
    let unit = if absolute { "albedo" } else { "relative units" };
    let (cols, g_name) = (ch.cols, ch.g_name);
    let _ = write!(h, "<table><tr><th>model</th><th>kd {cols}<br><span class=\"muted\">{unit}</span></th><th>ks {cols}<br><span class=\"muted\">{}</span></th><th>n [95%]<br><span class=\"muted\">(ggx: α)</span></th><th>ks/kd {g_name}<br><span class=\"muted\">ratio</span></th><th>χ²/dof</th><th>BIC</th><th>held-out<br><span class=\"muted\">per value</span></th></tr>", if absolute { "sr⁻¹ (ggx: F0)" } else { "relative units" });
    for c in &f.candidates {
        fit_row(h, f, c, absolute, ch);
    }
    h.push_str("</table>\n<p class=\"muted\">Held-out: mean squared standardised residual on the half of the samples not fitted (about 1 for a model that explains the tile to its noise). The simplest model within the tolerance of the best is chosen.</p>\n");
    warnings(h, &f.warnings);
}

/// One candidate's row of the fit's table.
fn fit_row(
    h: &mut String,
    f: &FitFile,
    c: &crate::fit::file::Candidate,
    absolute: bool,
    ch: &Channels,
) {
    let chosen = c.model == f.chosen;
    let lobe = c.model != "lambert";
    // A value at its bound (0) is flagged: its interval is one-sided there.
    let at_bound = |p: &Param| {
        if p.value == Some(0.0) {
            " <b title=\"at its bound: the fit held it at 0\">(at 0)</b>"
        } else {
            ""
        }
    };
    let rgb = |own: &[Param], kd: bool| {
        // Absolute where the standard gave them: kd as albedo, ks in 1/sr (F0).
        let shown: &[Param] = match (&c.absolute, absolute) {
            (Some(a), true) if kd => &a.albedo,
            (Some(a), true) if !a.f0.is_empty() => &a.f0,
            (Some(a), true) => &a.ks_per_sr,
            _ => own,
        };
        (0..ch.n)
            .map(|i| format!("{}{}", pm(&at(shown, i)), at_bound(&at(own, i))))
            .collect::<Vec<_>>()
            .join("<br>")
    };
    let n = c.n.unwrap_or_default();
    let _ = write!(
        h,
        "<tr{}><td>{}{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
        if chosen { " class=\"chosen\"" } else { "" },
        esc(&c.model),
        if chosen { " (chosen)" } else { "" },
        rgb(&c.kd, true),
        if lobe { rgb(&c.ks, false) } else { "–".into() },
        if lobe {
            format!(
                "{} [{}, {}]{}",
                sig(n.value, 4),
                sig(n.ci95[0], 4),
                sig(n.ci95[1], 4),
                match &c.alpha {
                    Some(a) => format!(
                        "<br>α {} [{}, {}]",
                        sig(a.value, 3),
                        sig(a.ci95[0], 3),
                        sig(a.ci95[1], 3)
                    ),
                    None => String::new(),
                }
            )
        } else {
            "–".into()
        },
        if lobe { pm(&at(&c.ks_over_kd, ch.g)) } else { "–".into() },
        sig(c.reduced_chi2, 3),
        sig(c.bic, 6),
        sig(c.held_out, 3),
    );
}

/// The validation: every model against the photographs, the chosen one exposure by
/// exposure, and the figures.
fn validation_section(
    h: &mut String,
    missing: &mut Vec<String>,
    dir: &Path,
    val: Option<&ValidationFile>,
    figs: &Figures,
) {
    h.push_str("<h2>Validation: renders against the photographs</h2>\n");
    let Some(v) = val else {
        not_yet(h, missing, "validate", "Not validated yet", dir);
        return;
    };
    let _ = writeln!(
        h,
        "<p>The scene rendered with each fitted model, mapped through the camera's response to pixel values for every exposure and compared with the photographs over {} tile pixels (readings saturated or too dark in photo or render left out). RMSE is in pixel values, beside the RMSE the noise alone gives on the same readings; the radiance error and mean z² are against the merged HDR radiance.</p>",
        v.tile_pixels
    );
    h.push_str("<table><tr><th>model</th><th>readings</th><th>RMSE</th><th>noise RMSE</th><th>PSNR (dB)</th><th>SSIM</th><th>radiance error</th><th>mean z²</th></tr>");
    for mv in &v.models {
        let _ = write!(
            h,
            "<tr{}><td>{}{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}%</td><td>{}</td></tr>",
            if mv.chosen { " class=\"chosen\"" } else { "" },
            esc(&mv.model),
            if mv.chosen { " (chosen)" } else { "" },
            mv.pixels.readings,
            sig(mv.pixels.rmse, 3),
            sig(mv.pixels.noise_rmse, 3),
            sig(mv.pixels.psnr_db, 4),
            sig(mv.pixels.ssim, 4),
            sig(mv.radiance.relative_error.map(|x| 100.0 * x), 3),
            sig(mv.radiance.mean_z2, 3),
        );
    }
    h.push_str("</table>\n");
    if let Some(cv) = v.chosen() {
        h.push_str("<p>The chosen model, exposure by exposure:</p><table><tr><th>exposure (µs)</th><th>readings</th><th>RMSE</th><th>noise RMSE</th><th>PSNR (dB)</th><th>SSIM</th></tr>");
        for e in &cv.pixels.per_exposure {
            let _ = write!(
                h,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                json_num(e.exposure_us),
                e.readings,
                sig(e.rmse, 3),
                sig(e.noise_rmse, 3),
                sig(e.psnr_db, 4),
                sig(e.ssim, 4),
            );
        }
        h.push_str("</table>\n");
    }
    warnings(h, &v.warnings);
    let t = v.figure_exposure_us.unwrap_or(f64::NAN);
    figs.fig(h, "compare.png", &format!("The photograph at {t} µs beside the render of each model at the same exposure, through the camera's response (as the paper's figures 4 to 7)."));
    figs.fig(h, "difference.png", "Relative radiance difference (model − measured) / measured over the tile, per model, on one colour scale.");
    figs.fig(h, "profile.svg", "Radiance along the line through the highlight in the plane of incidence: measured (with its 95% interval), every fitted model, and the chosen model fitted to this line with saturated pixels clipped (the paper's way) against unsaturated pixels only (the paper's figure 3).");
    if figs.has("brdf.svg") {
        figs.fig(h, "brdf.svg", "The BRDF in the plane of incidence (polar): f_r at each tile point on that line, at the angle of the view direction from the normal, measured (with its 95% interval) against every candidate; in 1/sr where the rig has a reference standard.");
    }
}

/// Write the folder `report/` under a temporary name, then swap it in; returns the page's
/// path and the folder's files.
fn write_folder(
    dir: &Path,
    page: &str,
    copies: &[(&str, Vec<u8>)],
) -> Result<(PathBuf, Vec<String>), ReportError> {
    let out = dir.join("report");
    let tmp = dir.join(format!(".report.new-{}", std::process::id()));
    let old = dir.join(format!(".report.old-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir(&tmp).map_err(|e| file_err(&tmp, e))?;
    let mut files = vec!["index.html".to_string()];
    session::write_new(&tmp.join("index.html"), page.as_bytes())?;
    for (n, bytes) in copies {
        session::write_new(&tmp.join(n), bytes)?;
        files.push(n.to_string());
    }
    if out.symlink_metadata().is_ok() {
        std::fs::rename(&out, &old).map_err(|e| file_err(&out, e))?;
    }
    std::fs::rename(&tmp, &out).map_err(|e| file_err(&out, e))?;
    let _ = std::fs::remove_dir_all(&old);
    Ok((out.join("index.html"), files))
}

/// A stage that has not run: named, with the command that runs it.
fn not_yet(h: &mut String, missing: &mut Vec<String>, stage: &str, what: &str, dir: &Path) {
    missing.push(stage.into());
    let _ = writeln!(
        h,
        "<p class=\"missing\">{what}: <code>glint {stage} {}</code></p>",
        esc(&dir.display().to_string())
    );
}

fn warnings(h: &mut String, w: &[String]) {
    for s in w {
        let _ = writeln!(h, "<p class=\"warn\">warning: {}</p>", esc(s));
    }
}

/// The files an HTML page references (src and href attributes, relative ones only).
pub fn references(html: &str) -> Vec<String> {
    let mut out = Vec::new();
    for attr in ["src=\"", "href=\""] {
        let mut rest = html;
        while let Some(i) = rest.find(attr) {
            rest = &rest[i + attr.len()..];
            if let Some(j) = rest.find('"') {
                let r = &rest[..j];
                if !r.contains("://") && !r.starts_with('#') && !r.starts_with("data:") {
                    out.push(r.to_string());
                }
                rest = &rest[j..];
            }
        }
    }
    out
}
