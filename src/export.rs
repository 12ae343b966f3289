//! `glint export`: a session's fitted model as a material other tools load: a plain JSON
//! record, a Mitsuba 3 `<bsdf>`, or a glTF 2.0 material.
//!
//! The paper's lobes (Phong, Blinn-Phong, the cosine lobe) have no exact counterpart in a
//! renderer's microfacet models, so the renderer's parameters are not derived by a rule of
//! thumb but FITTED: the Glint model's f_r · (n.l) is evaluated at every sample geometry of
//! `fit/samples.csv` (the angles the tile was actually measured at), and the target's
//! parameters (roughness, specular strength, diffuse reflectance) are chosen by weighted
//! least squares to minimise the relative error there. That error (rms over samples and
//! channels) is the conversion's error; it is written into the file and printed. Rules of
//! thumb (Walter et al. 2007: Blinn-Phong n ~ Beckmann alpha = sqrt(2 / (n + 2))) are
//! reported beside the fit, never used in its place.
//!
//! The targets' BRDFs are implemented here ([`brdf`]) after their definitions: Mitsuba 3's
//! `roughplastic` (src/bsdfs/roughplastic.cpp, include/mitsuba/render/microfacet.h at
//! commit b45b0a9) and glTF 2.0's metallic-roughness BRDF (the specification's appendix B)
//! with `KHR_materials_specular`'s Fresnel (its ratified `fresnel_mix`).
//!
//! fit.json is read and checked as every stage reads it ([`crate::fit::file`]), the
//! session's manifest as every stage opens it ([`crate::session::open`]).

use std::f64::consts::PI;
use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use crate::fit::model::{dot, sub, unit, Geometry, Model, Reflectance};

/// What went wrong, naming the file and what to do.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error("{0}")]
    Input(String),
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> ExportError {
    ExportError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

// ---------------------------------------------------------------------------------------
// fit.json, as every stage reads it (crate::fit::file)

use crate::fit::file::CandidateModel as _;
pub use crate::fit::file::{
    Absolute, CameraRefined, Candidate, Covariance, FitFile, Param, ReferenceFactor,
};

/// One sample of fit/samples.csv: its unit light and view vectors in the tile's frame
/// (normal +z), and the measured f_r (n.l) in fit.json's units (radiance times D^2) where
/// it was not censored.
#[derive(Debug, Clone, Copy)]
pub struct SampleDir {
    pub l: [f64; 3],
    pub v: [f64; 3],
    pub measured: [Option<f64>; 3],
}

/// A session's fit, ready to export.
#[derive(Debug, Clone)]
pub struct Loaded {
    pub session: PathBuf,
    pub fit: FitFile,
    /// Index into `fit.candidates` of the model exported.
    pub index: usize,
    pub model: Model,
    pub samples: Vec<SampleDir>,
    /// Warnings about the session (one that is not complete: `--allow-incomplete`).
    pub warnings: Vec<String>,
}

impl Loaded {
    pub fn candidate(&self) -> &Candidate {
        &self.fit.candidates[self.index]
    }
    pub fn absolute(&self) -> bool {
        self.fit.units.as_deref() == Some("absolute")
    }
}

pub fn model_named(name: &str) -> Option<Model> {
    Model::ALL.into_iter().find(|m| m.name() == name)
}

/// Read a session's fit/fit.json and fit/samples.csv and pick the model: `model` by name,
/// or the chosen one. The session must be complete.
pub fn load(dir: &Path, model: Option<&str>) -> Result<Loaded, ExportError> {
    load_allowing(dir, model, false)
}

/// [`load`], on a session that is not complete too if `allow_incomplete` (with a warning
/// in [`Loaded::warnings`]). The manifest is opened as every stage opens it (its state,
/// its frames' rules), fit.json read and checked against it as every stage reads it
/// ([`crate::fit::file::load`]).
pub fn load_allowing(
    dir: &Path,
    model: Option<&str>,
    allow_incomplete: bool,
) -> Result<Loaded, ExportError> {
    let manifest = crate::session::open(dir, allow_incomplete)
        .map_err(|e| ExportError::Input(e.to_string()))?;
    let warnings: Vec<String> = crate::session::incomplete_warning(&manifest)
        .into_iter()
        .collect();
    let path = dir.join("fit/fit.json");
    let fit = crate::fit::file::load(dir, &crate::fit::file::Facts::of(&manifest)).map_err(
        |e| match e {
            crate::fit::run::FitError::File { path, reason } => ExportError::File { path, reason },
            other => ExportError::Input(other.to_string()),
        },
    )?;
    let name = model.unwrap_or(&fit.chosen).to_string();
    let names: Vec<&str> = fit.candidates.iter().map(|c| c.model.as_str()).collect();
    let Some(index) = fit.candidates.iter().position(|c| c.model == name) else {
        let known = Model::ALL.map(|m| m.name()).join(", ");
        return Err(ExportError::Input(if model_named(&name).is_some() {
            format!(
                "{} was not fitted in {} (it has {}); give one of those to --model, or fit it (glint fit {} --model {name})",
                crate::fsx::quote(&name),
                path.display(),
                names.join(", "),
                dir.display()
            )
        } else {
            format!(
                "unknown model {}; give --model one of {known}",
                crate::fsx::quote(&name)
            )
        }));
    };
    // Every candidate's model is known once the file is checked.
    let m = fit.candidates[index].model().ok_or_else(|| {
        ExportError::Input(format!(
            "{} names model {}, which this Glint does not know; update Glint",
            path.display(),
            crate::fsx::quote(&name)
        ))
    })?;
    let samples = load_samples(dir, &manifest, &fit, fit.channels)?;
    Ok(Loaded {
        session: dir.to_path_buf(),
        fit,
        index,
        model: m,
        samples,
        warnings,
    })
}

/// The sample geometries: fit/samples.csv's tile points, with the lamp and tile height of
/// the session's rig and the camera the fit used (fit.json's refined camera where there is
/// one, else calib/camera.json's). Each row's recomputed n.l is checked against its
/// `cos_l`, so a calibration re-run after the fit is caught.
fn load_samples(
    dir: &Path,
    manifest: &crate::session::Manifest,
    fit: &FitFile,
    channels: usize,
) -> Result<Vec<SampleDir>, ExportError> {
    let rig = manifest.rig.as_ref().ok_or_else(|| {
        ExportError::Input(format!(
            "{}: the session has no rig (an imported session), so its lamp position, and with it the measured angles, are unknown",
            dir.display()
        ))
    })?;
    let lamp = rig.geometry.lamp_position_mm;
    let height = rig.geometry.tile_thickness_mm;
    let eye = match &fit.camera_refined {
        Some(c) => c.centre_mm,
        None => {
            let cam_file = crate::fsx::Within::new(dir, "calib/camera.json");
            let cam = cam_file.path();
            let (_, cal) = crate::calib::run::load_camera_file(&cam_file)
                .map_err(|e| ExportError::Input(e.to_string()))?;
            cal.views
                .first()
                .ok_or_else(|| file_err(&cam, "has no view (pose); re-run glint calibrate"))?
                .camera_centre
        }
    };
    let file = crate::fsx::Within::new(dir, "fit/samples.csv");
    let path = file.path();
    let text = file.read_text(crate::fsx::MAX_TEXT_BYTES).map_err(|e| {
        file_err(
            &path,
            format!("cannot read ({e}); re-run glint fit {}", dir.display()),
        )
    })?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = |name: &str| {
        header.iter().position(|h| *h == name).ok_or_else(|| {
            file_err(
                &path,
                format!("has no column `{name}`; re-run glint fit {}", dir.display()),
            )
        })
    };
    let names: &[&str] = if channels == 1 {
        &["y"]
    } else {
        &["r", "g", "b"]
    };
    let (cx, cy, ccos, cd) = (
        col("x_mm")?,
        col("y_mm")?,
        col("cos_l")?,
        col("lamp_distance_mm")?,
    );
    let mut crad = Vec::new();
    let mut ccens = Vec::new();
    for n in names {
        crad.push(col(&format!("radiance_{n}"))?);
        ccens.push(col(&format!("censored_{n}"))?);
    }
    let mut out = Vec::new();
    for (k, line) in lines.enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let row = k + 2;
        let cells: Vec<&str> = line.split(',').collect();
        let num = |i: usize| -> Result<f64, ExportError> {
            cells
                .get(i)
                .and_then(|s| s.trim().parse::<f64>().ok())
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    file_err(
                        &path,
                        format!(
                            "line {row}, column `{}`: not a finite number; re-run glint fit {}",
                            header.get(i).copied().unwrap_or("?"),
                            dir.display()
                        ),
                    )
                })
        };
        let p = [num(cx)?, num(cy)?, height];
        let l = unit(sub(lamp, p));
        let v = unit(sub(eye, p));
        if !(l[2] > 0.0 && v[2] > 0.0) {
            continue;
        }
        let cos_csv = num(ccos)?;
        if (l[2] - cos_csv).abs() > 2e-3 {
            return Err(file_err(
                &path,
                format!(
                    "line {row}: n.l is {:.4} at the session's lamp and tile, but the file says {cos_csv:.4}: the rig or calibration changed after the fit; re-run glint fit {}",
                    l[2],
                    dir.display()
                ),
            ));
        }
        let d = num(cd)?;
        let mut measured = [None; 3];
        for c in 0..names.len() {
            let rad = cells
                .get(crad[c])
                .and_then(|s| s.trim().parse::<f64>().ok());
            let censored = cells.get(ccens[c]).map(|s| s.trim()) == Some("1");
            measured[c] = rad
                .filter(|r| r.is_finite() && !censored)
                .map(|r| r * d * d);
        }
        out.push(SampleDir { l, v, measured });
    }
    if out.len() < 3 {
        return Err(file_err(
            &path,
            format!(
                "has {} usable samples, too few to convert the model over; re-run glint fit {}",
                out.len(),
                dir.display()
            ),
        ));
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------
// Units

/// The exported model's parameters in 1/sr (absolute, or scaled by the user's assumed
/// albedo), one entry per channel.
#[derive(Debug, Clone)]
pub struct Material {
    pub kd: Vec<f64>,
    pub ks: Vec<f64>,
    pub n: f64,
    /// Factor from fit.json's kd, ks (and samples.csv's radiance times D^2) to these, per
    /// channel.
    pub scale: Vec<f64>,
    /// How the scale was found, for the file.
    pub units_note: String,
    /// The assumed albedo, where the session is relative.
    pub assumed_albedo: Option<f64>,
}

/// The parameters in 1/sr: the candidate's absolute values where the session is absolute;
/// where it is relative, fit.json's values scaled so that the brightest channel's diffuse
/// albedo (pi kd) is `albedo` (the same factor for the whole BRDF, so ks/kd is kept).
/// Without `albedo` a relative session is refused: a renderer needs reflectances in [0, 1].
pub fn material(l: &Loaded, albedo: Option<f64>, target: &str) -> Result<Material, ExportError> {
    let c = l.candidate();
    let n = if l.model.has_lobe() {
        c.n.map_or(f64::NAN, |p| p.v())
    } else {
        0.0
    };
    let ks_rel: Vec<f64> = if l.model.has_lobe() {
        c.ks.iter().map(|p| p.v()).collect()
    } else {
        vec![0.0; c.kd.len()]
    };
    if l.absolute() {
        if albedo.is_some() {
            return Err(ExportError::Input(format!(
                "{} is in absolute units (a reference target); --albedo is only for relative sessions: drop it",
                l.session.display()
            )));
        }
        let a = c.absolute.as_ref().ok_or_else(|| {
            ExportError::Input(format!(
                "{}: units are absolute but model {} has no `absolute` block; re-run glint fit {}",
                l.session.join("fit/fit.json").display(),
                l.model.name(),
                l.session.display()
            ))
        })?;
        let kd: Vec<f64> = a.kd_per_sr.iter().map(|p| p.v()).collect();
        let ks: Vec<f64> = if !l.model.has_lobe() {
            vec![0.0; kd.len()]
        } else if a.ks_per_sr.len() == kd.len() {
            a.ks_per_sr.iter().map(|p| p.v()).collect()
        } else if a.f0.len() == kd.len() {
            a.f0.iter().map(|p| p.v()).collect()
        } else {
            return Err(ExportError::Input(format!(
                "{}: model {} has no absolute.ks_per_sr; re-run glint fit {}",
                l.session.join("fit/fit.json").display(),
                l.model.name(),
                l.session.display()
            )));
        };
        let scale = kd
            .iter()
            .zip(&c.kd)
            .zip(ks.iter().zip(&ks_rel))
            .map(|((a, r), (sa, sr))| {
                if r.v() > 0.0 {
                    a / r.v()
                } else if *sr > 0.0 {
                    sa / sr
                } else {
                    f64::NAN
                }
            })
            .collect();
        return Ok(Material {
            kd,
            ks,
            n,
            scale,
            units_note: "absolute: kd and ks in 1/sr from the session's reference target".into(),
            assumed_albedo: None,
        });
    }
    let Some(a) = albedo else {
        return Err(ExportError::Input(format!(
            "{} is in relative units (no reference target), and {target} needs reflectances in [0, 1]: give --albedo A, your assumed diffuse albedo of the brightest channel (e.g. --albedo 0.8), or use --to json",
            l.session.display()
        )));
    };
    if !(a.is_finite() && a > 0.0 && a <= 1.0) {
        return Err(ExportError::Input(format!(
            "--albedo {a}: must be in (0, 1]"
        )));
    }
    let kd_max = c.kd.iter().map(|p| p.v()).fold(0.0, f64::max);
    if kd_max <= 0.0 {
        return Err(ExportError::Input(format!(
            "model {} has kd = 0 in every channel, so --albedo cannot set its scale",
            l.model.name()
        )));
    }
    let s = a / (PI * kd_max);
    Ok(Material {
        kd: c.kd.iter().map(|p| s * p.v()).collect(),
        ks: ks_rel.iter().map(|k| s * k).collect(),
        n,
        scale: vec![s; c.kd.len()],
        units_note: format!(
            "relative session: scaled by the user's assumption (--albedo {a}) that the brightest channel's diffuse albedo pi kd is {a}; the whole BRDF is scaled by the same factor {s:.6e}, so ks/kd and n are as fitted"
        ),
        assumed_albedo: Some(a),
    })
}

// ---------------------------------------------------------------------------------------
// The source model at the samples

/// The Glint model's f_r (n.l) at each sample, per channel.
pub fn source_values(l: &Loaded, m: &Material) -> Vec<Vec<f64>> {
    l.samples
        .iter()
        .map(|s| {
            let g = Geometry::from_vectors(s.l, s.v, [0.0, 0.0, 1.0], 1.0);
            (0..m.kd.len())
                .map(|c| l.model.radiance(&g, m.kd[c], m.ks[c], m.n))
                .collect()
        })
        .collect()
}

/// How well a target reproduces the source over the samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Errors {
    /// rms over samples and channels of (target - glint model) / glint model, f_r (n.l).
    pub rms_relative: f64,
    /// The same against the measured radiance (times D^2, scaled like kd), over the
    /// samples not censored; None where there is none.
    pub rms_relative_measured: Option<f64>,
    pub samples: usize,
}

fn errors(l: &Loaded, m: &Material, source: &[Vec<f64>], target: &[Vec<f64>]) -> Errors {
    let (mut e, mut k, mut em, mut km) = (0.0, 0usize, 0.0, 0usize);
    for (i, (s, t)) in source.iter().zip(target).enumerate() {
        for c in 0..s.len() {
            if s[c] > 0.0 {
                e += ((t[c] - s[c]) / s[c]).powi(2);
                k += 1;
            }
            if let Some(meas) = l.samples[i].measured[c] {
                let meas = meas * m.scale[c];
                if meas > 0.0 && meas.is_finite() {
                    em += ((t[c] - meas) / meas).powi(2);
                    km += 1;
                }
            }
        }
    }
    Errors {
        rms_relative: if k > 0 { (e / k as f64).sqrt() } else { 0.0 },
        rms_relative_measured: (km > 0).then(|| (em / km as f64).sqrt()),
        samples: l.samples.len(),
    }
}

/// Walter et al. (2007)'s rule of thumb for the Beckmann alpha of a Blinn-Phong exponent,
/// with the usual equivalences for the other lobes (a Phong or cosine lobe in r.v with
/// exponent n is about a Blinn-Phong lobe of 4n).
pub fn walter_alpha(model: Model, n: f64) -> Option<f64> {
    let nb = match model {
        Model::Lambert => return None,
        Model::BlinnPhong => n,
        Model::Phong | Model::CosineLobe => 4.0 * n,
        // Fitted on the same scale: its own α.
        Model::Ggx => n,
    };
    Some((2.0 / (nb + 2.0)).sqrt())
}

// ---------------------------------------------------------------------------------------
// Least squares

/// The renderers' roughness α is searched over [ALPHA_MIN, ALPHA_MAX].
const ALPHA_MIN: f64 = 2e-3;
const ALPHA_MAX: f64 = 1.0;

/// A warning where the fitted α lies at an end of its search (within 2%): the renderer's
/// distribution could not follow the lobe's width, and the α written is a bound, not a fit.
fn alpha_bound_warning(alpha: f64, warnings: &mut Vec<String>) {
    if alpha <= ALPHA_MIN * 1.02 || alpha >= ALPHA_MAX / 1.02 {
        warnings.push(format!(
            "the roughness α = {alpha:.4} is at the end of its range ({ALPHA_MIN} to {ALPHA_MAX}): the renderer's distribution cannot match the lobe's width (see the conversion error)"
        ));
    }
}

/// Minimise `f` over ln alpha in [ln lo, ln hi]: a scan of 41 points, then golden-section
/// search around the best.
fn minimise_log(lo: f64, hi: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
    let (a, b) = (lo.ln(), hi.ln());
    let k = 40;
    let xs: Vec<f64> = (0..=k).map(|i| a + (b - a) * i as f64 / k as f64).collect();
    let vals: Vec<f64> = xs.iter().map(|x| f(x.exp())).collect();
    let best = (0..=k)
        .min_by(|&i, &j| vals[i].total_cmp(&vals[j]))
        .unwrap_or(0);
    let (mut x0, mut x1) = (xs[best.saturating_sub(1)], xs[(best + 1).min(k)]);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = x1 - g * (x1 - x0);
    let mut d = x0 + g * (x1 - x0);
    let (mut fc, mut fd) = (f(c.exp()), f(d.exp()));
    for _ in 0..40 {
        if fc < fd {
            x1 = d;
            d = c;
            fd = fc;
            c = x1 - g * (x1 - x0);
            fc = f(c.exp());
        } else {
            x0 = c;
            c = d;
            fc = fd;
            d = x0 + g * (x1 - x0);
            fd = f(d.exp());
        }
    }
    let x = if fc < fd { c } else { d };
    if f(x.exp()) <= vals[best] {
        x.exp()
    } else {
        xs[best].exp()
    }
}

// ---------------------------------------------------------------------------------------
// Mitsuba 3

/// Mitsuba's parameters fitted to the model.
#[derive(Debug, Clone)]
pub struct MitsubaFit {
    /// `diffuse` (Lambert) or `roughplastic`.
    pub plugin: &'static str,
    pub distribution: brdf::Distribution,
    pub alpha: f64,
    pub int_ior: f64,
    pub ext_ior: f64,
    pub diffuse_reflectance: Vec<f64>,
    pub specular_reflectance: Vec<f64>,
    pub errors: Errors,
    /// The other distribution's error, for the record.
    pub other: Option<(brdf::Distribution, f64, Errors)>,
    pub warnings: Vec<String>,
}

/// The roughplastic's interface: polypropylene-like, as Mitsuba's default (1.49); 1.5 here.
pub const INT_IOR: f64 = 1.5;

/// Fit Mitsuba's `diffuse` (a Lambert model: exact) or `roughplastic` (a lobe) to the model
/// over the samples.
pub fn fit_mitsuba(l: &Loaded, m: &Material) -> MitsubaFit {
    let src = source_values(l, m);
    let nc = m.kd.len();
    let mut warnings = Vec::new();
    if !l.model.has_lobe() {
        let refl: Vec<f64> = m.kd.iter().map(|k| PI * k).collect();
        let clamped = clamp_reflectance(&refl, "diffuse reflectance", &mut warnings);
        let tgt: Vec<Vec<f64>> = l
            .samples
            .iter()
            .map(|s| clamped.iter().map(|r| r / PI * s.l[2]).collect())
            .collect();
        return MitsubaFit {
            plugin: "diffuse",
            distribution: brdf::Distribution::Beckmann,
            alpha: 0.0,
            int_ior: INT_IOR,
            ext_ior: 1.0,
            diffuse_reflectance: clamped,
            specular_reflectance: vec![0.0; nc],
            errors: errors(l, m, &src, &tgt),
            other: None,
            warnings,
        };
    }
    let fits: Vec<_> = [brdf::Distribution::Beckmann, brdf::Distribution::Ggx]
        .into_iter()
        .map(|d| fit_roughplastic(l, m, &src, d))
        .collect();
    let (best, other) = if fits[0].3.rms_relative <= fits[1].3.rms_relative {
        (&fits[0], &fits[1])
    } else {
        (&fits[1], &fits[0])
    };
    let (dist, alpha, (diff, spec), errs) = best.clone();
    alpha_bound_warning(alpha, &mut warnings);
    if diff.iter().any(|d| *d >= 1.0 - 1e-9) {
        warnings.push("the diffuse reflectance reached 1 in a channel (the fit wanted more): the assumed albedo is too high".into());
    }
    MitsubaFit {
        plugin: "roughplastic",
        distribution: dist,
        alpha,
        int_ior: INT_IOR,
        ext_ior: 1.0,
        diffuse_reflectance: diff,
        specular_reflectance: spec,
        errors: errs,
        other: Some((other.0, other.1, other.3)),
        warnings,
    }
}

type RoughFit = (brdf::Distribution, f64, (Vec<f64>, Vec<f64>), Errors);

fn fit_roughplastic(l: &Loaded, m: &Material, src: &[Vec<f64>], d: brdf::Distribution) -> RoughFit {
    let nc = m.kd.len();
    // For a given alpha, f (n.l) = diffuse_c K + specular_c S: linear per channel.
    let bases = |alpha: f64| {
        let rp = brdf::RoughPlastic::new(d, alpha, INT_IOR);
        l.samples
            .iter()
            .map(|s| rp.bases(s.l, s.v))
            .collect::<Vec<(f64, f64)>>()
    };
    // The diffuse is converted to the model's diffuse kd (n.l) and the lobe to its lobe,
    // each weighted as the total's relative error: near the highlight a wide microfacet
    // tail and a Lambert term are nearly indistinguishable, and a joint fit traded one for
    // the other (diffuse_reflectance 0 in blue, specular 2.3 on the mock tile).
    let solve = |ab: &[(f64, f64)]| -> (Vec<f64>, Vec<f64>, f64) {
        let ka: Vec<f64> = ab.iter().map(|x| x.0).collect();
        let sb: Vec<f64> = ab.iter().map(|x| x.1).collect();
        let (mut diff, mut spec, mut cost) = (Vec::new(), Vec::new(), 0.0);
        for c in 0..nc {
            let (y, w, yd, ys) = split(l, m, src, c);
            let a = ls1(&ka, &yd, &w, 1.0);
            let b = ls1(&sb, &ys, &w, f64::INFINITY);
            cost += (0..y.len())
                .map(|i| w[i] * (a * ka[i] + b * sb[i] - y[i]).powi(2))
                .sum::<f64>();
            diff.push(a);
            spec.push(b);
        }
        (diff, spec, cost)
    };
    let alpha = minimise_log(ALPHA_MIN, ALPHA_MAX, |a| solve(&bases(a)).2);
    let ab = bases(alpha);
    let (diff, spec, _) = solve(&ab);
    let tgt: Vec<Vec<f64>> = ab
        .iter()
        .map(|(k, s)| (0..nc).map(|c| diff[c] * k + spec[c] * s).collect())
        .collect();
    let errs = errors(l, m, src, &tgt);
    (d, alpha, (diff, spec), errs)
}

/// Channel `c` of the source: its f_r (n.l), the weights of relative error, its diffuse
/// part kd (n.l) and its lobe (the rest).
type Split = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);
fn split(l: &Loaded, m: &Material, src: &[Vec<f64>], c: usize) -> Split {
    let y: Vec<f64> = src.iter().map(|v| v[c]).collect();
    let w = y
        .iter()
        .map(|v| if *v > 0.0 { 1.0 / (v * v) } else { 0.0 })
        .collect();
    let yd: Vec<f64> = l.samples.iter().map(|s| m.kd[c] * s.l[2]).collect();
    let ys = y.iter().zip(&yd).map(|(y, d)| y - d).collect();
    (y, w, yd, ys)
}

/// Minimise sum w (x a - y)^2 over x in [0, hi].
fn ls1(a: &[f64], y: &[f64], w: &[f64], hi: f64) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..y.len() {
        num += w[i] * a[i] * y[i];
        den += w[i] * a[i] * a[i];
    }
    if den > 0.0 {
        (num / den).clamp(0.0, hi)
    } else {
        0.0
    }
}

fn clamp_reflectance(r: &[f64], what: &str, warnings: &mut Vec<String>) -> Vec<f64> {
    if r.iter().any(|x| *x > 1.0) {
        warnings.push(format!(
            "the {what} is above 1 in a channel ({}); clamped to 1",
            r.iter()
                .map(|x| format!("{x:.4}"))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    r.iter().map(|x| x.clamp(0.0, 1.0)).collect()
}

fn fmt_list(v: &[f64]) -> String {
    let v: Vec<f64> = if v.len() == 1 {
        vec![v[0]; 3]
    } else {
        v.to_vec()
    };
    v.iter()
        .map(|x| format!("{x:.6}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn pct(x: f64) -> String {
    format!("{:.2}%", 100.0 * x)
}

/// One line on the conversion, for stderr.
pub fn describe_errors(e: &Errors) -> String {
    let mut s = format!(
        "rms relative error of f_r (n.l) against the glint model over {} measured angles: {}",
        e.samples,
        pct(e.rms_relative)
    );
    if let Some(m) = e.rms_relative_measured {
        s.push_str(&format!(" (against the measured radiance: {})", pct(m)));
    }
    s
}

/// The Mitsuba 3 `<bsdf>` (an XML fragment, comments first).
pub fn mitsuba_xml(l: &Loaded, m: &Material, f: &MitsubaFit) -> String {
    let c = l.candidate();
    let mut out = String::new();
    // "--" may not appear in an XML comment.
    let comment = |s: &str| {
        format!(
            "<!-- {} -->\n",
            s.replace("--albedo", "the albedo option")
                .replace("--", "- -")
        )
    };
    out.push_str(&comment(&format!(
        "glint export: model {} of session {} (fit.json created {})",
        l.model.name(),
        l.session.display(),
        l.fit.created
    )));
    out.push_str(&comment(&format!("units: {}", m.units_note)));
    if let Some(a) = m.assumed_albedo {
        out.push_str(&comment(&format!(
            "ASSUMPTION: diffuse albedo of the brightest channel = {a}, given to glint export; the session itself is relative"
        )));
    }
    out.push_str(&comment(&format!(
        "glint model: {}; kd = [{}] 1/sr, ks = [{}] 1/sr, n = {}",
        formula(l.model),
        fmt_list(&m.kd),
        fmt_list(&m.ks),
        c.n.map_or("-".into(), |p| format!("{:.4}", p.v()))
    )));
    if f.plugin == "diffuse" {
        out.push_str(&comment(
            "conversion: Lambert f_r = kd is Mitsuba's diffuse with reflectance = pi kd (exact)",
        ));
    } else {
        out.push_str(&comment(&format!(
            "conversion: roughplastic fitted by least squares to the glint model's f_r (n.l) at the {} measured sample angles (fit/samples.csv); {}",
            f.errors.samples,
            describe_errors(&f.errors)
        )));
        if let Some((d, a, e)) = &f.other {
            out.push_str(&comment(&format!(
                "the {} distribution fitted worse: alpha {:.5}, rms relative error {}",
                d.name(),
                a,
                pct(e.rms_relative)
            )));
        }
        if let Some(w) = walter_alpha(l.model, m.n) {
            out.push_str(&comment(&format!(
                "for comparison, Walter et al. 2007's rule of thumb gives Beckmann alpha = sqrt(2 / (n + 2)) = {w:.5}; the fitted alpha is {:.5}",
                f.alpha
            )));
        }
        out.push_str(&comment(
            "specular_reflectance scales the microfacet lobe (1 is Mitsuba's physical default); it carries the fitted specular strength",
        ));
        if f.specular_reflectance.iter().any(|s| *s > 1.0) {
            out.push_str(&comment(&format!(
                "specular_reflectance above 1: the tile's lobe is stronger than a plastic of int_ior {} reflects (F0 {:.3})",
                f.int_ior,
                brdf::fresnel(1.0, f.int_ior / f.ext_ior).0
            )));
        }
    }
    for w in &f.warnings {
        out.push_str(&comment(&format!("WARNING: {w}")));
    }
    if f.plugin == "diffuse" {
        out.push_str(&format!(
            "<bsdf type=\"diffuse\" id=\"glint-{}\">\n    <rgb name=\"reflectance\" value=\"{}\"/>\n</bsdf>\n",
            l.model.name(),
            fmt_list(&f.diffuse_reflectance)
        ));
    } else {
        out.push_str(&format!(
            "<bsdf type=\"roughplastic\" id=\"glint-{}\">\n    <string name=\"distribution\" value=\"{}\"/>\n    <float name=\"alpha\" value=\"{:.6}\"/>\n    <float name=\"int_ior\" value=\"{}\"/>\n    <float name=\"ext_ior\" value=\"{}\"/>\n    <rgb name=\"diffuse_reflectance\" value=\"{}\"/>\n    <rgb name=\"specular_reflectance\" value=\"{}\"/>\n    <boolean name=\"nonlinear\" value=\"false\"/>\n</bsdf>\n",
            l.model.name(),
            f.distribution.name(),
            f.alpha,
            f.int_ior,
            f.ext_ior,
            fmt_list(&f.diffuse_reflectance),
            fmt_list(&f.specular_reflectance)
        ));
    }
    out
}

// ---------------------------------------------------------------------------------------
// glTF 2.0

#[derive(Debug, Clone)]
pub struct GltfFit {
    pub base_color: Vec<f64>,
    /// GGX alpha; roughnessFactor = sqrt(alpha).
    pub alpha: f64,
    pub roughness: f64,
    /// KHR_materials_specular.
    pub specular_factor: f64,
    pub specular_color: Vec<f64>,
    pub errors: Errors,
    pub warnings: Vec<String>,
}

/// Fit glTF's metallic-roughness material (metallic 0) with KHR_materials_specular to the
/// model over the samples.
pub fn fit_gltf(l: &Loaded, m: &Material) -> GltfFit {
    let src = source_values(l, m);
    let nc = m.kd.len();
    let mut warnings = Vec::new();
    if !l.model.has_lobe() {
        let base = clamp_reflectance(
            &m.kd.iter().map(|k| PI * k).collect::<Vec<_>>(),
            "base colour (diffuse albedo)",
            &mut warnings,
        );
        let tgt: Vec<Vec<f64>> = l
            .samples
            .iter()
            .map(|s| {
                let p = brdf::GltfParams {
                    base: base.clone(),
                    alpha: 1.0,
                    specular: 0.0,
                    specular_color: vec![1.0; nc],
                };
                p.eval_cos(s.l, s.v)
            })
            .collect();
        return GltfFit {
            base_color: base,
            alpha: 1.0,
            roughness: 1.0,
            specular_factor: 0.0,
            specular_color: vec![1.0; nc],
            errors: errors(l, m, &src, &tgt),
            warnings,
        };
    }
    // For given alpha and specularFactor w, with f0_c = 0.04 specularColor_c (below 1) and
    // S = (1 - |v.h|)^5:
    //   f (n.l) = base_c/pi (1 - w max_c fr_c) (n.l) + w fr_c V D (n.l),  fr = f0 + (1 - f0) S,
    // linear in base_c and g_c = w f0_c once max_c fr_c is fixed: solved by a few rounds of
    // fixing it at the last solution's largest f0. As for Mitsuba, the diffuse is fitted to
    // the model's diffuse and the lobe to its lobe (see fit_roughplastic).
    let solve = |alpha: f64, w: f64| -> (Vec<f64>, Vec<f64>, f64) {
        let geo: Vec<(f64, f64, f64)> = l
            .samples
            .iter()
            .map(|s| {
                let h = unit([s.l[0] + s.v[0], s.l[1] + s.v[1], s.l[2] + s.v[2]]);
                let sch = (1.0 - dot(s.v, h).abs()).powi(5);
                let vd = brdf::gltf_vd(s.l, s.v, alpha);
                (s.l[2], sch, vd)
            })
            .collect();
        let mut f0max = 0.04;
        let (mut base, mut f0, mut cost) = (vec![0.0; nc], vec![0.0; nc], 0.0);
        for _ in 0..12 {
            let aa: Vec<f64> = geo
                .iter()
                .map(|(cl, s, _)| cl / PI * (1.0 - w * (f0max + (1.0 - f0max) * s)))
                .collect();
            let bb: Vec<f64> = geo.iter().map(|(cl, s, vd)| (1.0 - s) * vd * cl).collect();
            let cc: Vec<f64> = geo.iter().map(|(cl, s, vd)| w * s * vd * cl).collect();
            cost = 0.0;
            for c in 0..nc {
                let (y, wt, yd, ys) = split(l, m, &src, c);
                let a = ls1(&aa, &yd, &wt, 1.0);
                let ys2: Vec<f64> = ys.iter().zip(&cc).map(|(y, c)| y - c).collect();
                let g = ls1(&bb, &ys2, &wt, w);
                cost += (0..y.len())
                    .map(|i| wt[i] * (a * aa[i] + g * bb[i] + cc[i] - y[i]).powi(2))
                    .sum::<f64>();
                base[c] = a;
                f0[c] = if w > 0.0 { g / w } else { 0.0 };
            }
            let next = f0.iter().copied().fold(0.0, f64::max);
            if (next - f0max).abs() < 1e-9 {
                break;
            }
            f0max = next;
        }
        (base, f0, cost)
    };
    let ws = [1.0, 0.8, 0.6, 0.4, 0.2, 0.1, 0.05];
    let mut best: Option<(f64, f64, f64)> = None;
    for w in ws {
        let alpha = minimise_log(ALPHA_MIN, ALPHA_MAX, |a| solve(a, w).2);
        let cost = solve(alpha, w).2;
        if best.is_none_or(|b| cost < b.2 * (1.0 - 1e-6)) {
            best = Some((alpha, w, cost));
        }
    }
    let (alpha, w, _) = best.unwrap_or((1.0, 1.0, 0.0));
    let (base, f0, _) = solve(alpha, w);
    alpha_bound_warning(alpha, &mut warnings);
    let specular_color: Vec<f64> = f0.iter().map(|f| f / 0.04).collect();
    let p = brdf::GltfParams {
        base: base.clone(),
        alpha,
        specular: w,
        specular_color: specular_color.clone(),
    };
    let tgt: Vec<Vec<f64>> = l.samples.iter().map(|s| p.eval_cos(s.l, s.v)).collect();
    if base.iter().any(|b| *b >= 1.0 - 1e-9) {
        warnings.push("the base colour reached 1 in a channel (the fit wanted more): the assumed albedo is too high".into());
    }
    if f0.iter().any(|f| *f >= 1.0 - 1e-9) {
        warnings.push(
            "F0 reached 1 in a channel: the lobe is stronger than a dielectric can be".into(),
        );
    }
    GltfFit {
        base_color: base,
        alpha,
        roughness: alpha.sqrt(),
        specular_factor: w,
        specular_color,
        errors: errors(l, m, &src, &tgt),
        warnings,
    }
}

fn rgb3(v: &[f64]) -> Vec<f64> {
    if v.len() == 1 {
        vec![v[0]; 3]
    } else {
        v.to_vec()
    }
}

fn round6(x: f64) -> f64 {
    (x * 1e6).round() / 1e6
}

/// A glTF 2.0 file (JSON) with the material on a 100 mm square quad (the tile, in metres),
/// its geometry in one embedded buffer.
pub fn gltf_json(l: &Loaded, m: &Material, f: &GltfFit) -> Value {
    let mut base: Vec<f64> = rgb3(&f.base_color).into_iter().map(round6).collect();
    base.push(1.0);
    let sc: Vec<f64> = rgb3(&f.specular_color).into_iter().map(round6).collect();
    let default_specular =
        (f.specular_factor - 1.0).abs() < 1e-6 && sc.iter().all(|s| (s - 1.0).abs() < 1e-3);
    let mut material = json!({
        "name": format!("glint-{}", l.model.name()),
        "pbrMetallicRoughness": {
            "baseColorFactor": base,
            "metallicFactor": 0.0,
            "roughnessFactor": round6(f.roughness.clamp(0.0, 1.0)),
        },
        "doubleSided": false,
    });
    let mut used: Vec<&str> = Vec::new();
    if !default_specular {
        material["extensions"] = json!({
            "KHR_materials_specular": {
                "specularFactor": round6(f.specular_factor),
                "specularColorFactor": sc,
            }
        });
        used.push("KHR_materials_specular");
    }
    // The quad: positions, normals (f32) and indices (u16), little-endian.
    let h = 0.05f32;
    let pos: [[f32; 3]; 4] = [[-h, 0.0, h], [h, 0.0, h], [h, 0.0, -h], [-h, 0.0, -h]];
    let mut buf: Vec<u8> = Vec::new();
    for p in pos {
        for x in p {
            buf.extend_from_slice(&x.to_le_bytes());
        }
    }
    for _ in 0..4 {
        for x in [0f32, 1.0, 0.0] {
            buf.extend_from_slice(&x.to_le_bytes());
        }
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        buf.extend_from_slice(&i.to_le_bytes());
    }
    let extras = json!({
        "glint": {
            "session": l.session.display().to_string(),
            "model": l.model.name(),
            "formula": formula(l.model),
            "units": m.units_note,
            "assumed_albedo": m.assumed_albedo,
            "kd_per_sr": m.kd,
            "ks_per_sr": m.ks,
            "n": if l.model.has_lobe() { json!(m.n) } else { Value::Null },
            "conversion": {
                "method": if l.model.has_lobe() {
                    "least squares fit of baseColorFactor, roughness (GGX alpha = roughnessFactor^2), specularFactor and specularColorFactor to the glint model's f_r (n.l) at the measured sample angles (fit/samples.csv), glTF 2.0 appendix B BRDF with KHR_materials_specular"
                } else {
                    "Lambert: baseColorFactor = pi kd, specularFactor 0, roughness 1 (exact)"
                },
                "ggx_alpha": f.alpha,
                "rms_relative_error": f.errors.rms_relative,
                "rms_relative_error_measured": f.errors.rms_relative_measured,
                "samples": f.errors.samples,
                "warnings": f.warnings,
            }
        }
    });
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": format!("glint export {}", crate::VERSION) },
        "scene": 0,
        "scenes": [{ "name": "glint tile", "nodes": [0] }],
        "nodes": [{ "name": "tile", "mesh": 0 }],
        "meshes": [{
            "name": "tile",
            "primitives": [{
                "attributes": { "POSITION": 0, "NORMAL": 1 },
                "indices": 2,
                "material": 0,
                "mode": 4
            }]
        }],
        "materials": [material],
        "buffers": [{
            "byteLength": buf.len(),
            "uri": format!("data:application/octet-stream;base64,{}", base64(&buf)),
        }],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": 48, "target": 34962 },
            { "buffer": 0, "byteOffset": 48, "byteLength": 48, "target": 34962 },
            { "buffer": 0, "byteOffset": 96, "byteLength": 12, "target": 34963 }
        ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
              "min": [-h, 0.0, -h], "max": [h, 0.0, h] },
            { "bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3" },
            { "bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR" }
        ],
        "extras": extras,
    });
    if !used.is_empty() {
        doc["extensionsUsed"] = json!(used);
    }
    doc
}

fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for ch in bytes.chunks(3) {
        let b = [ch[0], *ch.get(1).unwrap_or(&0), *ch.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= ch.len() {
                out.push(T[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// JSON

/// docs/design.md's f_r of a model, as text.
pub fn formula(m: Model) -> &'static str {
    match m {
        Model::Lambert => "f_r = kd",
        Model::Phong => "f_r = kd + ks (r.v)^n / (n.l)",
        Model::BlinnPhong => "f_r = kd + ks (n.h)^n / (n.l)",
        Model::CosineLobe => "f_r = kd + ks (n+2)/(2 pi) (r.v)^n",
        Model::Ggx => "f_r = kd + ks D(h) G1(l) G1(v) F~(v.h) / (4 (n.l) (n.v)); D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2), G1(x) = 2 (n.x) / ((n.x) + sqrt(a^2 + (1 - a^2) (n.x)^2)), F~ = 1 + (1/0.04 - 1) (1 - v.h)^5, a = sqrt(2 / (n + 2)); ks is F0",
    }
}

fn params(p: &[Param]) -> Value {
    json!(p
        .iter()
        .map(|p| json!({ "value": p.value, "sd": p.sd, "ci95": p.ci95 }))
        .collect::<Vec<_>>())
}

/// A candidate's covariance for the JSON record, in the record's units: as fit.json has it
/// (relative kd and ks, ln n), or with `reference` in 1/sr (F0 for ggx's ks): kd and ks
/// divided by the channel's factor F, and the factor's own relative uncertainty added as
/// one common to every channel (its certificate's share dominates it), p_i p_j (sd_F/F)^2
/// for the absolute values p. None where fit.json has no usable covariance.
fn covariance_record(c: &Candidate, reference: Option<&ReferenceFactor>) -> Option<Value> {
    let cov = c.covariance.as_ref()?;
    let k = cov.parameters.len();
    if k == 0 || k > 7 || cov.matrix.len() != k || cov.matrix.iter().any(|r| r.len() != k) {
        return None;
    }
    // Per parameter: its channel (kd_*, ks_*), or None (ln_n).
    let channel_of = |name: &str| -> Option<usize> {
        let (kind, ch) = name.split_once('_')?;
        if kind != "kd" && kind != "ks" {
            return None;
        }
        match ch {
            "y" => Some(0),
            _ => ["r", "g", "b"].iter().position(|c| *c == ch),
        }
    };
    let mut matrix: Vec<Vec<Option<f64>>> = cov.matrix.clone();
    let mut units = "kd and ks in the fit's relative units (as fit.json), ln n";
    if let Some(r) = reference {
        let mut scale = vec![1.0; k];
        let mut abs = vec![0.0; k];
        let mut rel = vec![0.0; k];
        for (i, name) in cov.parameters.iter().enumerate() {
            if let Some(ch) = channel_of(name) {
                let f = r.factor.get(ch.min(r.factor.len().saturating_sub(1)))?;
                let (fv, fsd) = (f.value?, f.sd.unwrap_or(0.0));
                if !(fv.is_finite() && fv > 0.0) {
                    return None;
                }
                let list = if name.starts_with("kd") { &c.kd } else { &c.ks };
                let ch_in = ch.min(list.len().saturating_sub(1));
                let p = list.get(ch_in).and_then(|p| p.value).unwrap_or(0.0);
                scale[i] = 1.0 / fv;
                abs[i] = p / fv;
                rel[i] = fsd / fv;
            }
        }
        for i in 0..k {
            for j in 0..k {
                matrix[i][j] = matrix[i][j]
                    .map(|x| x * scale[i] * scale[j] + abs[i] * abs[j] * rel[i] * rel[j]);
            }
        }
        units = "kd and ks in 1/sr (ggx: ks is F0), with the reference factor's uncertainty, ln n";
    }
    Some(json!({
        "parameters": cov.parameters,
        "matrix": matrix,
        "units": units,
    }))
}

/// The plain JSON record: the model, its formula, every parameter per channel with its sd
/// and 95% interval, the covariance where fit.json has one, the units and the session.
pub fn json_record(l: &Loaded) -> Value {
    let c = l.candidate();
    let lobe = l.model.has_lobe();
    let absolute = l.absolute() && c.absolute.is_some();
    let channels = if l.fit.channels == 1 {
        json!(["y"])
    } else {
        json!(["r", "g", "b"])
    };
    let mut v = json!({
        "format": "glint-material",
        "format_version": 1,
        "model": l.model.name(),
        "formula": formula(l.model),
        "conventions": "l to the lamp, v to the camera, n the normal, r = 2(n.l)n - l, h = (l+v)/|l+v|; dot products clamped at 0; radiance L = f_r (I / D^2) max(0, n.l) (docs/design.md, after Schirmacher et al. 1999)",
        "session": l.session.display().to_string(),
        "fit_file": l.session.join("fit/fit.json").display().to_string(),
        "fit_created": l.fit.created,
        "chosen_in_fit": l.fit.chosen == l.model.name(),
        "channels": channels,
        "units": if absolute { "absolute" } else { "relative" },
        "units_note": if absolute {
            "kd and ks in 1/sr (absolute, from the session's reference target); albedo = pi kd; n dimensionless"
        } else {
            "RELATIVE: kd and ks carry the lamp's and camera's unknown common scale (not 1/sr, not reflectances); only ks/kd and n are physical; n dimensionless"
        },
    });
    if absolute {
        let a = c.absolute.as_ref().expect("checked above");
        v["kd"] = params(&a.kd_per_sr);
        v["albedo"] = if a.albedo.is_empty() {
            json!(a
                .kd_per_sr
                .iter()
                .map(|p| json!({
                    "value": p.value.map(|x| PI * x),
                    "sd": p.sd.map(|x| PI * x),
                    "ci95": p.ci95.map(|x| x.map(|x| PI * x))
                }))
                .collect::<Vec<_>>())
        } else {
            params(&a.albedo)
        };
        if lobe {
            v["ks"] = params(&a.ks_per_sr);
        }
        v["relative"] =
            json!({ "kd": params(&c.kd), "ks": if lobe { params(&c.ks) } else { Value::Null } });
    } else {
        v["kd"] = params(&c.kd);
        if lobe {
            v["ks"] = params(&c.ks);
        }
    }
    if lobe {
        v["n"] = params(&c.n.into_iter().collect::<Vec<_>>())[0].clone();
        v["ks_over_kd"] = params(&c.ks_over_kd);
        v["ks_n_correlation"] = json!(c.ks_n_correlation);
    } else {
        v["ks"] = Value::Null;
        v["n"] = Value::Null;
    }
    let factor = l.fit.reference.as_ref().filter(|_| absolute);
    match covariance_record(c, factor) {
        Some(cov) if absolute == factor.is_some() => {
            v["covariance"] = cov;
        }
        Some(_) => {
            v["covariance"] = Value::Null;
            v["covariance_note"] = json!(
                "fit.json's covariance is in its relative units and it gives no reference factor to put it in 1/sr, so none is given: only each parameter's sd and 95% interval"
            );
        }
        None => {
            v["covariance"] = Value::Null;
            v["covariance_note"] = json!(
                "fit.json has no covariance of this model's parameters, so none is given: only each parameter's sd and 95% interval (and the correlation of ks and n where fitted)"
            );
        }
    }
    v
}

// ---------------------------------------------------------------------------------------

/// The targets' BRDFs, written from their definitions (Mitsuba 3's roughplastic and
/// microfacet.h; glTF 2.0 appendix B with KHR_materials_specular). Vectors are in the
/// surface frame (normal +z), l towards the light, v towards the viewer.
pub mod brdf {
    use std::f64::consts::PI;

    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub enum Distribution {
        Beckmann,
        Ggx,
    }

    impl Distribution {
        pub fn name(&self) -> &'static str {
            match self {
                Distribution::Beckmann => "beckmann",
                Distribution::Ggx => "ggx",
            }
        }

        /// The normal distribution D(m) (isotropic alpha), per unit solid angle of m;
        /// integral D(m) cos(theta_m) d omega = 1.
        pub fn d(&self, alpha: f64, m: [f64; 3]) -> f64 {
            let c2 = m[2] * m[2];
            if m[2] <= 0.0 {
                return 0.0;
            }
            let a2 = alpha * alpha;
            let r = match self {
                Distribution::Beckmann => {
                    let t2 = (m[0] * m[0] + m[1] * m[1]) / c2;
                    (-t2 / a2).exp() / (PI * a2 * c2 * c2)
                }
                Distribution::Ggx => {
                    let q = (m[0] * m[0] + m[1] * m[1]) / a2 + c2;
                    1.0 / (PI * a2 * q * q)
                }
            };
            if r * m[2] > 1e-20 {
                r
            } else {
                0.0
            }
        }

        /// Smith's G1 of direction `v` for microfacet `m`, as Mitsuba computes it (its
        /// rational approximation for Beckmann).
        pub fn g1(&self, alpha: f64, v: [f64; 3], m: [f64; 3]) -> f64 {
            let xy = alpha * alpha * (v[0] * v[0] + v[1] * v[1]);
            let mut r = if xy == 0.0 {
                1.0
            } else {
                let t = xy / (v[2] * v[2]);
                match self {
                    Distribution::Beckmann => {
                        let a = 1.0 / t.sqrt();
                        if a >= 1.6 {
                            1.0
                        } else {
                            (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
                        }
                    }
                    Distribution::Ggx => 2.0 / (1.0 + (1.0 + t).sqrt()),
                }
            };
            if super::dot(v, m) * v[2] <= 0.0 {
                r = 0.0;
            }
            r
        }
    }

    /// Unpolarised Fresnel reflectance of a dielectric interface (eta = interior /
    /// exterior index) for incidence cosine `cos_i` (negative: from inside), and the
    /// cosine of the transmitted direction (0 under total internal reflection).
    pub fn fresnel(cos_i: f64, eta: f64) -> (f64, f64) {
        let (ci, eta) = if cos_i >= 0.0 {
            (cos_i, eta)
        } else {
            (-cos_i, 1.0 / eta)
        };
        let s2 = (1.0 - ci * ci) / (eta * eta);
        if s2 >= 1.0 {
            return (1.0, 0.0);
        }
        let ct = (1.0 - s2).sqrt();
        let rs = (ci - eta * ct) / (ci + eta * ct);
        let rp = (eta * ci - ct) / (eta * ci + ct);
        (0.5 * (rs * rs + rp * rp), ct)
    }

    /// Integrate `f(m)` over the hemisphere of microfacet normals (d omega_m): midpoint
    /// rule in phi and in u, where tan(theta_m) = alpha u / (1 - u) (dense where a
    /// distribution of that alpha is).
    pub fn integrate_m(
        alpha: f64,
        nu: usize,
        nphi: usize,
        mut f: impl FnMut([f64; 3]) -> f64,
    ) -> f64 {
        let mut sum = 0.0;
        for i in 0..nu {
            let u = (i as f64 + 0.5) / nu as f64;
            let t = alpha * u / (1.0 - u);
            let theta = t.atan();
            let dtheta = (alpha / ((1.0 - u) * (1.0 - u))) / (1.0 + t * t) / nu as f64;
            let (st, ct) = theta.sin_cos();
            for j in 0..nphi {
                let phi = 2.0 * PI * (j as f64 + 0.5) / nphi as f64;
                let m = [st * phi.cos(), st * phi.sin(), ct];
                sum += f(m) * st * dtheta * (2.0 * PI / nphi as f64);
            }
        }
        sum
    }

    const TABLE: usize = 64;

    /// Mitsuba 3's roughplastic at one alpha and eta: the specular microfacet lobe
    /// F D G / (4 cos_i cos_o), and the diffuse term
    /// rho t(cos_i) t(cos_o) / (pi eta^2 (1 - R_int)) (nonlinear = false), with the rough
    /// interface's transmittance t tabulated at 64 cosines and R_int its internal
    /// reflectance, computed as Mitsuba does (by quadrature here instead of its visible
    /// normal samples).
    pub struct RoughPlastic {
        pub distribution: Distribution,
        pub alpha: f64,
        pub eta: f64,
        pub transmittance: Vec<f64>,
        pub internal_reflectance: f64,
    }

    impl RoughPlastic {
        pub fn new(distribution: Distribution, alpha: f64, eta: f64) -> Self {
            let mus: Vec<f64> = (0..TABLE)
                .map(|i| (i as f64 / (TABLE - 1) as f64).max(1e-6))
                .collect();
            let d = distribution;
            // The expected value over visible normals of G1(out, m) (1 - F) (transmitted)
            // or G1(out, m) F (reflected), as in Mitsuba's eval_transmittance and
            // eval_reflectance.
            let through = |mu: f64, eta: f64, reflect: bool| {
                let wi = [(1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu];
                integrate_m(alpha, 48, 32, |m| {
                    let im = super::dot(wi, m);
                    if im <= 0.0 {
                        return 0.0;
                    }
                    let vis = d.g1(alpha, wi, m) * im * d.d(alpha, m) / mu;
                    let (f, ct) = fresnel(im, eta);
                    if reflect {
                        let wo = [
                            2.0 * im * m[0] - wi[0],
                            2.0 * im * m[1] - wi[1],
                            2.0 * im * m[2] - wi[2],
                        ];
                        if wo[2] <= 0.0 {
                            return 0.0;
                        }
                        vis * f * d.g1(alpha, wo, m)
                    } else {
                        if f >= 1.0 {
                            return 0.0;
                        }
                        let e = 1.0 / eta;
                        let wt = [
                            m[0] * (im * e - ct) - wi[0] * e,
                            m[1] * (im * e - ct) - wi[1] * e,
                            m[2] * (im * e - ct) - wi[2] * e,
                        ];
                        if wt[2] >= 0.0 {
                            return 0.0;
                        }
                        vis * (1.0 - f) * d.g1(alpha, wt, m)
                    }
                })
            };
            let transmittance = mus.iter().map(|&mu| through(mu, eta, false)).collect();
            let internal_reflectance = 2.0
                * mus
                    .iter()
                    .map(|&mu| through(mu, 1.0 / eta, true) * mu)
                    .sum::<f64>()
                / TABLE as f64;
            RoughPlastic {
                distribution,
                alpha,
                eta,
                transmittance,
                internal_reflectance,
            }
        }

        /// The transmittance at cosine `x`, interpolated as Mitsuba's lerp_gather.
        pub fn t(&self, x: f64) -> f64 {
            let x = x.clamp(0.0, 1.0) * (TABLE - 1) as f64;
            let i = (x as usize).min(TABLE - 2);
            let f = x - i as f64;
            self.transmittance[i] * (1.0 - f) + self.transmittance[i + 1] * f
        }

        /// f_r (n.l) = rho K + s S with diffuse_reflectance rho and specular_reflectance s:
        /// returns (K, S).
        pub fn bases(&self, l: [f64; 3], v: [f64; 3]) -> (f64, f64) {
            if l[2] <= 0.0 || v[2] <= 0.0 {
                return (0.0, 0.0);
            }
            let h = super::unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
            let d = self.distribution;
            let f = fresnel(super::dot(l, h), self.eta).0;
            let spec = f * d.d(self.alpha, h) * d.g1(self.alpha, l, h) * d.g1(self.alpha, v, h)
                / (4.0 * v[2]);
            let diff = self.t(l[2]) * self.t(v[2]) * l[2]
                / (PI * self.eta * self.eta * (1.0 - self.internal_reflectance));
            (diff, spec)
        }
    }

    /// glTF 2.0 appendix B's V D for alpha (= roughness^2): the GGX D and the separable
    /// Smith visibility V = G1(l) G1(v) / (4 |n.l| |n.v|).
    pub fn gltf_vd(l: [f64; 3], v: [f64; 3], alpha: f64) -> f64 {
        if l[2] <= 0.0 || v[2] <= 0.0 {
            return 0.0;
        }
        let h = super::unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
        let a2 = alpha * alpha;
        let nh = h[2];
        if nh <= 0.0 {
            return 0.0;
        }
        let q = nh * nh * (a2 - 1.0) + 1.0;
        let d = a2 / (PI * q * q);
        let g1 = |c: f64| 2.0 * c / (c + (a2 + (1.0 - a2) * c * c).sqrt());
        d * g1(l[2]) * g1(v[2]) / (4.0 * l[2] * v[2])
    }

    /// A glTF material with metallic 0: baseColorFactor, alpha = roughnessFactor^2, and
    /// KHR_materials_specular's specularFactor and specularColorFactor.
    #[derive(Debug, Clone)]
    pub struct GltfParams {
        pub base: Vec<f64>,
        pub alpha: f64,
        pub specular: f64,
        pub specular_color: Vec<f64>,
    }

    impl GltfParams {
        /// f_r (n.l) per channel: KHR_materials_specular's fresnel_mix of the diffuse
        /// base/pi and the microfacet V D.
        pub fn eval_cos(&self, l: [f64; 3], v: [f64; 3]) -> Vec<f64> {
            if l[2] <= 0.0 || v[2] <= 0.0 {
                return vec![0.0; self.base.len()];
            }
            let h = super::unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
            let s = (1.0 - super::dot(v, h).abs()).powi(5);
            let fr: Vec<f64> = self
                .specular_color
                .iter()
                .map(|c| {
                    let f0 = (0.04 * c).min(1.0);
                    f0 + (1.0 - f0) * s
                })
                .collect();
            let fmax = fr.iter().copied().fold(0.0, f64::max);
            let vd = gltf_vd(l, v, self.alpha);
            self.base
                .iter()
                .zip(&fr)
                .map(|(b, f)| {
                    ((1.0 - self.specular * fmax) * b / PI + self.specular * f * vd) * l[2]
                })
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::brdf::*;
    use super::*;

    #[test]
    fn microfacet_distributions_integrate_to_one_over_the_hemisphere() {
        for d in [Distribution::Beckmann, Distribution::Ggx] {
            for alpha in [0.02, 0.1, 0.3, 0.7, 1.0] {
                // A plain grid in theta and phi, not the substitution the code uses.
                let (nt, np) = (4000, 8);
                let mut s = 0.0;
                for i in 0..nt {
                    let th = (i as f64 + 0.5) / nt as f64 * PI / 2.0;
                    for j in 0..np {
                        let ph = (j as f64 + 0.5) / np as f64 * 2.0 * PI;
                        let m = [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()];
                        s += d.d(alpha, m) * th.cos() * th.sin();
                    }
                }
                s *= (PI / 2.0 / nt as f64) * (2.0 * PI / np as f64);
                let q = integrate_m(alpha, 200, 8, |m| d.d(alpha, m) * m[2]);
                println!(
                    "{} alpha {alpha}: grid {s:.6}, substitution {q:.6}",
                    d.name()
                );
                // GGX's tail beyond 89.98 degrees is lost by neither rule; 1e-3 at alpha 1.
                assert!((s - 1.0).abs() < 2e-3, "{} {alpha} {s}", d.name());
                assert!((q - 1.0).abs() < 2e-3, "{} {alpha} {q}", d.name());
            }
        }
    }

    #[test]
    fn fresnel_limits() {
        let (r0, _) = fresnel(1.0, 1.5);
        assert!((r0 - 0.04).abs() < 1e-12);
        assert!((fresnel(1e-9, 1.5).0 - 1.0).abs() < 1e-6);
        // Total internal reflection inside glass beyond asin(1/1.5).
        assert_eq!(fresnel(0.5, 1.0 / 1.5).0, 1.0);
        assert_eq!(fresnel(-0.5, 1.5).0, 1.0);
    }

    #[test]
    fn beckmann_g1_approximation_is_close_to_the_exact_smith() {
        // Exact Beckmann Lambda = (erf(a) - 1)/2 + exp(-a^2)/(2 a sqrt(pi)); G1 = 1/(1+L).
        let erf = |x: f64| {
            // Abramowitz and Stegun 7.1.26 (|error| < 1.5e-7).
            let t = 1.0 / (1.0 + 0.3275911 * x);
            1.0 - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t
                + 0.254829592)
                * t
                * (-x * x).exp()
        };
        for a in [0.2, 0.5, 1.0, 1.5] {
            let lam = (erf(a) - 1.0) / 2.0 + (-a * a).exp() / (2.0 * a * PI.sqrt());
            let exact = 1.0 / (1.0 + lam);
            // v with 1 / (alpha tan theta) = a.
            let alpha = 0.3;
            let tan = 1.0 / (alpha * a);
            let v = unit([tan, 0.0, 1.0]);
            let g = Distribution::Beckmann.g1(alpha, v, [0.0, 0.0, 1.0]);
            assert!((g / exact - 1.0).abs() < 0.0035, "{a}: {g} {exact}");
        }
    }

    #[test]
    fn roughplastic_specular_albedo_and_transmittance_are_physical() {
        for d in [Distribution::Beckmann, Distribution::Ggx] {
            for alpha in [0.05, 0.2, 0.5] {
                let rp = RoughPlastic::new(d, alpha, 1.5);
                // Normal incidence: t about 1 - 0.04 (a little less: shadowing).
                let t1 = rp.t(1.0);
                assert!(t1 > 0.9 && t1 <= 0.961, "{t1}");
                assert!(rp.transmittance.iter().all(|t| (0.0..=1.0).contains(t)));
                // Smooth glass from inside: 0.60; a rough interface loses some to shadowing.
                println!(
                    "{} alpha {alpha}: R_int {:.4}",
                    d.name(),
                    rp.internal_reflectance
                );
                assert!(rp.internal_reflectance > 0.2 && rp.internal_reflectance < 0.61);
                // Directional albedo of the specular lobe plus the interface's
                // transmittance stays below 1 (energy), and is near it for small alpha.
                let v = unit([0.5, 0.0, 1.0]);
                let mut spec = 0.0;
                let (nt, np) = (600, 120);
                for i in 0..nt {
                    let th = (i as f64 + 0.5) / nt as f64 * PI / 2.0;
                    for j in 0..np {
                        let ph = (j as f64 + 0.5) / np as f64 * 2.0 * PI;
                        let l = [th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()];
                        spec += rp.bases(l, v).1 * th.sin();
                    }
                }
                spec *= (PI / 2.0 / nt as f64) * (2.0 * PI / np as f64);
                let total = spec + rp.t(v[2]);
                println!(
                    "{} alpha {alpha}: specular albedo {spec:.4}, t {:.4}, R_int {:.4}",
                    d.name(),
                    rp.t(v[2]),
                    rp.internal_reflectance
                );
                assert!(total <= 1.01 && total > 0.85, "{total}");
            }
        }
    }

    #[test]
    fn gltf_with_no_specular_is_lambert_and_its_vd_is_reciprocal() {
        let p = GltfParams {
            base: vec![0.5, 0.25, 0.1],
            alpha: 1.0,
            specular: 0.0,
            specular_color: vec![1.0; 3],
        };
        let l = unit([0.3, 0.2, 1.0]);
        let v = unit([-0.5, 0.1, 1.0]);
        let f = p.eval_cos(l, v);
        assert!((f[0] - 0.5 / PI * l[2]).abs() < 1e-15);
        assert!((gltf_vd(l, v, 0.2) - gltf_vd(v, l, 0.2)).abs() < 1e-12);
        // GGX D at the normal: 1 / (pi alpha^2).
        let a: f64 = 0.3;
        let vd = gltf_vd([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], a);
        assert!((vd - 1.0 / (PI * a * a) / 4.0).abs() < 1e-9);
    }

    #[test]
    fn bounded_least_squares() {
        let a = [1.0, 2.0, 3.0];
        let y = [2.0, 4.0, 6.0];
        let w = [1.0; 3];
        assert_eq!(ls1(&a, &y, &w, 10.0), 2.0);
        assert_eq!(ls1(&a, &y, &w, 1.5), 1.5);
        assert_eq!(ls1(&a, &[-1.0; 3], &w, 1.5), 0.0);
    }

    #[test]
    fn base64_matches_rfc_4648() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
    }

    #[test]
    fn an_alpha_at_its_search_bound_is_warned_of() {
        for (a, warned) in [
            (ALPHA_MIN, true),
            (0.2, false),
            (ALPHA_MAX, true),
            (0.9, false),
        ] {
            let mut w = Vec::new();
            alpha_bound_warning(a, &mut w);
            assert_eq!(!w.is_empty(), warned, "α {a}: {w:?}");
        }
        // The search itself stops at the bound for a cost falling beyond it.
        assert!((minimise_log(ALPHA_MIN, ALPHA_MAX, |a| -a) / ALPHA_MAX - 1.0).abs() < 1e-9);
    }
}
