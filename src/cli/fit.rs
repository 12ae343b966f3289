//! `glint fit`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use glint::fit::model::{Model, Reflectance};
use glint::fit::run::{self, Candidate, FitOptions, FitReport};
use glint::fit::sample::{Saturated, Strategy};
use glint::fit::solve::Options;

#[derive(Clone, Copy, ValueEnum)]
enum ModelArg {
    /// Every model below; the simplest that explains the tile is chosen.
    All,
    Lambert,
    Phong,
    BlinnPhong,
    CosineLobe,
    /// Cook-Torrance with the GGX distribution (roughness α = sqrt(2 / (n + 2)); ks is
    /// F0, absolute with a reference standard).
    Ggx,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum StrategyArg {
    /// Two lines through the highlight, along and across the plane of incidence, half the
    /// samples each (along alone cannot tell Phong from Blinn-Phong).
    Cross,
    /// A line through the highlight along the plane of incidence (the paper's way).
    Line,
    /// A line through the highlight across the plane of incidence.
    Perpendicular,
    /// A regular grid over a square around the highlight.
    Rect,
    /// Uniformly random tile pixels (--seed).
    Random,
}

impl StrategyArg {
    pub(crate) fn strategy(self) -> Strategy {
        match self {
            StrategyArg::Cross => Strategy::Cross,
            StrategyArg::Line => Strategy::Line,
            StrategyArg::Perpendicular => Strategy::Perpendicular,
            StrategyArg::Rect => Strategy::Rect,
            StrategyArg::Random => Strategy::Random,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum SaturatedArg {
    /// Leave saturated pixels out, with a blooming margin around them.
    Exclude,
    /// Keep them as censored samples: the model must reach the saturation level there.
    Censor,
    /// Keep them as if measured at the saturation level (biased; for comparison).
    Clip,
}

#[derive(Clone, Copy, ValueEnum)]
enum MosaicArg {
    /// Read it from the radiance's noise (a demosaicked channel is its neighbours'
    /// average, and smoother than a measured one).
    Auto,
    /// Every channel of every pixel is a measurement (three-chip or Foveon cameras).
    Off,
    Rggb,
    Grbg,
    Gbrg,
    Bggr,
}

#[derive(Args)]
pub struct FitArgs {
    /// A session with hdr/ (glint hdr) and calib/ (glint calibrate); writes
    /// SESSION/fit/samples.csv and fit.json.
    #[arg(value_name = "SESSION")]
    session: PathBuf,
    /// The model to fit, or all of them (the default): every candidate is reported and
    /// the simplest whose error on held-out samples is within the noise of the best is
    /// chosen.
    #[arg(long, value_enum, default_value = "all")]
    model: ModelArg,
    /// Samples asked for (a line gives at most one per pixel it crosses) [default: 400 per
    /// 640 pixels of the image's longer side, at least 400: 800 at 1280x960, so the samples
    /// lie as densely along the lines at every image size].
    #[arg(long, value_name = "N")]
    samples: Option<usize>,
    /// Where the samples lie.
    #[arg(long, value_enum, default_value = "cross")]
    strategy: StrategyArg,
    /// A line of your own, in pixel coordinates (overrides --strategy).
    #[arg(long, value_name = "U0,V0,U1,V1", allow_hyphen_values = true)]
    line: Option<String>,
    /// What becomes of pixels saturated in every exposure.
    #[arg(long, value_enum, default_value = "exclude")]
    saturated: SaturatedArg,
    /// Pixels left out around saturated ones (blooming).
    #[arg(long, default_value_t = 2, value_name = "PX")]
    bloom_margin: usize,
    /// The colour filter layout of a demosaicked camera, named by the 2x2 cell's top row
    /// then bottom row from the image's top-left pixel: each sample then keeps only the
    /// channel its photosite measured (the other two are interpolated from the
    /// neighbours, which smooths a sharp highlight and counts their noise again).
    #[arg(long, value_enum, default_value = "auto")]
    mosaic: MosaicArg,
    /// One ks for all channels (white highlights, as on dielectrics).
    #[arg(long)]
    grey_ks: bool,
    /// Huber loss with this threshold in standard deviations (for tiles with flaws).
    #[arg(long, value_name = "K")]
    huber: Option<f64>,
    /// Seed of --strategy random (and of the draws below).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Draws of the camera (from the calibration's covariance) and of the response curve
    /// (from its covariance) whose refits widen every interval by the calibration's and the
    /// HDR stage's uncertainty; 0 gives the fit's own uncertainty only.
    #[arg(long, default_value_t = 40, value_name = "N")]
    draws: usize,
    /// Work on a session that is not complete (`capturing`: killed, or `failed`), with a
    /// warning.
    #[arg(long)]
    allow_incomplete: bool,
    /// Keep the calibrated camera where the grid photo leaves the pose weak. By default
    /// the camera is then refined with the highlight and everything fitted again there,
    /// the intervals carrying the camera's uncertainty the highlight leaves (widened where
    /// the highlight and the grid photo disagree; fit.json's camera_refined says where it
    /// moved and the tension; needs --draws above 0).
    #[arg(long)]
    keep_camera: bool,
    /// Print fit.json on stdout.
    #[arg(long)]
    json: bool,
}

fn parse_line(s: &str) -> Result<[f64; 4]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .context("--line must be four numbers: u0,v0,u1,v1 (pixels)")?;
    if v.len() != 4 || v.iter().any(|x| !x.is_finite()) {
        bail!("--line must be four numbers: u0,v0,u1,v1 (pixels)");
    }
    Ok([v[0], v[1], v[2], v[3]])
}

pub fn cmd_fit(a: FitArgs) -> Result<ExitCode> {
    let mut o = FitOptions {
        models: models_of(a.model),
        ..FitOptions::default()
    };
    if let Some(p) = a
        .samples
        .and_then(|k| glint::fit::sample::count_problem(k, None))
    {
        bail!("--samples {p}");
    }
    o.sample.count = a.samples;
    o.sample.strategy = match &a.line {
        Some(l) => Strategy::UserLine(parse_line(l)?),
        None => a.strategy.strategy(),
    };
    o.sample.saturated = match a.saturated {
        SaturatedArg::Exclude => Saturated::Exclude,
        SaturatedArg::Censor => Saturated::Censor,
        SaturatedArg::Clip => Saturated::Clip,
    };
    o.sample.bloom_margin_px = a.bloom_margin;
    o.sample.mosaic = {
        use glint::fit::mosaic::{Mosaic, MosaicChoice};
        match a.mosaic {
            MosaicArg::Auto => MosaicChoice::Auto,
            MosaicArg::Off => MosaicChoice::Off,
            MosaicArg::Rggb => MosaicChoice::Given(Mosaic::Rggb),
            MosaicArg::Grbg => MosaicChoice::Given(Mosaic::Grbg),
            MosaicArg::Gbrg => MosaicChoice::Given(Mosaic::Gbrg),
            MosaicArg::Bggr => MosaicChoice::Given(Mosaic::Bggr),
        }
    };
    o.sample.seed = a.seed;
    o.draws = a.draws;
    o.allow_incomplete = a.allow_incomplete;
    o.refine_weak_pose = !a.keep_camera;
    if let Some(k) = a.huber {
        if !(k.is_finite() && k > 0.0) {
            bail!("--huber must be a positive number of standard deviations (got {k})");
        }
    }
    o.solver = Options {
        grey_ks: a.grey_ks,
        huber: a.huber,
        ..Options::default()
    };
    eprintln!("fitting {} ...", a.session.display());
    let report = run::run(&a.session, &o)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ExitCode::SUCCESS)
}

/// The channels' values (R G B, or a monochrome camera's one), each formatted by `f`.
fn rgb(p: &[glint::fit::run::Param], f: impl Fn(f64) -> String) -> String {
    p.iter().map(|x| f(x.value)).collect::<Vec<_>>().join(" ")
}

fn fmt_sig(x: f64) -> String {
    if !x.is_finite() {
        return "-".into();
    }
    let mag = x.abs().log10().floor();
    let d = (3.0 - mag).clamp(0.0, 9.0) as usize;
    format!("{x:.d$}")
}

/// n with its 95% interval, or "-" for Lambert; marked `~` where ks and n trade off.
fn n_cell(c: &Candidate) -> String {
    if !c.model.has_lobe() {
        return "-".into();
    }
    format!(
        "{}{} [{}, {}]",
        if c.trade_off.is_some() { "~" } else { "" },
        fmt_sig(c.n.value),
        fmt_sig(c.n.ci95[0]),
        fmt_sig(c.n.ci95[1])
    )
}

fn print_candidate(c: &Candidate, chosen: bool) {
    let lobe = c.model.has_lobe();
    let scale = c.kd.iter().map(|p| p.value).fold(0.0f64, f64::max);
    let rel = |p: &[glint::fit::run::Param]| rgb(p, |x| format!("{:.3}", x / scale.max(1e-300)));
    // Green's ratio, or a monochrome camera's one.
    let g = if c.ks_over_kd.len() == 1 { 0 } else { 1 };
    println!(
        "{} {:<12} {:>17} {:>17} {:>25} {:>17} {:>10} {:>12} {:>10}",
        if chosen { "*" } else { " " },
        c.model.name(),
        rel(&c.kd),
        if lobe { rel(&c.ks) } else { "-".into() },
        n_cell(c),
        if lobe {
            let r = &c.ks_over_kd[g];
            if r.value.is_finite() && r.sd.is_finite() {
                format!("{:.3}±{:.3}", r.value, r.sd)
            } else if r.value.is_finite() {
                // Its interval open above (kd reaches 0 within n's profile): the estimate
                // and the interval's lower end, not an infinite sd.
                format!("{:.3} (>= {})", r.value, fmt_sig(r.ci95[0]))
            } else {
                // kd at 0: the ratio is open above; its lower 95% end (Fieller).
                format!(">= {}", fmt_sig(r.ci95[0]))
            }
        } else {
            "-".into()
        },
        format!("{:.3}", c.reduced_chi2),
        format!("{:.1}", c.bic),
        format!("{:.3}{}", c.held_out, if c.explains { " " } else { "!" }),
    );
}

fn print_report(r: &FitReport) {
    let s = &r.sampling.sampled;
    let h = &s.highlight;
    println!(
        "samples: {} ({} asked for, {}), {} for fitting and {} held out; tile {} px",
        s.used,
        s.requested,
        s.strategy.name(),
        r.sampling.fitting_half,
        r.sampling.held_out_half,
        s.tile_pixels
    );
    if let Some(m) = s.mosaic {
        println!(
            "camera: demosaicked, colour filters {} ({}): each sample keeps its photosite's own channel",
            m.name(),
            match s.mosaic_detection {
                Some(d) => format!("read from the radiance's noise, contrast {:.1}", d.contrast),
                None => "as given".into(),
            }
        );
    }
    println!(
        "highlight: centre ({:.1}, {:.1}) px, mirror point predicted at ({:.1}, {:.1}) px{}",
        h.centre_px[0],
        h.centre_px[1],
        h.predicted_px[0],
        h.predicted_px[1],
        if h.saturated_pixels > 0 {
            format!(", {} tile pixels saturated", h.saturated_pixels)
        } else {
            String::new()
        }
    );
    if r.mono {
        println!(
            "kd and ks relative to kd (mono: one channel); n with its 95% interval; ks/kd with its standard error"
        );
    } else {
        println!(
            "kd and ks relative to the largest kd (RGB); n with its 95% interval; ks/kd of green with its standard error"
        );
    }
    println!(
        "  {:<12} {:>17} {:>17} {:>25} {:>17} {:>10} {:>12} {:>10}",
        "model",
        "kd",
        "ks",
        "n [95%]",
        if r.mono { "ks/kd (y)" } else { "ks/kd (g)" },
        "chi2/dof",
        "BIC",
        "held-out"
    );
    for c in &r.candidates {
        print_candidate(c, c.model == r.chosen);
    }
    println!(
        "chosen: {} (the simplest whose held-out error is within {:.3} of the best)",
        r.chosen.name(),
        r.choice_tolerance
    );
    println!("{}", r.verdict.line(&r.candidates));
    if r.candidates.iter().any(|c| !c.explains) {
        println!(
            "  ! held-out residuals more than {} times the noise: that model does not explain the tile",
            glint::fit::run::EXPLAINS_HELD_OUT_RMS
        );
    }
    for c in r.candidates.iter().filter(|c| c.trade_off.is_some()) {
        println!(
            "  ~ {}: {}",
            c.model.name(),
            c.trade_off.as_deref().unwrap_or_default()
        );
    }
    let chosen = r.candidates.iter().find(|c| c.model == r.chosen);
    match (&r.reference, chosen.and_then(|c| c.absolute.as_ref())) {
        (Some(f), Some(a)) => {
            let pm = |p: &[glint::fit::run::Param]| {
                p.iter()
                    .map(|x| format!("{:.4} ± {:.4}", x.value, x.sd))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            println!(
                "absolute (reference standard, {} pixels, factor ± {:.2}%): albedo {}{}",
                f.pixels,
                100.0 * f.factor_relative_sd.iter().map(|s| s.total).fold(0.0, f64::max),
                pm(&a.albedo),
                if !a.f0.is_empty() {
                    format!("; F0 {}", pm(&a.f0))
                } else if a.ks_per_sr.is_empty() {
                    String::new()
                } else {
                    format!("; ks {} 1/sr", pm(&a.ks_per_sr))
                }
            );
        }
        _ => println!(
            "units: relative (the rig has no [reference] standard, so kd and ks carry the lamp's and camera's unknown factor; n and ks/kd are absolute)"
        ),
    }
    println!("wrote {}/fit/samples.csv and fit.json", r.session);
}

#[derive(Args)]
pub struct FitPhotometricArgs {
    /// A photometric data set in DiLiGenT's layout: images/NNN.png (16-bit), line NNN of
    /// light_directions.txt and light_intensities.txt for each, mask.png and the normals in
    /// Normal_gt.mat.
    #[arg(value_name = "DIR")]
    dir: PathBuf,
    /// The model to fit, or all of them (the default).
    #[arg(long, value_enum, default_value = "all")]
    model: ModelArg,
    /// Use every STRIDE-th masked pixel each way (1: all of them).
    #[arg(long, default_value_t = 2)]
    stride: usize,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// Also write the report (JSON) to this file, created new: an existing file (or a
    /// link) there is never replaced or followed.
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
}

fn models_of(m: ModelArg) -> Vec<Model> {
    match m {
        ModelArg::All => Model::ALL.to_vec(),
        ModelArg::Lambert => vec![Model::Lambert],
        ModelArg::Phong => vec![Model::Phong],
        ModelArg::BlinnPhong => vec![Model::BlinnPhong],
        ModelArg::CosineLobe => vec![Model::CosineLobe],
        ModelArg::Ggx => vec![Model::Ggx],
    }
}

pub fn cmd_fit_photometric(a: FitPhotometricArgs) -> Result<ExitCode> {
    if a.stride == 0 {
        bail!("--stride must be at least 1");
    }
    if let Some(o) = &a.out {
        // symlink_metadata: a link there (even one to nothing) is something that exists.
        if std::fs::symlink_metadata(o).is_ok() {
            bail!(
                "{} exists; give another --out (Glint never replaces a file it did not write)",
                o.display()
            );
        }
    }
    eprintln!("reading {} ...", a.dir.display());
    let set = glint::fit::photometric::load(&a.dir)?;
    eprintln!(
        "{} photos of {}x{} ({} masked pixels); fitting on alternate photos, predicting the others ...",
        set.photos.len(),
        set.width,
        set.height,
        set.mask.iter().filter(|m| **m).count()
    );
    let r = glint::fit::photometric::fit_set(&set, &models_of(a.model), a.stride);
    let json = serde_json::to_string_pretty(&r)?;
    if let Some(o) = &a.out {
        // Created new (never replacing, never following a link): something that appeared
        // at --out during the fit is left alone.
        glint::fsx::create_new(o, json.as_bytes()).map_err(|e| {
            if e.kind() == std::io::ErrorKind::AlreadyExists {
                anyhow::anyhow!(
                    "{} appeared while fitting; give another --out (Glint never replaces a file it did not write)",
                    o.display()
                )
            } else {
                anyhow::anyhow!("cannot write {} ({e})", o.display())
            }
        })?;
    }
    if a.json {
        println!("{json}");
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{} samples from {} photos for fitting, {} from {} held out ({} left out near saturation)",
        r.fit_samples,
        r.fit_photos.len(),
        r.held_out_samples,
        r.held_out_photos.len(),
        r.left_out_saturated
    );
    println!(
        "  {:<12} {:>20} {:>20} {:>24} {:>12} {:>14}",
        "model", "kd (RGB)", "ks (RGB)", "n [95%]", "error (fit)", "error (held out)"
    );
    for pc in &r.candidates {
        let c = &pc.candidate;
        let lobe = c.model.has_lobe();
        let trip = |p: &[glint::fit::run::Param]| rgb(p, fmt_sig);
        println!(
            "{} {:<12} {:>20} {:>20} {:>24} {:>11.2}% {:>15.2}%",
            if c.model == r.chosen { "*" } else { " " },
            c.model.name(),
            trip(&c.kd),
            if lobe { trip(&c.ks) } else { "-".into() },
            n_cell(c),
            100.0 * pc.relative_error_fit,
            100.0 * pc.relative_error_held_out
        );
    }
    println!(
        "chosen: {} (errors: sqrt(sum (predicted - measured)^2 / sum measured^2) over every value)",
        r.chosen.name()
    );
    Ok(ExitCode::SUCCESS)
}
