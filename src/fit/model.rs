//! Reflectance models of DESIGN.md, written so that for a fixed exponent n every model is
//! linear in kd and ks:
//!
//!   L_c = kd_c a + ks_c b(n),   a = (n.l) / D^2,   b(n) = S(n) / D^2,
//!
//! where S is the specular term times the cosine: Phong (r.v)^n, Blinn-Phong (n.h)^n,
//! cosine lobe (n+2)/(2 pi) (r.v)^n (n.l); Lambert has none. The lamp intensity I is
//! absorbed into kd and ks (they are known up to one common factor). Dot products are
//! clamped at 0.

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

/// The models.
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

    pub fn name(&self) -> &'static str {
        match self {
            Model::Lambert => "lambert",
            Model::Phong => "phong",
            Model::BlinnPhong => "blinn-phong",
            Model::CosineLobe => "cosine-lobe",
        }
    }

    /// Whether the model has a specular lobe (ks and n).
    pub fn has_lobe(&self) -> bool {
        *self != Model::Lambert
    }

    /// The diffuse basis a = (n.l) / D^2.
    pub fn diffuse(g: &Geometry) -> f64 {
        g.cos_l / g.d2
    }

    /// The specular basis b(n) and its derivative by ln n, d b / d ln n = n db/dn.
    pub fn specular(&self, g: &Geometry, n: f64) -> (f64, f64) {
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

    /// Predicted radiance of one channel.
    pub fn radiance(&self, g: &Geometry, kd: f64, ks: f64, n: f64) -> f64 {
        kd * Model::diffuse(g) + ks * self.specular(g, n).0
    }
}
