//! `glint import`, `glint response` and `glint hdr`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use glint::hdr::response::{ModelChoice, RecoverOptions, Response};
use glint::hdr::run::{self, HdrEvent, HdrOptions};
use glint::import;
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Args)]
pub struct ImportArgs {
    /// Folder of bracketed photos (PNG, JPEG, TIFF, or uncompressed DNG read as half-size
    /// linear RGB; 8 or 16 bits; regular files, not links),
    /// all of one scene, at most 16384 pixels a side and 160 megapixels each. Photos are
    /// decoded one at a time; brightness must rise with exposure time (a photo exposed
    /// longer but clearly darker than the one before it is refused: the times are wrong,
    /// or in 1/s).
    #[arg(value_name = "DIR")]
    dir: PathBuf,
    /// Exposure times: one line per photo, `<file name> <seconds> [tile|dark|grid]`, the
    /// time as a decimal (0.004) or a fraction (1/250), from 1 µs to 1 hour (3600), the
    /// kind `tile` (the bracket) unless named. Without it the photos' EXIF ExposureTime is
    /// used (EXIF aperture and ISO are recorded, and a change within the bracket warned of).
    #[arg(long, value_name = "FILE")]
    times: Option<PathBuf>,
    /// The rig whose geometry and grid the session holds, so that calibrate, fit, validate
    /// and report run on it: a processing rig (`camera.backend = "external"`, `lamp.backend =
    /// "external"`, a [geometry]; see rigs/processing-example.toml) or the rig of the bench
    /// the photos were taken on. Without it only `glint hdr` applies.
    #[arg(long, value_name = "RIG")]
    rig: Option<PathBuf>,
    /// A grid photo: the chessboard with the tile removed, same camera, lens and focus
    /// (a path, or a name in DIR; its time from the times file or EXIF). Repeatable; needs
    /// --rig.
    #[arg(long, value_name = "PHOTO")]
    grid: Vec<PathBuf>,
    /// A dark photo: lens capped, at one of the bracket's exposures (subtracted from the
    /// tile photos of that exposure). Repeatable.
    #[arg(long, value_name = "PHOTO")]
    dark: Vec<PathBuf>,
    /// Where to write the session; must not exist or be empty. It is built beside it in a
    /// temporary folder and renamed into place once every photo is good.
    /// [default: sessions/import-<folder name>-<UTC time>]
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ModelArg {
    /// Fit every model (any bit depth) and keep the simplest whose shape fits the bracket as well as any; the others that fit nearly as well are kept as alternatives, which `glint fit` counts into the intervals
    Auto,
    /// Debevec & Malik: a free curve of 256 values (above 8 bits: on 256 bins of values).
    Debevec,
    /// ln exposure a polynomial in ln(value), degree chosen by BIC.
    Polynomial,
    /// Linear: value = black + exposure / gain (black from the dark frames); warns when
    /// the data show a tone curve.
    Linear,
}

#[derive(Args)]
pub struct RecoverArgs {
    /// Response model (used when a response is recovered).
    #[arg(long, value_enum, default_value = "auto")]
    model: ModelArg,
    /// Smoothness weight of the Debevec curve (Debevec & Malik's / OpenCV's lambda).
    #[arg(long, default_value_t = 10.0)]
    lambda: f64,
    /// Sample pixels per channel [default: from the number of exposures, 300..600, and
    /// eight times as many, up to 4800, for the linear and polynomial curves and the
    /// noise]. Debevec's curve takes at most 1500 (its solve grows with their cube).
    #[arg(long)]
    samples: Option<usize>,
}

impl RecoverArgs {
    fn options(&self) -> Result<RecoverOptions> {
        if !(self.lambda.is_finite() && self.lambda >= 0.0) {
            bail!("--lambda must be zero or positive, got {}", self.lambda);
        }
        Ok(RecoverOptions {
            model: match self.model {
                ModelArg::Auto => ModelChoice::Auto,
                ModelArg::Debevec => ModelChoice::Debevec,
                ModelArg::Polynomial => ModelChoice::Polynomial,
                ModelArg::Linear => ModelChoice::Linear,
            },
            lambda: self.lambda,
            samples: self.samples,
            ..RecoverOptions::default()
        })
    }
}

#[derive(Args)]
pub struct ResponseArgs {
    /// The session (a folder written by `glint capture` or `glint import`).
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    #[command(flatten)]
    recover: RecoverArgs,
    /// Camera profile file to store the response in
    /// [default with --rig: <rig folder>/profiles/<camera>-<bits>bit.response.json, or
    /// <camera>-<bits>bit-mono.response.json for a monochrome camera].
    #[arg(long, value_name = "FILE")]
    profile: Option<PathBuf>,
    /// The rig file you capture with: the camera's profile is kept beside it (never where
    /// the session's manifest says).
    #[arg(long, value_name = "FILE")]
    rig: Option<PathBuf>,
    /// Replace an existing camera profile (otherwise it is kept and only the session's
    /// hdr/ gets the new curve). Refused for a session that is not complete or fails the
    /// profile's checks (at least 3 exposures, enough valid readings).
    #[arg(long)]
    replace_profile: bool,
    /// Work on a session that is not complete (`capturing`: killed, or `failed`), with a
    /// warning; its response never becomes the camera's profile.
    #[arg(long)]
    allow_incomplete: bool,
    /// Print the response summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct HdrArgs {
    /// The session (a folder written by `glint capture` or `glint import`).
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// Use this response file (JSON from `glint response`) instead of the camera profile.
    #[arg(long, value_name = "FILE")]
    response: Option<PathBuf>,
    /// Recover the response from this session even if the camera has a profile.
    #[arg(long)]
    recover: bool,
    #[command(flatten)]
    recover_args: RecoverArgs,
    /// Camera profile file [default with --rig: <rig folder>/profiles/<camera>-<bits>bit.response.json].
    #[arg(long, value_name = "FILE")]
    profile: Option<PathBuf>,
    /// The rig file you capture with: the camera's profile beside it is used, or stored
    /// when this session's response is recovered (never where the session's manifest says).
    #[arg(long, value_name = "FILE")]
    rig: Option<PathBuf>,
    /// Work on a session that is not complete (`capturing`: killed, or `failed`), with a
    /// warning; its response never becomes the camera's profile.
    #[arg(long)]
    allow_incomplete: bool,
    /// Also write hdr/radiance_filled.exr: the radiance with no NaN (saturated samples hold
    /// their channel's brightest measured radiance, too-dark ones 0), for tone mappers that
    /// NaN poisons (OpenCV's Reinhard). radiance.exr keeps NaN where nothing was measured.
    #[arg(long)]
    fill: bool,
    /// Print the summary as JSON on stdout (progress stays on stderr).
    #[arg(long)]
    json: bool,
}

pub(crate) fn check_session(dir: &Path) -> Result<()> {
    if !dir.join("manifest.json").exists() {
        bail!(
            "{} has no manifest.json; give a session directory (from glint capture or glint import)",
            dir.display()
        );
    }
    Ok(())
}

/// What the HDR stage is doing, for a progress line.
/// Stage messages on stderr (a spinner on a terminal).
struct Stages {
    bar: Option<ProgressBar>,
    start: Instant,
}

impl Stages {
    fn new() -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let b = ProgressBar::new_spinner();
            b.set_style(ProgressStyle::with_template("{spinner} {elapsed} {msg}").expect("valid"));
            b.enable_steady_tick(std::time::Duration::from_millis(120));
            b
        });
        Stages {
            bar,
            start: Instant::now(),
        }
    }
    fn show(&self, e: HdrEvent) {
        let msg = e.to_string();
        match &self.bar {
            Some(b) => b.set_message(msg),
            None => eprintln!("[{:6.2} s] {msg}", self.start.elapsed().as_secs_f64()),
        }
    }
    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

pub fn cmd_import(a: ImportArgs) -> Result<ExitCode> {
    let out = a.out.unwrap_or_else(|| {
        let name = a
            .dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "photos".into());
        super::default_out(&format!("import-{name}"))
    });
    let rig = match &a.rig {
        Some(p) => Some(glint::rig::load(p).map_err(|e| anyhow::anyhow!("--rig: {e}"))?),
        None => None,
    };
    let opts = import::ImportOptions {
        times: a.times.clone(),
        rig,
        grid: a.grid.clone(),
        dark: a.dark.clone(),
    };
    let r = import::import(&a.dir, &opts, &out)?;
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let (f, l) = (&r.exposures_s[0], r.exposures_s.last().unwrap());
        println!(
            "Session {}: {} photos, {}x{} {}-bit, exposures {} s ({}) .. {} s ({}).",
            r.session.display(),
            r.frames,
            r.width,
            r.height,
            r.bit_depth,
            f.1,
            f.0,
            l.1,
            l.0
        );
        if r.grid + r.dark > 0 {
            println!("With {} grid and {} dark photo(s).", r.grid, r.dark);
        }
        match (&r.rig, r.grid) {
            (Some(_), g) if g > 0 => println!(
                "Process it with: glint hdr {0} && glint calibrate {0} && glint fit {0} && glint validate {0} && glint report {0}",
                r.session.display()
            ),
            (Some(_), _) => println!(
                "Merge it with: glint hdr {0}. It has no grid photo, so it cannot be calibrated or fitted (the camera's pose comes from a photo of the grid): import again with --grid PHOTO",
                r.session.display()
            ),
            (None, _) => println!(
                "Merge it with: glint hdr {0} (to calibrate and fit, import with --rig RIG --grid PHOTO)",
                r.session.display()
            ),
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn print_response(r: &Response) {
    println!(
        "Response: {} model, {}-bit{}",
        r.model.as_str(),
        r.bit_depth,
        r.choice.as_ref().map_or(String::new(), |c| format!(
            " (BIC {})",
            c.bic
                .iter()
                .map(|(m, b)| format!("{} {b:.0}", m.as_str()))
                .collect::<Vec<_>>()
                .join(", ")
        ))
    );
    for (c, ch) in r.channels.iter().enumerate() {
        println!(
            "  {}: valid values {}..{}, {} samples, rms residual {:.4}, noise: shot {:.3e}, read {:.3e}",
            r.channel_name(c),
            ch.valid_min,
            ch.valid_max,
            ch.samples,
            ch.rms_residual,
            ch.noise.shot,
            ch.noise.read
        );
    }
    for w in &r.warnings {
        println!("warning: {w}");
    }
}

pub fn cmd_response(a: ResponseArgs) -> Result<ExitCode> {
    check_session(&a.session)?;
    let opts = run::ResponseOptions {
        recover_options: a.recover.options()?,
        profile: a.profile.clone(),
        rig: a.rig.clone(),
        replace_profile: a.replace_profile,
        allow_incomplete: a.allow_incomplete,
    };
    let stages = Stages::new();
    let res = run::response(&a.session, &opts, &mut |e| stages.show(e));
    stages.finish();
    let (r, stored, warnings) = res?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if a.json {
        let (profile, written) = match &stored {
            run::ProfileStored::Written(p) => (Some(p), true),
            run::ProfileStored::Kept(p) | run::ProfileStored::Refused { path: p, .. } => {
                (Some(p), false)
            }
            run::ProfileStored::Nowhere => (None, false),
        };
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "response": r,
                "session_files": ["hdr/response.json", "hdr/response.csv", "hdr/response.svg"],
                "profile": profile,
                "profile_written": written,
                "profile_outcome": stored,
                "warnings": warnings,
            }))?
        );
    } else {
        print_response(&r);
        println!(
            "Wrote {}/hdr/response.{{json,csv,svg}}.",
            a.session.display()
        );
        match &stored {
            run::ProfileStored::Written(p) => {
                println!("Stored as the camera's profile: {}", p.display())
            }
            run::ProfileStored::Kept(p) => println!(
                "The camera profile {} exists and was kept; pass --replace-profile to replace it.",
                p.display()
            ),
            run::ProfileStored::Refused { path, why } => println!(
                "Not stored as the camera's profile {}: {why}.",
                path.display()
            ),
            run::ProfileStored::Nowhere => println!(
                "No camera profile stored: give --rig FILE (the rig file you capture with) or --profile FILE to store one."
            ),
        }
    }
    Ok(ExitCode::SUCCESS)
}

pub fn cmd_hdr(a: HdrArgs) -> Result<ExitCode> {
    check_session(&a.session)?;
    let opts = HdrOptions {
        response_file: a.response.clone(),
        recover: a.recover,
        recover_options: a.recover_args.options()?,
        profile: a.profile.clone(),
        rig: a.rig.clone(),
        allow_incomplete: a.allow_incomplete,
    };
    let stages = Stages::new();
    let res = run::run(&a.session, &opts, &mut |e| stages.show(e));
    stages.finish();
    let (mut s, _) = res?;
    if a.fill {
        let t = Instant::now();
        glint::hdr::files::write_filled(&a.session.join("hdr"))?;
        s.files.push("hdr/radiance_filled.exr".into());
        s.seconds += t.elapsed().as_secs_f64();
    }
    for n in &s.notes {
        eprintln!("note: {n}");
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
        for w in &s.warnings {
            eprintln!("warning: {w}");
        }
    } else {
        let src = match &s.response {
            run::ResponseSource::File(p) => format!("from {p}"),
            run::ResponseSource::Profile(p) => format!("camera profile {p}"),
            run::ResponseSource::Recovered => "recovered from this session".into(),
        };
        println!(
            "HDR of {}: {}x{}, {} exposures {}..{} µs, {} dark frames; response {} ({}).",
            s.session,
            s.width,
            s.height,
            s.exposures_us.len(),
            s.exposures_us[0],
            s.exposures_us.last().unwrap(),
            s.dark_frames,
            s.model,
            src
        );
        if let Some(p) = &s.profile_written {
            println!("Stored the response as the camera's profile: {p}");
        }
        let total = (s.samples_measured + s.samples_saturated + s.samples_too_dark) as f64;
        println!(
            "Radiance {:.4e}..{:.4e}; median relative sd {:.2}%; {:.2}% of samples saturated in every frame, {:.2}% too dark in every frame.",
            s.radiance_min,
            s.radiance_max,
            100.0 * s.median_relative_sd,
            100.0 * s.samples_saturated as f64 / total,
            100.0 * s.samples_too_dark as f64 / total
        );
        for w in &s.warnings {
            println!("warning: {w}");
        }
        println!("Wrote {} in {:.2} s.", s.files.join(", "), s.seconds);
    }
    Ok(ExitCode::SUCCESS)
}
