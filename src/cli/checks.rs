//! `glint rig check` and `glint session verify`.

use std::path::Path;
use std::process::ExitCode;

use anyhow::{bail, Result};
use glint::{devices, rig, session};

pub fn cmd_rig_check(file: &Path, json: bool) -> Result<ExitCode> {
    match rig::load(file) {
        Ok(l) => {
            // A valid rig this build cannot drive (a backend left out of it) is not ok.
            let backends = devices::check_backends(&l.rig);
            if json {
                println!(
                    "{}",
                    serde_json::json!({
                        "file": file, "ok": backends.problems.is_empty(),
                        "problems": backends.problems, "warnings": backends.warnings,
                    })
                );
            } else if !backends.problems.is_empty() {
                for p in &backends.problems {
                    println!("error: {}: {p}", file.display());
                }
            } else if l.rig.camera.backend == rig::CameraBackend::External {
                let c = &l.rig.camera;
                let size = match (c.width, c.bit_depth) {
                    (0, 0) => String::new(),
                    (0, b) => format!(" {b}-bit"),
                    (w, 0) => format!(" {w}x{}", c.height),
                    (w, b) => format!(" {w}x{} {b}-bit", c.height),
                };
                println!(
                    "{}: ok (processing rig `{}`: external camera{size}, {} lamp; Glint does not capture with it: glint import DIR --times FILE --rig {} [--grid PHOTO] [--dark PHOTO])",
                    file.display(),
                    l.rig.rig.name,
                    format!("{:?}", l.rig.lamp.backend).to_lowercase(),
                    file.display()
                );
            } else {
                let r = &l.rig;
                println!(
                    "{}: ok (rig `{}`: {:?} camera {}x{} {}-bit, {:?} lamp, {} exposures {}..{} µs)",
                    file.display(),
                    r.rig.name,
                    r.camera.backend,
                    r.camera.width,
                    r.camera.height,
                    r.camera.bit_depth,
                    r.lamp.backend,
                    r.bracket.exposures_us.len(),
                    r.bracket.exposures_us.first().unwrap_or(&0),
                    r.bracket.exposures_us.last().unwrap_or(&0)
                );
                for w in &backends.warnings {
                    println!("warning: {}: {w}", file.display());
                }
            }
            Ok(if backends.problems.is_empty() {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            })
        }
        Err(e) => {
            let problems = e.problems();
            if json {
                println!(
                    "{}",
                    serde_json::json!({ "file": file, "ok": false, "problems": problems })
                );
            } else if let rig::RigError::Invalid { path, .. } = &e {
                for p in &problems {
                    println!("error: {}: {p}", path.display());
                }
            } else {
                println!("error: {e}");
            }
            Ok(ExitCode::FAILURE)
        }
    }
}

pub fn cmd_session_verify(dir: &Path, json: bool) -> Result<ExitCode> {
    if !dir.join("manifest.json").exists() {
        bail!(
            "{} has no manifest.json; give the session directory that `glint capture` printed",
            dir.display()
        );
    }
    let report = session::verify(dir)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for p in &report.problems {
            println!("problem: {p}");
        }
        for w in &report.warnings {
            println!("note: {w}");
        }
        println!(
            "{}: {} frames, state {}, {}",
            dir.display(),
            report.frames,
            serde_json::to_value(report.state)?.as_str().unwrap_or("?"),
            if report.intact() {
                "all checksums match"
            } else {
                "DAMAGED"
            }
        );
    }
    Ok(if report.intact() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
