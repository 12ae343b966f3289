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

use crate::plan::FrameKind;
use crate::session::{self, SessionError};

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error(transparent)]
    Session(#[from] SessionError),
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
/// ([`crate::fit::file::load`]).
fn check_fit(dir: &Path, m: &session::Manifest) -> Result<(), ReportError> {
    crate::fit::file::load(dir, &crate::fit::file::Facts::of(m))
        .map(|_| ())
        .map_err(|e| ReportError::Input(e.to_string()))
}

/// The session's results as JSON, for scripts (`glint report --json`): each stage's key
/// figures, null where the stage has not run. `hdr`: its summary.json; `calibration`: the
/// model fitted, intrinsics, RMS, the first view's camera centre with its sd, and OpenCV's
/// arrays; `fit`: the chosen model and its candidate (kd, ks, ks/kd, n with sd and 95%
/// interval, reduced chi2, BIC, warnings) and the fit's warnings; `validation`: the chosen
/// model and every model's pixel figures (RMSE, noise RMSE, PSNR, SSIM).
pub fn results(dir: &Path) -> Result<Value, ReportError> {
    if crate::fsx::Within::new(dir, "fit/fit.json").is_there() {
        check_fit(dir, &session::open(dir, true)?)?;
    }
    let hdr = read_json(dir, "hdr/summary.json")?;
    let calibration = read_json(dir, "calib/camera.json")?.map(|c| {
        let cal = &c["calibration"];
        let view = &cal["views"][0];
        serde_json::json!({
            "fit": cal["fit"],
            "intrinsics": cal["intrinsics"],
            "parameters": cal["parameters"],
            "rms_px": cal["rms_px"],
            "camera_centre": view["camera_centre"],
            "camera_centre_sd": view["camera_centre_sd"],
            "length_unit": c["length_unit"],
            "camera_matrix": c["camera_matrix"],
            "dist_coeffs": c["dist_coeffs"],
            "uncertainty_includes": cal["uncertainty_includes"],
            "warnings": cal["warnings"],
        })
    });
    let fit = read_json(dir, "fit/fit.json")?.map(|f| {
        let chosen = f["chosen"].clone();
        let candidate = f["candidates"]
            .as_array()
            .and_then(|cs| cs.iter().find(|c| c["model"] == chosen))
            .map(|c| {
                serde_json::json!({
                    "model": c["model"], "kd": c["kd"], "ks": c["ks"],
                    "ks_over_kd": c["ks_over_kd"], "n": c["n"],
                    "reduced_chi2": c["reduced_chi2"], "bic": c["bic"],
                    "warnings": c["warnings"],
                })
            });
        serde_json::json!({
            "chosen": chosen,
            "candidate": candidate,
            "camera_refined": f.get("camera_refined").cloned(),
            "warnings": f["warnings"],
        })
    });
    let validation = read_json(dir, "validation/validation.json")?.map(|v| {
        let models: Vec<Value> = v["models"]
            .as_array()
            .map(|ms| {
                ms.iter()
                    .map(|m| {
                        let p = &m["pixels"];
                        serde_json::json!({
                            "model": m["model"], "chosen": m["chosen"],
                            "rmse": p["rmse"], "noise_rmse": p["noise_rmse"],
                            "psnr_db": p["psnr_db"], "ssim": p["ssim"],
                        })
                    })
                    .collect()
            })
            .unwrap_or_default();
        serde_json::json!({
            "chosen": v["chosen"],
            "models": models,
            "warnings": v["warnings"],
        })
    });
    Ok(serde_json::json!({
        "hdr": hdr,
        "calibration": calibration,
        "fit": fit,
        "validation": validation,
    }))
}

/// Largest figure the report copies.
const MAX_FIGURE_BYTES: u64 = 256 << 20;

fn num(v: &Value) -> Option<f64> {
    v.as_f64()
}

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
fn pm(p: &Value) -> String {
    let (t, e) = value_sd(
        num(&p["value"]).unwrap_or(f64::NAN),
        num(&p["sd"]).unwrap_or(f64::NAN),
    );
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

/// Write `report/` for a session.
pub fn write(dir: &Path, opts: &ReportOptions) -> Result<Written, ReportError> {
    let manifest = session::open(dir, opts.allow_incomplete)?;
    let warnings_out: Vec<String> = session::incomplete_warning(&manifest).into_iter().collect();
    let m = serde_json::to_value(&manifest).expect("a manifest serialises");
    // Every stage's file, checked as the stage after it checks it.
    let hdr = match read_json(dir, "hdr/summary.json")? {
        Some(_) => Some(
            crate::fit::run::load_hdr_summary(&crate::fsx::Within::new(dir, "hdr/summary.json"))
                .map_err(ReportError::Input)?,
        ),
        None => None,
    };
    let cam = match read_json(dir, "calib/camera.json")? {
        Some(_) => Some(
            crate::calib::run::load_camera_file(crate::fsx::Within::new(dir, "calib/camera.json"))
                .map_err(|e| ReportError::Input(e.to_string()))?
                .0,
        ),
        None => None,
    };
    let fit = read_json(dir, "fit/fit.json")?;
    if fit.is_some() {
        check_fit(dir, &manifest)?;
    }
    let val_path = dir.join("validation/validation.json");
    let val = read_json(dir, "validation/validation.json")?;
    if let Some(v) = &val {
        if v["format"] != crate::validate::FORMAT || !v["models"].is_array() {
            return Err(file_err(
                &val_path,
                "not a glint-validation file; re-run glint validate",
            ));
        }
    }
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| dir.display().to_string());

    // Figures to copy: (source, name in report/).
    let within = |rel: &str| crate::fsx::Within::new(dir, rel);
    let mut figures: Vec<(crate::fsx::Within, &str)> = vec![
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
    // Only figures Glint wrote: the fixed list above, each a regular file inside the
    // session reached through no symbolic link, size-capped. One missing is left out (its
    // stage has not run); one there but unreadable (a link, a device, too big) is an error.
    let mut copies: Vec<(&str, Vec<u8>)> = Vec::new();
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
    // The rig's geometry, drawn here from the rig the session recorded and the camera
    // the calibration found (and the fit's refinement of it, where there is one).
    let mut sketch_problem = None;
    if let (Some(rig), Some(c)) = (&manifest.rig, &cam) {
        let v3 = |v: &Value| -> Option<[f64; 3]> { Some([num(&v[0])?, num(&v[1])?, num(&v[2])?]) };
        if let Some(camera) = v3(&c["calibration"]["views"][0]["camera_centre"]) {
            let sketch = crate::sketch::RigSketch {
                geometry: &rig.geometry,
                reference: rig.reference.as_ref(),
                camera,
                axis: v3(&c["rotations"][0][2]),
                refined: fit
                    .as_ref()
                    .and_then(|f| v3(&f["camera_refined"]["centre_mm"])),
            };
            match crate::sketch::rig_svg(&sketch) {
                Ok(svg) => copies.push(("rig.svg", svg.into_bytes())),
                Err(e) => sketch_problem = Some(e.to_string()),
            }
        }
    }
    let present: Vec<&str> = copies.iter().map(|(n, _)| *n).collect();
    let has = |n: &str| present.contains(&n);
    let fig = |h: &mut String, n: &str, caption: &str| {
        if has(n) {
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
    };
    let mut missing = Vec::new();
    let mut h = String::new();
    let _ = writeln!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Glint report: {}</title><style>{STYLE}</style></head><body>\n<h1>Glint report: {}</h1>\n<p class=\"muted\">Session <code>{}</code>, captured {}; report written {} by glint {}.</p>",
        esc(&name),
        esc(&name),
        esc(&dir.display().to_string()),
        esc(m["created"].as_str().unwrap_or("?")),
        esc(&session::timestamp(std::time::SystemTime::now())),
        env!("CARGO_PKG_VERSION")
    );

    // The session's state, where it is not complete, first and prominently.
    if manifest.state != session::State::Complete {
        let _ = writeln!(
            h,
            "<p class=\"incomplete\"><b>Incomplete session: state {}</b>{}. Every result below comes from an unfinished capture ({} frames); re-capture before relying on it.</p>",
            esc(m["state"].as_str().unwrap_or("?")),
            m["failure"]
                .as_str()
                .map(|f| format!(" ({})", esc(f)))
                .unwrap_or_default(),
            manifest.frames.len()
        );
    }

    // A monochrome camera's results have one channel: kd, ks and ks/kd one value each
    // (the fit's "channels", else the session's).
    let channels = fit
        .as_ref()
        .and_then(|f| f["channels"].as_u64())
        .unwrap_or(manifest.channels() as u64) as usize;
    let mono = channels == 1;
    let (cols, g) = if mono {
        ("(mono)", 0)
    } else {
        ("(R, G, B)", 1)
    };
    let g_name = if mono { "(mono)" } else { "(G)" };

    // The summary.
    h.push_str("<div class=\"summary\">");
    match (&fit, &val) {
        (Some(f), v) => {
            let chosen = f["chosen"].as_str().unwrap_or("?");
            let c = f["candidates"]
                .as_array()
                .and_then(|a| a.iter().find(|c| c["model"] == f["chosen"]));
            let _ = write!(h, "<p><b>Chosen model: {}</b>", esc(chosen));
            if let Some(c) = c {
                let rgb = |k: &str| {
                    (0..channels)
                        .map(|i| pm(&c[k][i]))
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let _ = write!(h, "<br>kd {cols} = {}", rgb("kd"));
                if chosen != "lambert" {
                    let _ = write!(
                        h,
                        "<br>ks {cols} = {}<br>n = {} (95%: {} to {})<br>ks/kd {g_name} = {}",
                        rgb("ks"),
                        sig(num(&c["n"]["value"]), 4),
                        sig(num(&c["n"]["ci95"][0]), 4),
                        sig(num(&c["n"]["ci95"][1]), 4),
                        pm(&c["ks_over_kd"][g])
                    );
                    if c["alpha"].is_object() {
                        let _ = write!(
                            h,
                            "<br>α (roughness) = {} (95%: {} to {})",
                            sig(num(&c["alpha"]["value"]), 4),
                            sig(num(&c["alpha"]["ci95"][0]), 4),
                            sig(num(&c["alpha"]["ci95"][1]), 4)
                        );
                    }
                }
                let abs = &c["absolute"];
                if abs.is_object() && f["units"] == "absolute" {
                    let arr = |k: &str| {
                        (0..channels)
                            .map(|i| pm(&abs[k][i]))
                            .collect::<Vec<_>>()
                            .join(", ")
                    };
                    let _ = write!(h, "<br><b>albedo {cols} = {}</b>", arr("albedo"));
                    if abs["f0"].is_array() {
                        let _ = write!(h, "<br>F0 {cols} = {}", arr("f0"));
                    } else if chosen != "lambert" {
                        let _ = write!(h, "<br>ks {cols} = {} sr⁻¹", arr("ks_per_sr"));
                    }
                    let r = &f["reference"];
                    let _ = write!(
                        h,
                        "<br><span class=\"muted\">Absolute: the reference standard (reflectance {}, {} pixels) gives the factor the lamp and camera put on the radiance, known to ±{}%; kd and ks above it are in the radiance's relative units. Albedo = π kd, ks in sr⁻¹ (DESIGN.md's f_r). Intervals include the factor's, the calibration's and the response curve's uncertainty.</span>",
                        r["reflectance"]
                            .as_array()
                            .map(|a| a.iter().map(|x| sig(num(x), 4)).collect::<Vec<_>>().join(", "))
                            .unwrap_or_default(),
                        r["pixels"],
                        r["factor_relative_sd"]
                            .as_array()
                            .map(|a| {
                                sig(
                                    a.iter()
                                        .filter_map(|x| num(&x["total"]))
                                        .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
                                        .map(|x| 100.0 * x),
                                    2,
                                )
                            })
                            .unwrap_or_default()
                    );
                } else {
                    h.push_str("<br><span class=\"muted\">kd and ks are in the radiance's relative units (lamp intensity and camera gain included: the rig has no [reference] standard to take them out); their ratios and n are absolute. Intervals include the calibration's and the response curve's uncertainty where fit.json says so.</span>");
                }
            }
            h.push_str("</p>");
            let truth = &m["rig"]["mock"]["tile"];
            if let Some(model) = truth["model"].as_str() {
                let lobe = model != "lambert";
                // A mono camera sees the mean of the three bands: kd = mean(kd), ks =
                // mean(ks), the same n.
                let mean = |k: &str| -> Option<f64> {
                    (0..3)
                        .map(|i| num(&truth[k][i]))
                        .sum::<Option<f64>>()
                        .map(|s| s / 3.0)
                };
                let (kd_seen, ks_seen) = if mono {
                    (mean("kd"), mean("ks"))
                } else {
                    (num(&truth["kd"][1]), num(&truth["ks"][1]))
                };
                let ratio = ks_seen.zip(kd_seen).map(|(s, d)| s / d);
                let _ = write!(
                    h,
                    "<p>Simulated lab: the true tile is {}{}{}; the chosen model {}.</p>",
                    esc(model),
                    if mono {
                        format!(
                            " (as the mono camera sees it, the mean of the three bands: kd = {})",
                            sig(kd_seen, 4)
                        )
                    } else {
                        String::new()
                    },
                    if model == "ggx" {
                        format!(
                            ", α = {} (n = {}), F0 {g_name} = {}",
                            sig(num(&truth["alpha"]), 4),
                            sig(
                                num(&truth["alpha"]).map(crate::fit::model::ggx::exponent),
                                4
                            ),
                            sig(ks_seen, 4)
                        )
                    } else if lobe {
                        format!(
                            ", n = {}, ks/kd {g_name} = {}",
                            sig(num(&truth["n"]), 4),
                            sig(ratio, 4)
                        )
                    } else {
                        String::new()
                    },
                    if Some(model) == f["chosen"].as_str() {
                        "matches"
                    } else {
                        "<b>does not match</b>"
                    }
                );
                if f["units"] == "absolute" {
                    let albedo: Vec<String> = if mono {
                        vec![sig(mean("kd").map(|k| std::f64::consts::PI * k), 4)]
                    } else {
                        (0..3)
                            .map(|i| sig(num(&truth["kd"][i]).map(|k| std::f64::consts::PI * k), 4))
                            .collect()
                    };
                    let _ = write!(
                        h,
                        "<p>Its true albedo {cols} is π kd = {}.</p>",
                        albedo.join(", ")
                    );
                }
            }
            if let Some(v) = v {
                if let Some(cv) = v["models"]
                    .as_array()
                    .and_then(|a| a.iter().find(|x| x["chosen"] == true))
                {
                    let _ = write!(
                        h,
                        "<p>Validation: PSNR <b>{} dB</b>, RMSE {} against {} from noise alone (pixel values, every exposure); relative radiance error {}%; SSIM {}.</p>",
                        sig(num(&cv["pixels"]["psnr_db"]), 4),
                        sig(num(&cv["pixels"]["rmse"]), 3),
                        sig(num(&cv["pixels"]["noise_rmse"]), 3),
                        sig(num(&cv["radiance"]["relative_error"]).map(|x| 100.0 * x), 3),
                        sig(num(&cv["pixels"]["ssim"]), 4),
                    );
                }
            }
        }
        (None, _) => h.push_str("<p class=\"missing\">No fit yet.</p>"),
    }
    h.push_str("</div>\n");

    // Capture.
    h.push_str("<h2>Capture</h2>\n<table>");
    let rig = &m["rig"];
    let row = |h: &mut String, k: &str, v: String| {
        let _ = write!(h, "<tr><th>{}</th><td>{}</td></tr>", esc(k), esc(&v));
    };
    row(&mut h, "state", m["state"].as_str().unwrap_or("?").into());
    if let Some(f) = m["failure"].as_str() {
        row(&mut h, "failure", f.into());
    }
    if rig.is_object() {
        row(
            &mut h,
            "rig",
            format!(
                "{} ({})",
                rig["rig"]["name"].as_str().unwrap_or("?"),
                rig["rig"]["description"].as_str().unwrap_or("")
            ),
        );
    }
    if let Some(c) = &manifest.camera {
        row(
            &mut h,
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
    row(
        &mut h,
        "lamp",
        m["lamp_identity"].as_str().unwrap_or("–").into(),
    );
    let count = |k: FrameKind| manifest.frames.iter().filter(|f| f.kind == k).count();
    row(
        &mut h,
        "frames",
        format!(
            "{} tile, {} dark, {} grid",
            count(FrameKind::Tile),
            count(FrameKind::Dark),
            count(FrameKind::Grid)
        ),
    );
    let mut exposures: Vec<f64> = manifest
        .frames
        .iter()
        .filter(|f| f.kind == FrameKind::Tile)
        .map(|f| f.exposure_us())
        .collect();
    exposures.dedup();
    row(
        &mut h,
        "exposures (µs)",
        exposures
            .iter()
            .map(|e| format!("{e}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    let mut verified: Vec<(String, usize)> = Vec::new();
    for f in &manifest.frames {
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
        &mut h,
        "exposure verified by",
        verified
            .iter()
            .map(|(k, n)| format!("{k} ({n})"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    row(
        &mut h,
        "time",
        format!(
            "{} to {}",
            m["created"].as_str().unwrap_or("?"),
            m["finished"].as_str().unwrap_or("?")
        ),
    );
    h.push_str("</table>\n");

    // HDR.
    h.push_str("<h2>HDR merge</h2>\n");
    match &hdr {
        Some(s) => {
            let total = ["samples_measured", "samples_saturated", "samples_too_dark"]
                .iter()
                .filter_map(|k| s[*k].as_f64())
                .sum::<f64>()
                .max(1.0);
            let src = match s["response"]["kind"].as_str() {
                Some("recovered") => "recovered from this session".to_string(),
                Some(k) => format!("{k} {}", s["response"]["path"].as_str().unwrap_or("")),
                None => "?".into(),
            };
            let _ = writeln!(
                h,
                "<table><tr><th>response</th><td>{} ({})</td></tr><tr><th>radiance range</th><td>{} to {}</td></tr><tr><th>median relative sd</th><td>{}%</td></tr><tr><th>saturated in every exposure</th><td>{}%</td></tr><tr><th>too dark in every exposure</th><td>{}%</td></tr></table>",
                esc(s["model"].as_str().unwrap_or("?")),
                esc(&src),
                sig(num(&s["radiance_min"]), 4),
                sig(num(&s["radiance_max"]), 4),
                sig(num(&s["median_relative_sd"]).map(|x| 100.0 * x), 3),
                sig(s["samples_saturated"].as_f64().map(|x| 100.0 * x / total), 3),
                sig(s["samples_too_dark"].as_f64().map(|x| 100.0 * x / total), 3),
            );
            warnings(&mut h, &s["warnings"]);
            fig(&mut h, "response.svg", "The camera's response curve: ln relative exposure against pixel value, per channel, over its valid range, with its 95% band; below, the band's half-width in percent of exposure (on the curve's own scale it is too narrow to see). The band is what the fit's response draws carry into every interval (the coefficients' covariance, the curve's misfit to its data beyond their noise, and a wiggle repeating every exposure step, which a bracket cannot see, as large as that misfit) plus the allowance for the curve's top above 0.8 of full scale, where a fitted curve is weakest.");
        }
        None => {
            not_yet(&mut h, &mut missing, "hdr", "Not merged yet", dir);
        }
    }

    // Calibration.
    h.push_str("<h2>Calibration</h2>\n");
    match &cam {
        Some(c) => {
            let cal = &c["calibration"];
            h.push_str("<table><tr><th>parameter</th><th>value</th><th>sd</th></tr>");
            for p in cal["parameters"].as_array().into_iter().flatten() {
                let _ = write!(
                    h,
                    "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
                    esc(p["name"].as_str().unwrap_or("?")),
                    sig(num(&p["value"]), 6),
                    sig(num(&p["sd"]), 2)
                );
            }
            h.push_str("</table>\n");
            if let Some(v) = cal["views"].get(0) {
                let cc = &v["camera_centre"];
                let sd = &v["camera_centre_sd"];
                // Files written before the centre's sd was stored have none.
                let pm = |i: usize| {
                    if num(&sd[i]).is_some_and(|x| x > 0.0) {
                        format!("{} ± {}", sig(num(&cc[i]), 5), sig(num(&sd[i]), 2))
                    } else {
                        sig(num(&cc[i]), 5)
                    }
                };
                let _ = writeln!(
                    h,
                    "<p>RMS reprojection error {} px; camera centre ({}, {}, {}) {} in the grid's frame.</p>",
                    sig(num(&cal["rms_px"]), 3),
                    pm(0),
                    pm(1),
                    pm(2),
                    esc(c["length_unit"].as_str().unwrap_or(""))
                );
                if let Some(u) = cal["uncertainty_includes"].as_str() {
                    let _ = writeln!(
                        h,
                        "<p class=\"muted\">The standard deviations include {}.</p>",
                        esc(u)
                    );
                }
            }
            warnings(&mut h, &cal["warnings"]);
            fig(&mut h, "corners.png", "The grid photo: detected corners (green), reprojected (red), residuals drawn 50 times longer (yellow).");
            fig(&mut h, "rig.svg", "The rig to scale, from above and from the side in the plane of incidence: the grid (its dark squares grey), the tile (blue), the reference standard (white, where the rig has one), the camera where the calibration put it (a triangle; a circle where the fit refined it with the highlight; the thin line its optical axis to where it meets the grid) and the lamp where the rig file says it is (orange), and the mirror point of the lamp on the tile's top face (red), where the highlight must be, with the light's angle from the normal there. A mirror point off the tile, or far from where the photographs show the highlight, means a lamp position or a tile outline measured wrong.");
            if let Some(e) = &sketch_problem {
                let _ = writeln!(
                    h,
                    "<p class=\"muted\">No sketch of the rig: {}.</p>",
                    esc(e)
                );
            }
        }
        None => {
            not_yet(&mut h, &mut missing, "calibrate", "Not calibrated yet", dir);
        }
    }

    // Fit.
    h.push_str("<h2>Reflectance fit</h2>\n");
    match &fit {
        Some(f) => {
            let s = &f["sampling"];
            let _ = writeln!(
                h,
                "<p>{} samples ({} sampling, {} asked for) out of {} tile pixels; {} for fitting, {} held out to choose the model. Solver: {}.</p>",
                s["used"],
                esc(s["strategy"].as_str().unwrap_or("?")),
                s["requested"],
                s["tile_pixels"],
                s["fitting_half"],
                s["held_out_half"],
                esc(f["solver"]["method"].as_str().unwrap_or("?"))
            );
            let absolute = f["units"] == "absolute";
            let unit = if absolute { "albedo" } else { "relative units" };
            let _ = write!(h, "<table><tr><th>model</th><th>kd {cols}<br><span class=\"muted\">{unit}</span></th><th>ks {cols}<br><span class=\"muted\">{}</span></th><th>n [95%]<br><span class=\"muted\">(ggx: α)</span></th><th>ks/kd {g_name}<br><span class=\"muted\">ratio</span></th><th>χ²/dof</th><th>BIC</th><th>held-out<br><span class=\"muted\">per value</span></th></tr>", if absolute { "sr⁻¹ (ggx: F0)" } else { "relative units" });
            for c in f["candidates"].as_array().into_iter().flatten() {
                let chosen = c["model"] == f["chosen"];
                let lobe = c["model"] != "lambert";
                // A value at its bound (0) is flagged: its interval is one-sided there.
                let at_bound = |p: &Value| {
                    if num(&p["value"]) == Some(0.0) {
                        " <b title=\"at its bound: the fit held it at 0\">(at 0)</b>"
                    } else {
                        ""
                    }
                };
                let abs = &c["absolute"];
                let rgb = |k: &str| {
                    // Absolute where the standard gave them: kd as albedo, ks in 1/sr (F0).
                    let key = match (absolute && abs.is_object(), k) {
                        (true, "kd") => Some("albedo"),
                        (true, "ks") if abs["f0"].is_array() => Some("f0"),
                        (true, "ks") => Some("ks_per_sr"),
                        _ => None,
                    };
                    (0..channels)
                        .map(|i| {
                            let p = match key {
                                Some(key) => &abs[key][i],
                                None => &c[k][i],
                            };
                            format!("{}{}", pm(p), at_bound(&c[k][i]))
                        })
                        .collect::<Vec<_>>()
                        .join("<br>")
                };
                let _ = write!(
                    h,
                    "<tr{}><td>{}{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                    if chosen { " class=\"chosen\"" } else { "" },
                    esc(c["model"].as_str().unwrap_or("?")),
                    if chosen { " (chosen)" } else { "" },
                    rgb("kd"),
                    if lobe { rgb("ks") } else { "–".into() },
                    if lobe {
                        format!(
                            "{} [{}, {}]{}",
                            sig(num(&c["n"]["value"]), 4),
                            sig(num(&c["n"]["ci95"][0]), 4),
                            sig(num(&c["n"]["ci95"][1]), 4),
                            if c["alpha"].is_object() {
                                format!(
                                    "<br>α {} [{}, {}]",
                                    sig(num(&c["alpha"]["value"]), 3),
                                    sig(num(&c["alpha"]["ci95"][0]), 3),
                                    sig(num(&c["alpha"]["ci95"][1]), 3)
                                )
                            } else {
                                String::new()
                            }
                        )
                    } else {
                        "–".into()
                    },
                    if lobe { pm(&c["ks_over_kd"][g]) } else { "–".into() },
                    sig(num(&c["reduced_chi2"]), 3),
                    sig(num(&c["bic"]), 6),
                    sig(num(&c["held_out"]), 3),
                );
            }
            h.push_str("</table>\n<p class=\"muted\">Held-out: mean squared standardised residual on the half of the samples not fitted (about 1 for a model that explains the tile to its noise). The simplest model within the tolerance of the best is chosen.</p>\n");
            warnings(&mut h, &f["warnings"]);
        }
        None => {
            not_yet(&mut h, &mut missing, "fit", "Not fitted yet", dir);
        }
    }

    // Validation.
    h.push_str("<h2>Validation: renders against the photographs</h2>\n");
    match &val {
        Some(v) => {
            let _ = writeln!(
                h,
                "<p>The scene rendered with each fitted model, mapped through the camera's response to pixel values for every exposure and compared with the photographs over {} tile pixels (readings saturated or too dark in photo or render left out). RMSE is in pixel values, beside the RMSE the noise alone gives on the same readings; the radiance error and mean z² are against the merged HDR radiance.</p>",
                v["tile_pixels"]
            );
            h.push_str("<table><tr><th>model</th><th>readings</th><th>RMSE</th><th>noise RMSE</th><th>PSNR (dB)</th><th>SSIM</th><th>radiance error</th><th>mean z²</th></tr>");
            for mv in v["models"].as_array().into_iter().flatten() {
                let chosen = mv["chosen"] == true;
                let _ = write!(
                    h,
                    "<tr{}><td>{}{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}%</td><td>{}</td></tr>",
                    if chosen { " class=\"chosen\"" } else { "" },
                    esc(mv["model"].as_str().unwrap_or("?")),
                    if chosen { " (chosen)" } else { "" },
                    mv["pixels"]["readings"],
                    sig(num(&mv["pixels"]["rmse"]), 3),
                    sig(num(&mv["pixels"]["noise_rmse"]), 3),
                    sig(num(&mv["pixels"]["psnr_db"]), 4),
                    sig(num(&mv["pixels"]["ssim"]), 4),
                    sig(num(&mv["radiance"]["relative_error"]).map(|x| 100.0 * x), 3),
                    sig(num(&mv["radiance"]["mean_z2"]), 3),
                );
            }
            h.push_str("</table>\n");
            if let Some(cv) = v["models"]
                .as_array()
                .and_then(|a| a.iter().find(|x| x["chosen"] == true))
            {
                h.push_str("<p>The chosen model, exposure by exposure:</p><table><tr><th>exposure (µs)</th><th>readings</th><th>RMSE</th><th>noise RMSE</th><th>PSNR (dB)</th><th>SSIM</th></tr>");
                for e in cv["pixels"]["per_exposure"]
                    .as_array()
                    .into_iter()
                    .flatten()
                {
                    let _ = write!(
                        h,
                        "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                        e["exposure_us"],
                        e["readings"],
                        sig(num(&e["rmse"]), 3),
                        sig(num(&e["noise_rmse"]), 3),
                        sig(num(&e["psnr_db"]), 4),
                        sig(num(&e["ssim"]), 4),
                    );
                }
                h.push_str("</table>\n");
            }
            warnings(&mut h, &v["warnings"]);
            let t = v["figure_exposure_us"].as_f64().unwrap_or(f64::NAN);
            fig(&mut h, "compare.png", &format!("The photograph at {t} µs beside the render of each model at the same exposure, through the camera's response (as the paper's figures 4 to 7)."));
            fig(&mut h, "difference.png", "Relative radiance difference (model − measured) / measured over the tile, per model, on one colour scale.");
            fig(&mut h, "profile.svg", "Radiance along the line through the highlight in the plane of incidence: measured (with its 95% interval), every fitted model, and the chosen model fitted to this line with saturated pixels clipped (the paper's way) against unsaturated pixels only (the paper's figure 3).");
            if has("brdf.svg") {
                fig(&mut h, "brdf.svg", "The BRDF in the plane of incidence (polar): f_r at each tile point on that line, at the angle of the view direction from the normal, measured (with its 95% interval) against every candidate; in 1/sr where the rig has a reference standard.");
            }
        }
        None => {
            not_yet(&mut h, &mut missing, "validate", "Not validated yet", dir);
        }
    }
    if has("fit_bench.svg") {
        h.push_str("<h2>Speed against accuracy</h2>\n");
        fig(&mut h, "fit_bench.svg", "Fit time against error by sample count and sampling strategy (glint bench fit, on simulated tiles).");
    }
    h.push_str("<h2>Files</h2>\n<p class=\"muted\">In the session: <code>manifest.json</code>, <code>frames/</code>, <code>hdr/</code>, <code>calib/camera.json</code>, <code>fit/fit.json</code>, <code>fit/samples.csv</code>, <code>validation/validation.json</code>. This page and its figures are in <code>report/</code>.</p>\n</body></html>\n");

    // Write the folder under a temporary name, then swap it in.
    let out = dir.join("report");
    let tmp = dir.join(format!(".report.new-{}", std::process::id()));
    let old = dir.join(format!(".report.old-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir(&tmp).map_err(|e| file_err(&tmp, e))?;
    let mut files = vec!["index.html".to_string()];
    session::write_new(&tmp.join("index.html"), h.as_bytes())?;
    for (n, bytes) in &copies {
        session::write_new(&tmp.join(n), bytes)?;
        files.push(n.to_string());
    }
    if out.symlink_metadata().is_ok() {
        std::fs::rename(&out, &old).map_err(|e| file_err(&out, e))?;
    }
    std::fs::rename(&tmp, &out).map_err(|e| file_err(&out, e))?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(Written {
        index: out.join("index.html"),
        files,
        missing,
        warnings: warnings_out,
    })
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

fn warnings(h: &mut String, w: &Value) {
    for w in w.as_array().into_iter().flatten() {
        if let Some(s) = w.as_str() {
            let _ = writeln!(h, "<p class=\"warn\">warning: {}</p>", esc(s));
        }
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
