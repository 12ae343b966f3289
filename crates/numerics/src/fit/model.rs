//! Reflectance models of docs/design.md, written so that for a fixed exponent n every model is
//! linear in kd and ks:
//!
//!   L_c = kd_c a + ks_c b(n),   a = (n.l) / D^2,   b(n) = S(n) / D^2,
//!
//! where S is the specular term times the cosine: Phong (r.v)^n, Blinn-Phong (n.h)^n,
//! cosine lobe (n+2)/(2 pi) (r.v)^n (n.l); Lambert has none. The lamp intensity I is
//! absorbed into kd and ks (they are known up to one common factor). Dot products are
//! clamped at 0.
//!
//! The fitter takes any [`Reflectance`]: a model is its name and its lobe's basis b(n)
//! with the derivative by ln n. The four built-in models are the [`Model`] enum; another
//! (Lafortune, Ward, a microfacet lobe with n as its sharpness) implements the trait and
//! is fitted, chosen among and reported the same way.

use serde::{Deserialize, Serialize};

/// The geometry of one sample: cosines and the lamp distance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Geometry {
    /// n . l (clamped at 0).
    pub cos_l: f64,
    /// r . v, r the mirror direction of l about n (clamped at 0).
    pub r_dot_v: f64,
    /// n . h, h the half vector of l and v (clamped at 0).
    pub n_dot_h: f64,
    /// Squared lamp distance (mm^2).
    pub d2: f64,
    /// n . v (clamped at 0): the microfacet model's view cosine.
    #[serde(default)]
    pub cos_v: f64,
    /// v . h (= l . h): the angle Fresnel's reflectance grows with.
    #[serde(default)]
    pub v_dot_h: f64,
}

pub type V3 = [f64; 3];

pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub fn unit(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

impl Geometry {
    /// The geometry at surface point `p` with unit normal `n`, lamp at `lamp`, camera centre
    /// at `eye` (all in one frame).
    pub fn at(p: V3, n: V3, lamp: V3, eye: V3) -> Self {
        let to_l = sub(lamp, p);
        let d2 = dot(to_l, to_l);
        Geometry::from_vectors(unit(to_l), unit(sub(eye, p)), n, 1.0 / d2)
    }

    /// From given unit vectors (light, view, normal) and a lamp intensity factor: for
    /// photometric data sets, where each sample has its own light. `d2` is 1 / intensity.
    pub fn from_vectors(l: V3, v: V3, n: V3, intensity: f64) -> Self {
        let nl = dot(n, l);
        let r = [
            2.0 * nl * n[0] - l[0],
            2.0 * nl * n[1] - l[1],
            2.0 * nl * n[2] - l[2],
        ];
        let h = unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
        Geometry {
            cos_l: nl.max(0.0),
            r_dot_v: dot(r, v).max(0.0),
            n_dot_h: dot(n, h).max(0.0),
            d2: 1.0 / intensity,
            cos_v: dot(n, v).max(0.0),
            v_dot_h: dot(v, h).max(0.0),
        }
    }
}

/// A lobe of the form b(n) = factor x^n, times (n + 2) for the cosine lobe: the fitter
/// precomputes ln x and the factor once per sample, so that each trial n costs one exp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PowerLobe {
    /// The lobe's cosine (r.v or n.h), clamped at 0.
    pub x: f64,
    pub factor: f64,
    /// Multiply by (n + 2) (the cosine lobe's normalisation).
    pub n_plus_two: bool,
}

/// A reflectance model the fitter can take: L_c = kd_c (n.l)/D^2 + ks_c b(n), linear in kd
/// and ks for a fixed sharpness n > 0.
pub trait Reflectance: std::fmt::Debug + Send + Sync {
    fn name(&self) -> &'static str;
    /// Whether the model has a specular lobe (ks and n); without one, L = kd (n.l)/D^2.
    fn has_lobe(&self) -> bool;
    /// How much the model assumes beyond its parameter count: among candidates of as many
    /// parameters, the chooser takes the lowest whose held-out error is within the noise
    /// of the best (0 for the paper's models).
    fn complexity(&self) -> u8 {
        0
    }
    /// The lobe's basis b(n) at a sample and its derivative by ln n, n db/dn.
    fn specular(&self, g: &Geometry, n: f64) -> (f64, f64);
    /// The lobe as a power of a cosine where it is one (the fast path); None otherwise.
    fn power_lobe(&self, _g: &Geometry) -> Option<PowerLobe> {
        None
    }
    /// Predicted radiance of one channel.
    fn radiance(&self, g: &Geometry, kd: f64, ks: f64, n: f64) -> f64 {
        let lobe = if self.has_lobe() && ks != 0.0 {
            ks * self.specular(g, n).0
        } else {
            0.0
        };
        kd * diffuse(g) + lobe
    }
}

/// A reference to a model is a model: candidates of different types can be compared as
/// `&dyn Reflectance`.
impl<T: Reflectance + ?Sized> Reflectance for &T {
    fn name(&self) -> &'static str {
        (**self).name()
    }
    fn has_lobe(&self) -> bool {
        (**self).has_lobe()
    }
    fn complexity(&self) -> u8 {
        (**self).complexity()
    }
    fn specular(&self, g: &Geometry, n: f64) -> (f64, f64) {
        (**self).specular(g, n)
    }
    fn power_lobe(&self, g: &Geometry) -> Option<PowerLobe> {
        (**self).power_lobe(g)
    }
}

/// The diffuse basis a = (n.l) / D^2.
pub fn diffuse(g: &Geometry) -> f64 {
    g.cos_l / g.d2
}

/// The built-in models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Model {
    Lambert,
    Phong,
    BlinnPhong,
    CosineLobe,
    /// Cook-Torrance with the GGX (Trowbridge-Reitz) distribution, Smith's separable
    /// shadowing and Schlick's Fresnel (see [`ggx`]).
    Ggx,
}

impl Model {
    pub const ALL: [Model; 5] = [
        Model::Lambert,
        Model::Phong,
        Model::BlinnPhong,
        Model::CosineLobe,
        Model::Ggx,
    ];

    /// The diffuse basis a = (n.l) / D^2.
    pub fn diffuse(g: &Geometry) -> f64 {
        diffuse(g)
    }
}

impl Reflectance for Model {
    fn name(&self) -> &'static str {
        match self {
            Model::Lambert => "lambert",
            Model::Phong => "phong",
            Model::BlinnPhong => "blinn-phong",
            Model::CosineLobe => "cosine-lobe",
            Model::Ggx => "ggx",
        }
    }

    fn has_lobe(&self) -> bool {
        *self != Model::Lambert
    }

    fn complexity(&self) -> u8 {
        // Shadowing and Fresnel are physics the paper's lobes do without: among models of
        // as many parameters, the microfacet one is taken only where it explains the
        // held-out samples better beyond their noise.
        u8::from(*self == Model::Ggx)
    }

    fn power_lobe(&self, g: &Geometry) -> Option<PowerLobe> {
        let inv = 1.0 / g.d2;
        Some(match self {
            Model::Ggx => return None,
            Model::Lambert => PowerLobe {
                x: 0.0,
                factor: 0.0,
                n_plus_two: false,
            },
            Model::Phong => PowerLobe {
                x: g.r_dot_v,
                factor: inv,
                n_plus_two: false,
            },
            Model::BlinnPhong => PowerLobe {
                x: g.n_dot_h,
                factor: inv,
                n_plus_two: false,
            },
            Model::CosineLobe => PowerLobe {
                x: g.r_dot_v,
                factor: g.cos_l * inv / (2.0 * std::f64::consts::PI),
                n_plus_two: true,
            },
        })
    }

    /// The specular basis b(n) and its derivative by ln n, d b / d ln n = n db/dn.
    fn specular(&self, g: &Geometry, n: f64) -> (f64, f64) {
        let pow = |x: f64| -> (f64, f64) {
            // x^n and n d(x^n)/dn = n x^n ln x; 0 where x = 0.
            if x <= 0.0 {
                (0.0, 0.0)
            } else {
                let p = x.powf(n);
                (p, n * p * x.ln())
            }
        };
        let inv = 1.0 / g.d2;
        match self {
            Model::Lambert => (0.0, 0.0),
            Model::Phong => {
                let (p, dp) = pow(g.r_dot_v);
                (p * inv, dp * inv)
            }
            Model::BlinnPhong => {
                let (p, dp) = pow(g.n_dot_h);
                (p * inv, dp * inv)
            }
            Model::CosineLobe => {
                let (p, dp) = pow(g.r_dot_v);
                let c = g.cos_l * inv / (2.0 * std::f64::consts::PI);
                // ((n + 2) p)' by ln n = n p + (n + 2) n p ln x.
                ((n + 2.0) * p * c, (n * p + (n + 2.0) * dp) * c)
            }
            Model::Ggx => ggx::lobe(g, n),
        }
    }
}

/// The microfacet candidate: Cook-Torrance with the GGX (Trowbridge-Reitz) normal
/// distribution, Smith's separable shadowing-masking and Schlick's Fresnel,
///
///   f_r = kd + ks D(h) G1(l) G1(v) F~(v.h) / (4 (n.l) (n.v)),
///   D = α² / (π ((n.h)² (α² - 1) + 1)²),   G1(x) = 2 (n.x) / ((n.x) + sqrt(α² + (1 - α²) (n.x)²)),
///
/// F~ = F / F0 = 1 + (1/F0 - 1) (1 - v.h)^5 Schlick's reflectance over its value at normal
/// incidence, so that ks is F0 (times the lamp-and-camera factor where the units are
/// relative; F0 itself with a reference standard). The growth's shape takes F0 =
/// [`ggx::F0_SHAPE`] (a dielectric of refractive index 1.5): ks scales the lobe, and the
/// shape's own F0 would be a second nonlinear parameter that the rig's angles (v.h ≥ 0.6
/// near the highlight, where (1 - v.h)^5 ≤ 0.01) barely determine.
///
/// The sharpness is fitted on the fitter's exponent scale: α = sqrt(2 / (n + 2)) (the
/// Beckmann-Phong correspondence of Walter et al. 2007), so that n means a lobe of about
/// the same width in every model, and α 0.05..0.5 is n 798..6.
pub mod ggx {
    use super::Geometry;

    /// The F0 that Schlick's growth is shaped with.
    pub const F0_SHAPE: f64 = 0.04;

    /// Roughness for exponent n.
    pub fn alpha(n: f64) -> f64 {
        (2.0 / (n + 2.0)).sqrt()
    }

    /// Exponent for roughness α.
    pub fn exponent(alpha: f64) -> f64 {
        2.0 / (alpha * alpha) - 2.0
    }

    /// The lobe's basis b = D G1(l) G1(v) F~ / (4 (n.v) D²) (f_r's lobe times n.l over
    /// the squared lamp distance) and n db/dn.
    pub fn lobe(g: &Geometry, n: f64) -> (f64, f64) {
        let (cl, cv, c) = (g.cos_l, g.cos_v, g.n_dot_h);
        if cl <= 0.0 || cv <= 0.0 {
            return (0.0, 0.0);
        }
        let a = alpha(n);
        let a2 = a * a;
        let t = 1.0 - c * c + c * c * a2;
        let d = a2 / (std::f64::consts::PI * t * t);
        let ql = (cl * cl + a2 * (1.0 - cl * cl)).sqrt();
        let qv = (cv * cv + a2 * (1.0 - cv * cv)).sqrt();
        let g1l = 2.0 * cl / (cl + ql);
        let w = (1.0 - g.v_dot_h).clamp(0.0, 1.0).powi(5);
        let fresnel = 1.0 + (1.0 / F0_SHAPE - 1.0) * w;
        // G1(v) / (4 n.v) = 1 / (2 (n.v + qv)): no division by a grazing n.v.
        let b = d * g1l * fresnel / (2.0 * (cv + qv) * g.d2);
        // d ln b / d α, then by ln n through α = sqrt(2 / (n + 2)).
        let dln_da = 2.0 / a
            - 4.0 * a * c * c / t
            - a * (1.0 - cl * cl) / (ql * (cl + ql))
            - a * (1.0 - cv * cv) / (qv * (cv + qv));
        let da_dln_n = -a * n / (2.0 * (n + 2.0));
        (b, b * dln_da * da_dln_n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Geometries over the hemisphere: light and view at several elevations and azimuths.
    fn geometries() -> Vec<Geometry> {
        let mut out = Vec::new();
        let dir = |el: f64, az: f64| {
            let (el, az) = (el.to_radians(), az.to_radians());
            [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]
        };
        for el_l in [15.0, 40.0, 75.0] {
            for el_v in [10.0, 35.0, 60.0, 85.0] {
                for az in [180.0, 160.0, 120.0, 60.0] {
                    out.push(Geometry::from_vectors(
                        dir(el_l, 0.0),
                        dir(el_v, az),
                        [0.0, 0.0, 1.0],
                        1.0,
                    ));
                }
            }
        }
        out
    }

    /// Every model's n db/dn against central differences in ln n.
    #[test]
    fn lobe_derivatives_match_finite_differences() {
        for m in Model::ALL {
            for g in geometries() {
                for n in [3.0, 18.0, 120.0, 900.0] {
                    let (b, db) = m.specular(&g, n);
                    let h: f64 = 1e-5;
                    let fd = (m.specular(&g, n * h.exp()).0 - m.specular(&g, n * (-h).exp()).0)
                        / (2.0 * h);
                    let scale = b.abs().max(1e-12);
                    assert!(
                        (db - fd).abs() <= 1e-5 * scale + 1e-12,
                        "{} n {n} {g:?}: analytic {db}, finite {fd}",
                        m.name()
                    );
                }
            }
        }
    }

    /// GGX's distribution is normalised (∫ D (n.h) dω = 1 over the hemisphere) at every
    /// roughness the fitter scans, and its lobe peaks at the mirror direction.
    #[test]
    fn the_ggx_distribution_is_normalised() {
        for alpha in [0.05, 0.1, 0.3, 0.5, 0.9] {
            let a2: f64 = alpha * alpha;
            // θ from 0 to π/2 in a fine grid (D is narrow for small α: substitute u = tan θ).
            let steps = 200_000;
            let mut sum = 0.0;
            let umax = 1e4 * alpha;
            for i in 0..steps {
                let u = (i as f64 + 0.5) / steps as f64 * umax;
                let th = u.atan();
                let c = th.cos();
                let t = 1.0 - c * c + c * c * a2;
                let d = a2 / (std::f64::consts::PI * t * t);
                // dω = 2π sin θ dθ, dθ = du / (1 + u²).
                sum += d * c * 2.0 * std::f64::consts::PI * th.sin() / (1.0 + u * u)
                    * (umax / steps as f64);
            }
            assert!((sum - 1.0).abs() < 2e-3, "alpha {alpha}: {sum}");
            assert!((ggx::alpha(ggx::exponent(alpha)) - alpha).abs() < 1e-12);
        }
        // The mirror configuration against one a little off it.
        let l = [0.5f64.sqrt(), 0.0, 0.5f64.sqrt()];
        let v = [-(0.5f64.sqrt()), 0.0, 0.5f64.sqrt()];
        let off = [-0.3, 0.4, 0.87f64];
        let nrm = (off[0] * off[0] + off[1] * off[1] + off[2] * off[2]).sqrt();
        let off = [off[0] / nrm, off[1] / nrm, off[2] / nrm];
        let at = Model::Ggx.specular(&Geometry::from_vectors(l, v, [0.0, 0.0, 1.0], 1.0), 100.0);
        let beside =
            Model::Ggx.specular(&Geometry::from_vectors(l, off, [0.0, 0.0, 1.0], 1.0), 100.0);
        assert!(at.0 > 5.0 * beside.0, "{at:?} {beside:?}");
    }
}
