//! Reflectance models of DESIGN.md, written so that for a fixed exponent n every model is
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
}

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn unit(a: V3) -> V3 {
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
}

impl Model {
    pub const ALL: [Model; 4] = [
        Model::Lambert,
        Model::Phong,
        Model::BlinnPhong,
        Model::CosineLobe,
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
        }
    }

    fn has_lobe(&self) -> bool {
        *self != Model::Lambert
    }

    fn power_lobe(&self, g: &Geometry) -> Option<PowerLobe> {
        let inv = 1.0 / g.d2;
        Some(match self {
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
        }
    }
}
