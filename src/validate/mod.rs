//! Validation (paper section 4): render the scene with every fitted model, map the radiance
//! back to pixel values with the camera's response, and compare with the photographs.
//!
//! `glint validate SESSION` (after `glint fit`) writes `validation/`:
//! - `validation.json`: per model, the pixel-value figures per exposure and pooled (RMSE
//!   beside the noise's own RMSE, PSNR, SSIM) and the HDR-space figures (relative radiance
//!   error, mean squared standardised residual); see [`compare`];
//! - `compare.png`: the photograph beside the render of each model at one exposure (the
//!   paper's figures 4 to 7);
//! - `difference.png`: per model, the relative radiance difference over the tile;
//! - `profile.svg`: the radiance along the line through the highlight in the plane of
//!   incidence, measured against each model, and the chosen model fitted to this line with
//!   the saturated pixels clipped (the paper's way) against unsaturated ones only (figure 3).

pub mod figures;
pub mod loaded;

pub use loaded::Loaded;

// Rendering and comparison on plain data live in `glint-numerics`.
pub use glint_numerics::validate::{compare, render};

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::fit::file::CandidateModel as _;
use crate::fit::model::{Model, Reflectance};
use crate::fit::run::{load_inputs_allowing, FitError};
use crate::hdr::merge::dark_levels;
use crate::hdr::HdrError;
use crate::session::{self, SessionError};
use compare::{pixel_metrics, radiance_metrics, PixelMetrics, RadianceMetrics, Region};
use render::{Board, Shading, View};

pub use glint_format::stage::validation::{FORMAT, FORMAT_VERSION};
use glint_format::stage::{finite, validation as file};

#[derive(Debug, thiserror::Error)]
pub enum ValidateError {
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Hdr(#[from] HdrError),
    #[error(transparent)]
    Figure(#[from] figures::FigureError),
    #[error("{0}")]
    Input(String),
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> ValidateError {
    ValidateError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Progress of the stage.
#[derive(Debug, Clone)]
pub enum ValidateEvent {
    Loading,
    Tracing { pixels: usize },
    Rendering { model: Model },
    Figures,
}

impl std::fmt::Display for ValidateEvent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ValidateEvent::Loading => {
                f.write_str("reading the radiance, the calibration and the frames")
            }
            ValidateEvent::Tracing { pixels } => write!(
                f,
                "tracing {:.1} MP through the calibrated camera",
                *pixels as f64 * 1e-6
            ),
            ValidateEvent::Rendering { model } => write!(f, "rendering {}", model.name()),
            ValidateEvent::Figures => f.write_str("drawing the figures"),
        }
    }
}

/// Options of `glint validate`.
#[derive(Debug, Clone, Default)]
pub struct ValidateOptions {
    /// The exposure shown in the figures (µs); by default the one that shows the most of
    /// the tile unsaturated.
    pub exposure_us: Option<f64>,
    /// Work on a session that is not complete (with a warning).
    pub allow_incomplete: bool,
}

/// A refined camera: intrinsics and the view's pose.
type Camera = (crate::calib::camera::Intrinsics, crate::calib::camera::Pose);

/// What `fit/fit.json` holds for validation.
struct FitLoaded {
    models: Vec<Shading>,
    chosen: Model,
    /// 3, or 1 for a monochrome camera.
    channels: usize,
    /// The camera the fit refined with the highlight (its pose checked here, its intrinsics
    /// against the image where it is used: [`load_with_camera`]).
    camera: Option<Camera>,
    /// The factor the reference standard gave per channel (radiance per unit BRDF), where
    /// the fit had one: what turns the plots' relative units into 1/sr.
    factor: Option<Vec<f64>>,
}

/// The camera `glint fit` refined with the highlight (fit.json's `camera_refined`, where
/// the grid photo left the pose weak), which the fitted parameters belong to; None where
/// the fit kept the calibrated camera.
pub fn refined_camera(dir: &Path) -> Result<Option<Camera>, ValidateError> {
    Ok(load_fit_file(dir, &session_facts(dir)?)?.camera)
}

/// The facts of the session at `dir` a fit.json is checked against (its manifest read and
/// checked as every stage does; its state is the caller's to check).
fn session_facts(dir: &Path) -> Result<crate::fit::file::Facts, ValidateError> {
    Ok(crate::fit::file::Facts::of(&session::open(dir, true)?))
}

/// The fitted models of a session and the chosen one, from `fit/fit.json`, read and
/// checked against the session as every stage does ([`crate::fit::file::load`]). A
/// monochrome fit's one kd and ks are in all three places of [`Shading`].
pub fn load_fit(dir: &Path) -> Result<(Vec<Shading>, Model), ValidateError> {
    load_fit_channels(dir).map(|(m, c, _)| (m, c))
}

/// [`load_fit`] with the fit's channel count (3, or 1 for a monochrome camera).
pub fn load_fit_channels(dir: &Path) -> Result<(Vec<Shading>, Model, usize), ValidateError> {
    let f = load_fit_file(dir, &session_facts(dir)?)?;
    Ok((f.models, f.chosen, f.channels))
}

fn load_fit_file(dir: &Path, facts: &crate::fit::file::Facts) -> Result<FitLoaded, ValidateError> {
    let f = crate::fit::file::load(dir, facts)?;
    // Checked: every model known, kd and ks one per channel (ks left out only where the
    // model has no lobe), n bounded where there is a lobe, the factor one per channel.
    let channels = f.channels;
    let three = |p: &[crate::fit::file::Param], missing: f64| -> [f64; 3] {
        [0, 1, 2].map(|i| {
            p.get(i.min(p.len().saturating_sub(1)))
                .and_then(|p| p.value)
                .unwrap_or(missing)
        })
    };
    let models = f
        .candidates
        .iter()
        .filter_map(|c| {
            Some(Shading {
                model: c.model()?,
                kd: three(&c.kd, f64::NAN),
                ks: three(&c.ks, 0.0),
                n: c.n.map_or(f64::NAN, |p| p.v()),
            })
        })
        .collect::<Vec<_>>();
    let chosen = Model::ALL
        .into_iter()
        .find(|m| m.name() == f.chosen)
        .ok_or_else(|| {
            file_err(
                &dir.join("fit/fit.json"),
                "the chosen model is not among the candidates; re-run glint fit",
            )
        })?;
    let camera = f.camera_refined.map(|c| {
        (
            crate::calib::camera::Intrinsics::from(&c.intrinsics),
            crate::calib::camera::Pose {
                rvec: c.rvec,
                t: c.t,
            },
        )
    });
    let factor = f
        .reference
        .map(|r| r.factor.iter().map(|p| p.v()).collect::<Vec<f64>>());
    Ok(FitLoaded {
        models,
        chosen,
        channels,
        camera,
        factor,
    })
}

/// One model's validation.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ModelValidation {
    pub model: Model,
    pub chosen: bool,
    /// Per channel: R, G, B, or a monochrome camera's one.
    pub kd: Vec<f64>,
    pub ks: Vec<f64>,
    pub n: Option<f64>,
    /// Against the photographs, in pixel values.
    pub pixels: PixelMetrics,
    /// Against the merged radiance.
    pub radiance: RadianceMetrics,
}

/// The file `validation/validation.json`.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ValidationReport {
    pub format: String,
    pub format_version: u32,
    pub created: String,
    pub session: String,
    /// Channels compared: 3 (R, G, B) or 1 (a monochrome camera).
    pub channels: usize,
    pub chosen: Model,
    /// Tile pixels compared.
    pub tile_pixels: usize,
    /// The exposure the figures show, µs.
    pub figure_exposure_us: f64,
    /// The floor's albedos measured from the radiance (dark squares, light squares,
    /// surround; per channel: R, G, B, or a monochrome camera's one), which the renders
    /// use.
    pub floor_albedo: Vec<Vec<Option<f64>>>,
    pub models: Vec<ModelValidation>,
    pub warnings: Vec<String>,
    pub files: Vec<String>,
    pub seconds: f64,
}

impl ValidationReport {
    /// The file `validation/validation.json` this report is written as.
    pub fn file(&self) -> file::ValidationFile {
        let list = |x: &[f64]| x.iter().map(|x| finite(*x)).collect();
        file::ValidationFile {
            format: self.format.clone(),
            format_version: Some(self.format_version),
            created: self.created.clone(),
            session: self.session.clone(),
            channels: self.channels,
            chosen: self.chosen.name().into(),
            tile_pixels: self.tile_pixels,
            figure_exposure_us: finite(self.figure_exposure_us),
            floor_albedo: self.floor_albedo.clone(),
            models: self
                .models
                .iter()
                .map(|m| file::ModelValidation {
                    model: m.model.name().into(),
                    chosen: m.chosen,
                    kd: list(&m.kd),
                    ks: list(&m.ks),
                    n: m.n.and_then(finite),
                    pixels: file::PixelMetrics {
                        readings: m.pixels.readings,
                        rmse: finite(m.pixels.rmse),
                        noise_rmse: finite(m.pixels.noise_rmse),
                        psnr_db: finite(m.pixels.psnr_db),
                        ssim: finite(m.pixels.ssim),
                        per_exposure: m
                            .pixels
                            .per_exposure
                            .iter()
                            .map(|e| file::ExposureMetrics {
                                exposure_us: finite(e.exposure_us),
                                readings: e.readings,
                                rmse: finite(e.rmse),
                                noise_rmse: finite(e.noise_rmse),
                                psnr_db: finite(e.psnr_db),
                                ssim: finite(e.ssim),
                                ssim_windows: e.ssim_windows,
                            })
                            .collect(),
                    },
                    radiance: file::RadianceMetrics {
                        samples: m.radiance.samples,
                        relative_error: finite(m.radiance.relative_error),
                        relative_error_rgb: list(&m.radiance.relative_error_rgb),
                        mean_z2: finite(m.radiance.mean_z2),
                    },
                })
                .collect(),
            warnings: self.warnings.clone(),
            files: self.files.clone(),
            seconds: finite(self.seconds),
        }
    }

    /// The chosen model's validation.
    pub fn chosen(&self) -> &ModelValidation {
        self.models
            .iter()
            .find(|m| m.chosen)
            .expect("the chosen model is validated")
    }
}

/// Load a session's radiance, calibration, frames and response, and trace its view.
pub fn load(dir: &Path, on_event: &mut dyn FnMut(ValidateEvent)) -> Result<Loaded, ValidateError> {
    load_allowing(dir, false, on_event)
}

/// [`load`], on a session that is not complete too if `allow_incomplete`.
pub fn load_allowing(
    dir: &Path,
    allow_incomplete: bool,
    on_event: &mut dyn FnMut(ValidateEvent),
) -> Result<Loaded, ValidateError> {
    load_with_camera(dir, allow_incomplete, None, on_event)
}

/// [`load_allowing`] with the scene seen by `camera` (intrinsics and pose) instead of the
/// calibrated one: the camera `glint fit` refined, which its parameters belong to.
pub fn load_with_camera(
    dir: &Path,
    allow_incomplete: bool,
    camera: Option<Camera>,
    on_event: &mut dyn FnMut(ValidateEvent),
) -> Result<Loaded, ValidateError> {
    on_event(ValidateEvent::Loading);
    let mut inputs = load_inputs_allowing(dir, allow_incomplete)?;
    if let Some((k, pose)) = camera {
        if let Some(p) = crate::calib::run::intrinsics_problem(&k, inputs.width, inputs.height) {
            return Err(file_err(
                &dir.join("fit/fit.json"),
                format!("camera_refined: {p}; re-run glint fit"),
            ));
        }
        inputs.scene = inputs.scene.with_camera(k, pose);
    }
    let m = inputs.manifest.clone();
    let rig = m
        .rig
        .as_ref()
        .ok_or_else(|| ValidateError::Input("the session has no rig".into()))?;
    let response = inputs.response.clone().ok_or_else(|| {
        file_err(
            &dir.join("hdr/response.json"),
            format!("missing or unreadable: re-run glint hdr {}", dir.display()),
        )
    })?;
    on_event(ValidateEvent::Tracing {
        pixels: inputs.width * inputs.height,
    });
    let board = Board {
        inner_corners: rig.geometry.grid_inner_corners,
        square_mm: rig.geometry.grid_square_mm,
    };
    // The frames are read while the view is traced: the two need nothing of each other.
    let (frames, view) = rayon::join(
        || crate::hdr::load_session(dir, &m),
        || View::new(&inputs.scene, board),
    );
    let (tiles, darks) = frames?;
    let dark = dark_levels(&response, &tiles, &darks);
    let region = Region::new(inputs.width, inputs.height, view.tile_pixels(&inputs.scene));
    if region.count() == 0 {
        return Err(ValidateError::Input(
            "no pixel sees the tile: check the rig's tile_outline_mm and the calibration".into(),
        ));
    }
    let floor = view.floor_albedo(&inputs.radiance, &inputs.mask);
    Ok(Loaded {
        inputs,
        tiles,
        dark,
        response,
        view,
        region,
        floor,
    })
}

/// Validate one model on a loaded session; returns the figures and the render.
pub fn validate_model(l: &Loaded, f: &Shading, chosen: bool) -> (ModelValidation, Vec<f32>) {
    let nc = l.inputs.channels;
    let rendered = l.view.render_channels(f, &l.floor, nc);
    let pixels = pixel_metrics(&rendered, &l.region, &l.response, &l.tiles, &l.dark);
    let radiance = radiance_metrics(
        &rendered,
        &l.region,
        &l.inputs.radiance,
        &l.inputs.variance,
        &l.inputs.mask,
    );
    (
        ModelValidation {
            model: f.model,
            chosen,
            kd: f.kd[..nc].to_vec(),
            ks: f.ks[..nc].to_vec(),
            n: f.n.is_finite().then_some(f.n),
            pixels,
            radiance,
        },
        rendered,
    )
}

/// `glint validate SESSION`.
pub fn run(
    dir: &Path,
    opts: &ValidateOptions,
    on_event: &mut dyn FnMut(ValidateEvent),
) -> Result<ValidationReport, ValidateError> {
    let start = Instant::now();
    // The session's state and consistency first, before any derived file.
    let manifest = session::open(dir, opts.allow_incomplete)?;
    session::check_out_dir(&dir.join("validation"))?;
    let FitLoaded {
        models: fitted,
        chosen,
        channels: fit_channels,
        camera,
        factor,
    } = load_fit_file(dir, &crate::fit::file::Facts::of(&manifest))?;
    let l = load_with_camera(dir, opts.allow_incomplete, camera, on_event)?;
    if fit_channels != l.inputs.channels {
        return Err(file_err(
            &dir.join("fit/fit.json"),
            format!(
                "fits {} but the session's radiance has {}; re-run glint fit",
                session::channels_name(fit_channels as u8),
                session::channels_name(l.inputs.channels as u8)
            ),
        ));
    }
    let mut models = Vec::new();
    let mut renders = Vec::new();
    // The radiance profile (its own samples and fits) is worked out beside the renders.
    let mut profile = None;
    rayon::in_place_scope(|s| {
        s.spawn(|_| profile = Some(figures::profile_svg(&l, &fitted, chosen, factor.as_deref())));
        for f in &fitted {
            on_event(ValidateEvent::Rendering { model: f.model });
            let (v, r) = validate_model(&l, f, f.model == chosen);
            models.push(v);
            renders.push(r);
        }
    });
    let profile = profile.expect("the profile task ran in the scope");
    let chosen_k = models
        .iter()
        .position(|m| m.chosen)
        .expect("load_fit checked the chosen model is among the fitted");
    let best = &models[chosen_k];
    // Nothing compared is no validation (a PSNR of NaN): say what to look at.
    if best.pixels.readings == 0 {
        return Err(ValidateError::Input(format!(
            "no reading of the tile could be compared with the render ({} tile pixels, every reading too dark, saturated or outside the response's valid range): check hdr/response.json and the exposures (re-run glint hdr {})",
            l.region.count(),
            dir.display()
        )));
    }
    let j = match opts.exposure_us {
        Some(t) => l
            .tiles
            .frames
            .iter()
            .position(|f| (f.exposure_us / t - 1.0).abs() < 0.01)
            .ok_or_else(|| {
                ValidateError::Input(format!(
                    "the session has no tile frame at {t} µs; its exposures are {}",
                    l.tiles
                        .frames
                        .iter()
                        .map(|f| format!("{}", f.exposure_us))
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?,
        // The exposure with the most tile readings counted (longest on a tie).
        None => (0..best.pixels.per_exposure.len())
            .max_by_key(|k| (best.pixels.per_exposure[*k].readings, *k))
            .unwrap_or(0),
    };
    on_event(ValidateEvent::Figures);
    let out = dir.join("validation");
    session::out_dir(&out)?;
    let write = |name: &str, bytes: &[u8]| -> Result<(), ValidateError> {
        session::write_replace(&out.join(name), bytes)?;
        Ok(())
    };
    let labels: Vec<String> = models
        .iter()
        .map(|m| {
            format!(
                "{}{}",
                m.model.name(),
                if m.chosen { " (chosen)" } else { "" }
            )
        })
        .collect();
    let (compare, difference) = rayon::join(
        || figures::compare_png(&l, j, &renders, &labels),
        || figures::difference_png(&l, j, &renders, &labels, chosen_k),
    );
    write("compare.png", &compare?)?;
    write("difference.png", &difference?)?;
    let mut warnings = l.inputs.warnings.clone();
    let mut files: Vec<String> = ["validation.json", "compare.png", "difference.png"]
        .iter()
        .map(|f| format!("validation/{f}"))
        .collect();
    match profile {
        Ok((svg, polar)) => {
            write("profile.svg", svg.as_bytes())?;
            write("brdf.svg", polar.as_bytes())?;
            files.push("validation/profile.svg".into());
            files.push("validation/brdf.svg".into());
        }
        Err(e) => {
            // A profile from an earlier run would no longer belong to these results (and
            // the report copies what it finds).
            for f in ["profile.svg", "brdf.svg"] {
                let stale = out.join(f);
                if stale.symlink_metadata().is_ok() {
                    std::fs::remove_file(&stale).map_err(|e| file_err(&stale, e))?;
                }
            }
            warnings.push(format!("no radiance profile: {e}"));
        }
    }
    let b = best.pixels.rmse / best.pixels.noise_rmse;
    if b > 1.5 {
        warnings.push(format!(
            "the chosen model's renders differ from the photographs by {:.1} times the noise (RMSE {:.2} against {:.2} values): the model, the calibration or the response does not explain the tile",
            b, best.pixels.rmse, best.pixels.noise_rmse
        ));
    }
    let report = ValidationReport {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        created: session::timestamp(std::time::SystemTime::now()),
        session: dir.display().to_string(),
        channels: l.inputs.channels,
        chosen,
        tile_pixels: l.region.count(),
        figure_exposure_us: l.tiles.frames[j].exposure_us,
        floor_albedo: l
            .floor
            .iter()
            .map(|r| {
                r[..l.inputs.channels]
                    .iter()
                    .map(|a| a.is_finite().then_some(*a))
                    .collect()
            })
            .collect(),
        models,
        warnings,
        files,
        seconds: start.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_vec_pretty(&report.file()).expect("report serialises");
    write("validation.json", &json)?;
    Ok(report)
}
