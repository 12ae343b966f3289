//! Absolute reflectance from a reference standard.
//!
//! The radiance Glint measures carries one unknown factor per channel: the lamp's
//! intensity times the camera's gain (docs/design.md: L = f_r (I / D²) (n·l), and the merged
//! radiance is L times the camera's scale). A Lambertian standard of known reflectance ρ
//! beside the tile, in the same frames, has f_r = ρ / π, and its geometry (where each pixel
//! sees it, the lamp's distance and angle there) is known from the calibration and the rig;
//! so each of its pixels gives the factor
//!
//!   F_c = π L_c / (ρ_c (n·l) / D²),
//!
//! and the fitted kd_c, ks_c (which carry F_c) divided by it are docs/design.md's kd and ks in
//! 1/sr; the diffuse albedo is π kd.
//!
//! The factor's uncertainty: the pixels' scatter (standard error of their mean, after
//! values beyond five robust standard deviations are set aside), the certificate's stated
//! uncertainty, and the response curve's error between the values the standard and the
//! tile are read at (the curve's misfit beyond the noise, [`Channel::misfit_sd`]). Not
//! included: the standard's departure from Lambertian (a white standard's reflectance
//! factor at 0/45° differs from its hemispherical reflectance by about 1%: give the
//! certificate's value for the rig's angles where it has one), vignetting (the standard
//! and the tile are compared through different parts of the lens: keep the standard near
//! the tile) and stray light.
//!
//! [`Channel::misfit_sd`]: crate::hdr::response::Channel::misfit_sd

use glint_format::stage::{finite, fit as file};
use serde::Serialize;

use super::geometry::Scene;
use super::model::{Geometry, Model, Reflectance as _};
use super::types::{FitError, Inputs, Param};
use crate::hdr::merge::MASK_OK;
use crate::rig::ReferenceSection;

/// Fewest usable pixels of the standard.
pub const MIN_PIXELS: usize = 30;

/// What the reference standard gave: `fit.json`'s `reference`.
#[derive(Debug, Clone, Serialize)]
pub struct ReferenceReport {
    /// The certificate's reflectance and its standard uncertainty, per channel.
    pub reflectance: Vec<f64>,
    pub reflectance_sd: Vec<f64>,
    /// Pixels that see only the standard, read within the response's valid range.
    pub pixels: usize,
    /// Of those, set aside as outliers (beyond five robust standard deviations).
    pub outliers: usize,
    /// The factor lamp intensity x camera gain per channel (radiance = F f_r (n·l) / D²,
    /// D in mm): what the relative kd and ks carry.
    pub factor: Vec<Param>,
    /// The factor's relative standard deviation by source, per channel: the pixels'
    /// scatter, the certificate, the response curve.
    pub factor_relative_sd: Vec<FactorSd>,
}

/// Sources of the factor's relative uncertainty.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FactorSd {
    pub pixels: f64,
    pub certificate: f64,
    pub response: f64,
    pub total: f64,
}

/// A candidate's parameters in absolute terms: `fit.json`'s `absolute`.
#[derive(Debug, Clone, Serialize)]
pub struct Absolute {
    /// docs/design.md's kd, 1/sr.
    pub kd_per_sr: Vec<Param>,
    /// The diffuse albedo, pi kd.
    pub albedo: Vec<Param>,
    /// docs/design.md's ks in 1/sr (empty for a model without a lobe, and for the microfacet
    /// model, whose ks is `f0`).
    pub ks_per_sr: Vec<Param>,
    /// The microfacet model's Fresnel reflectance at normal incidence (ggx only).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub f0: Vec<Param>,
}

impl ReferenceReport {
    /// As `fit/fit.json` holds it.
    pub fn file(&self) -> file::Reference {
        file::Reference {
            reflectance: self.reflectance.iter().map(|x| finite(*x)).collect(),
            reflectance_sd: self.reflectance_sd.iter().map(|x| finite(*x)).collect(),
            pixels: self.pixels,
            outliers: self.outliers,
            factor: self.factor.iter().map(Param::file).collect(),
            factor_relative_sd: self
                .factor_relative_sd
                .iter()
                .map(|s| file::FactorSd {
                    pixels: finite(s.pixels),
                    certificate: finite(s.certificate),
                    response: finite(s.response),
                    total: finite(s.total),
                })
                .collect(),
        }
    }
}

impl Absolute {
    /// As `fit/fit.json` holds it.
    pub fn file(&self) -> file::Absolute {
        let list = |p: &[Param]| p.iter().map(Param::file).collect();
        file::Absolute {
            kd_per_sr: list(&self.kd_per_sr),
            albedo: list(&self.albedo),
            ks_per_sr: list(&self.ks_per_sr),
            f0: list(&self.f0),
        }
    }
}

/// Measure the factor from the standard's pixels in the session's radiance.
pub fn measure(inputs: &Inputs, r: &ReferenceSection) -> Result<ReferenceReport, FitError> {
    let (w, h, nc) = (inputs.width, inputs.height, inputs.channels);
    let tile = &inputs.scene;
    let standard = Scene::new(
        tile.intrinsics.clone(),
        tile.pose,
        tile.lamp,
        r.thickness_mm,
        r.outline_mm.clone(),
        [w, h],
    );
    let map = super::sample::TileMap::new(&standard, w, h, 1.0);
    let rho: Vec<f64> = (0..nc).map(|c| r.reflectance.get(c, nc)).collect();
    let rho_sd: Vec<f64> = (0..nc).map(|c| r.reflectance_sd.get(c, nc)).collect();
    let mut seen = 0usize;
    let mut per_channel: Vec<Vec<f64>> = vec![Vec::new(); nc];
    for (i, p) in map.points.iter().enumerate() {
        let Some(p) = p else { continue };
        let (u, v) = ((i % w) as f64, (i / w) as f64);
        // The tile in front of the standard (its top face higher, hit first).
        if tile.height > r.thickness_mm
            && tile.on_plane(u, v).is_some_and(|q| tile.inside(q[0], q[1]))
        {
            continue;
        }
        seen += 1;
        let g = Geometry::at(*p, [0.0, 0.0, 1.0], tile.lamp, tile.centre);
        if g.cos_l <= 0.0 {
            continue;
        }
        let irradiance = g.cos_l / g.d2;
        let ok = (0..nc).all(|c| {
            let k = i * nc + c;
            inputs.mask[k] == MASK_OK && inputs.radiance[k].is_finite() && inputs.radiance[k] > 0.0
        });
        if !ok {
            continue;
        }
        for c in 0..nc {
            let l = inputs.radiance[i * nc + c] as f64;
            per_channel[c].push(std::f64::consts::PI * l / (rho[c] * irradiance));
        }
    }
    let usable = per_channel[0].len();
    let outline = "reference.outline_mm";
    if seen == 0 {
        return Err(FitError::Input(format!(
            "the reference standard ({outline}) is not in the photos as the calibration places it; check its outline (grid coordinates, mm) and that the camera sees it beside the tile"
        )));
    }
    if usable < MIN_PIXELS {
        return Err(FitError::Input(format!(
            "the reference standard ({outline}) shows in {seen} pixels but only {usable} are read within the response's valid range (fewer than {MIN_PIXELS}): it is saturated or too dark in every exposure; extend the bracket (bracket.exposures_us) to read it"
        )));
    }
    let response_sd = |c: usize| {
        inputs
            .response
            .as_ref()
            .and_then(|resp| resp.channels.get(c))
            .map_or(0.0, |ch| ch.misfit_sd)
    };
    let mut factor = Vec::new();
    let mut parts = Vec::new();
    let mut outliers = 0;
    for (c, x) in per_channel.iter_mut().enumerate() {
        let (mean, se, out) = robust_mean(x);
        outliers = outliers.max(out);
        let pixels = se / mean;
        let certificate = rho_sd[c] / rho[c];
        let response = response_sd(c);
        let total = (pixels * pixels + certificate * certificate + response * response).sqrt();
        let sd = total * mean;
        factor.push(Param {
            value: mean,
            sd,
            ci95: [mean - 1.96 * sd, mean + 1.96 * sd],
        });
        parts.push(FactorSd {
            pixels,
            certificate,
            response,
            total,
        });
    }
    Ok(ReferenceReport {
        reflectance: rho,
        reflectance_sd: rho_sd,
        pixels: usable,
        outliers,
        factor,
        factor_relative_sd: parts,
    })
}

/// Mean and standard error of the values within five robust standard deviations (1.4826
/// median absolute deviations) of the median, and how many were set aside.
fn robust_mean(x: &mut [f64]) -> (f64, f64, usize) {
    x.sort_by(f64::total_cmp);
    let median = x[x.len() / 2];
    let mut dev: Vec<f64> = x.iter().map(|v| (v - median).abs()).collect();
    dev.sort_by(f64::total_cmp);
    let mad = 1.4826 * dev[dev.len() / 2];
    let kept: Vec<f64> = if mad > 0.0 {
        x.iter()
            .copied()
            .filter(|v| (v - median).abs() <= 5.0 * mad)
            .collect()
    } else {
        x.to_vec()
    };
    let n = kept.len() as f64;
    let mean = kept.iter().sum::<f64>() / n;
    let var = kept.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, (var / n).sqrt(), x.len() - kept.len())
}

/// A relative parameter divided by the factor: its value and interval scaled, the factor's
/// relative uncertainty added in quadrature to the sd and to each half of the interval.
fn scaled(p: &Param, f: &Param, by: f64) -> Param {
    let rel = f.sd / f.value;
    let value = by * p.value / f.value;
    let sd = ((by * p.sd / f.value).powi(2) + (value * rel).powi(2)).sqrt();
    let lo = by * p.ci95[0] / f.value;
    let hi = by * p.ci95[1] / f.value;
    let widen = |half: f64| (half * half + (1.96 * value * rel).powi(2)).sqrt();
    Param {
        value,
        sd,
        ci95: [
            (value - widen(value - lo)).max(0.0),
            value + widen(hi - value),
        ],
    }
}

/// A candidate's kd and ks in absolute terms.
pub fn absolute(kd: &[Param], ks: &[Param], model: Model, r: &ReferenceReport) -> Absolute {
    let pi = std::f64::consts::PI;
    let per = |v: &[Param], by: f64| -> Vec<Param> {
        v.iter()
            .zip(&r.factor)
            .map(|(p, f)| scaled(p, f, by))
            .collect()
    };
    Absolute {
        kd_per_sr: per(kd, 1.0),
        albedo: per(kd, pi),
        ks_per_sr: if model.has_lobe() && model != Model::Ggx {
            per(ks, 1.0)
        } else {
            Vec::new()
        },
        f0: if model == Model::Ggx {
            per(ks, 1.0)
        } else {
            Vec::new()
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_factor_divides_out_with_its_uncertainty_added() {
        let p = Param {
            value: 2.0e6,
            sd: 2.0e4,
            ci95: [2.0e6 - 3.92e4, 2.0e6 + 3.92e4],
        };
        let f = Param {
            value: 1.0e7,
            sd: 1.0e5,
            ci95: [0.0, 0.0],
        };
        let a = scaled(&p, &f, 1.0);
        assert!((a.value - 0.2).abs() < 1e-12);
        // 1% and 1% in quadrature.
        assert!((a.sd / a.value - 2f64.sqrt() * 0.01).abs() < 1e-9, "{a:?}");
        assert!((a.ci95[1] - a.value - 1.96 * a.sd).abs() < 1e-6 * a.value);
    }

    #[test]
    fn outliers_are_set_aside() {
        let mut x: Vec<f64> = (0..100)
            .map(|i| 1.0 + 0.01 * ((i % 7) as f64 - 3.0))
            .collect();
        x.push(50.0);
        let (mean, se, out) = robust_mean(&mut x);
        assert_eq!(out, 1);
        assert!((mean - 1.0).abs() < 0.002 && se < 0.01, "{mean} {se}");
    }
}
