//! The validation renderer (paper section 4): the camera's view of the tile and the grid
//! floor under the point lamp, in radiance, for a fitted reflectance model.
//!
//! Every pixel's ray is found from the calibrated camera exactly as the fitter's geometry
//! does ([`Scene::on_plane`]): it meets the tile's top face, or else the floor z = 0, where
//! it lands on a light or dark chessboard square or on the board's surround. Pixels whose
//! four corners see different surfaces (a square's edge, the tile's outline) are
//! supersampled 4x4; every other pixel takes one ray through its centre. What each pixel
//! sees is worked out once ([`View`]); rendering a model is then a pass of arithmetic.
//!
//! The floor is Lambertian. Its three albedos (dark squares, light squares, surround; per
//! channel, in the radiance's units, lamp intensity included) are not known from the rig,
//! so [`View::floor_albedo`] measures them from the merged radiance: the median of
//! radiance / ((n.l) / D^2) over the pixels that see each surface. The tile casts no
//! shadow and its sides are not drawn (the comparison is over the tile's top face only).

use rayon::prelude::*;

use crate::fit::geometry::Scene;
use crate::fit::model::{diffuse, Geometry, Model, Reflectance};
use crate::hdr::merge::MASK_OK;

/// What a ray meets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    /// Nothing (above the horizon, or behind the camera).
    Nothing,
    /// The floor beyond the chessboard.
    Surround,
    /// A chessboard square, dark or light.
    Square { dark: bool },
    /// The tile's top face.
    Tile,
}

impl Surface {
    /// Index into [`FloorAlbedo`] for floor surfaces.
    fn floor_index(self) -> Option<usize> {
        match self {
            Surface::Square { dark: true } => Some(0),
            Surface::Square { dark: false } => Some(1),
            Surface::Surround => Some(2),
            _ => None,
        }
    }
}

/// One ray's hit: the surface and its geometry there.
#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub surface: Surface,
    pub geometry: Geometry,
}

const NO_HIT: Hit = Hit {
    surface: Surface::Nothing,
    geometry: Geometry {
        cos_l: 0.0,
        r_dot_v: 0.0,
        n_dot_h: 0.0,
        d2: 1.0,
        cos_v: 0.0,
        v_dot_h: 0.0,
    },
};

/// Lambertian albedo of the floor, per channel, in radiance units: radiance = albedo x
/// (n.l) / D^2. Rows: dark squares, light squares, surround. NaN where not measured.
pub type FloorAlbedo = [[f64; 3]; 3];

/// The chessboard on the floor (docs/design.md: the square on the +x, +y side of the origin
/// corner is dark; one square beyond the outermost inner corners on every side).
#[derive(Debug, Clone, Copy)]
pub struct Board {
    pub inner_corners: [u32; 2],
    pub square_mm: f64,
}

/// Supersampling per axis at pixels whose corners see different surfaces.
const EDGE_SAMPLES: usize = 4;

/// A fitted model's parameters, in the radiance's units (n is NaN for Lambert).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Shading {
    pub model: Model,
    pub kd: [f64; 3],
    pub ks: [f64; 3],
    pub n: f64,
}

impl Shading {
    /// Radiance of channel `c` of the tile at geometry `g`.
    pub fn tile(&self, g: &Geometry, c: usize) -> f64 {
        let ks = if self.model.has_lobe() {
            self.ks[c]
        } else {
            0.0
        };
        self.model.radiance(g, self.kd[c], ks, self.n)
    }
}

/// What every pixel of the camera sees.
pub struct View {
    pub width: usize,
    pub height: usize,
    /// The surface at each pixel corner: corner (i, j), at (i - 0.5, j - 0.5), is
    /// `corners[j * (width + 1) + i]`.
    corners: Vec<Surface>,
    /// The centre ray's hit per pixel.
    centre: Vec<Hit>,
    /// Pixels whose corners see different surfaces, with their 4x4 subsample hits.
    edges: Vec<(usize, Vec<Hit>)>,
}

/// One camera's rays against the tile's top face and the floor: each pixel position is
/// undistorted once, and the ray met with both planes (as [`Scene::on_plane`] does for
/// each, with the same arithmetic).
struct Tracer<'a> {
    tile: &'a Scene,
    board: Board,
    /// Rotation of the pose (rows: camera axes in grid coordinates).
    r: nalgebra::Matrix3<f64>,
}

impl Tracer<'_> {
    /// The ray's direction in grid coordinates, if it points down towards the planes.
    fn ray(&self, u: f64, v: f64) -> Option<nalgebra::Vector3<f64>> {
        let [x, y] = self.tile.intrinsics.undistort(u, v)?;
        let d = self.r.transpose() * nalgebra::Vector3::new(x, y, 1.0);
        (d.z < 0.0).then_some(d)
    }

    /// Where the ray `d` meets the plane z = `height`.
    fn on_plane(&self, d: &nalgebra::Vector3<f64>, height: f64) -> Option<[f64; 3]> {
        let c = self.tile.centre;
        let s = (height - c[2]) / d.z;
        (s > 0.0).then(|| [c[0] + s * d.x, c[1] + s * d.y, height])
    }

    /// What the ray through (u, v) meets, and where.
    fn point(&self, u: f64, v: f64) -> Option<(Surface, [f64; 3])> {
        let d = self.ray(u, v)?;
        if let Some(p) = self.on_plane(&d, self.tile.height) {
            if self.tile.inside(p[0], p[1]) {
                return Some((Surface::Tile, p));
            }
        }
        let p = self.on_plane(&d, 0.0)?;
        Some((self.board.surface(p[0], p[1]), p))
    }

    fn surface(&self, u: f64, v: f64) -> Surface {
        self.point(u, v).map_or(Surface::Nothing, |(s, _)| s)
    }

    fn hit(&self, u: f64, v: f64) -> Hit {
        // The geometry does not depend on the plane's height: the floor's is the tile's
        // formula at a floor point.
        self.point(u, v).map_or(NO_HIT, |(surface, p)| Hit {
            surface,
            geometry: self.tile.geometry(p),
        })
    }
}

impl View {
    /// Trace every pixel of `tile`'s camera (the tile scene of the fitter; the floor is the
    /// same camera's plane z = 0).
    pub fn new(tile: &Scene, board: Board) -> Self {
        let (w, h) = (tile.width, tile.image_height);
        let tracer = Tracer {
            tile,
            board,
            r: crate::calib::camera::rotation(tile.pose.rvec),
        };
        // Surfaces at pixel corners: corner (i, j) sits at (i - 0.5, j - 0.5).
        let corners: Vec<Surface> = (0..(w + 1) * (h + 1))
            .into_par_iter()
            .map(|k| {
                let (i, j) = (k % (w + 1), k / (w + 1));
                tracer.surface(i as f64 - 0.5, j as f64 - 0.5)
            })
            .collect();
        let centre: Vec<Hit> = (0..w * h)
            .into_par_iter()
            .map(|k| tracer.hit((k % w) as f64, (k / w) as f64))
            .collect();
        let edges: Vec<(usize, Vec<Hit>)> = (0..w * h)
            .into_par_iter()
            .filter_map(|k| {
                let (i, j) = (k % w, k / w);
                let c = [
                    corners[j * (w + 1) + i],
                    corners[j * (w + 1) + i + 1],
                    corners[(j + 1) * (w + 1) + i],
                    corners[(j + 1) * (w + 1) + i + 1],
                ];
                if c.iter().all(|s| *s == c[0]) && centre[k].surface == c[0] {
                    return None;
                }
                let n = EDGE_SAMPLES;
                let hits = (0..n * n)
                    .map(|s| {
                        let du = ((s % n) as f64 + 0.5) / n as f64 - 0.5;
                        let dv = ((s / n) as f64 + 0.5) / n as f64 - 0.5;
                        tracer.hit(i as f64 + du, j as f64 + dv)
                    })
                    .collect();
                Some((k, hits))
            })
            .collect();
        View {
            width: w,
            height: h,
            corners,
            centre,
            edges,
        }
    }

    /// The pixels (y * width + x) that see only tile with a pixel to spare on every side:
    /// [`Scene::sees_tile`] with a margin of 1 (the fitter's tile map, and so the pixels it
    /// may sample), read from the traced corners and centres; `tile` must be the scene the
    /// view was traced from (it is asked directly at the image's border only).
    pub fn tile_pixels(&self, tile: &Scene) -> Vec<bool> {
        let (w, h) = (self.width, self.height);
        let cw = w + 1;
        (0..w * h)
            .into_par_iter()
            .map(|k| {
                let (u, v) = (k % w, k / w);
                // The footprint grown by 1: (u ± 1.5, v ± 1.5), the corners (u - 1, v - 1)
                // and (u + 2, v + 2) of the corner grid.
                if u == 0 || v == 0 || u + 2 > w || v + 2 > h {
                    return tile.sees_tile(u as f64, v as f64, 1.0);
                }
                self.centre[k].surface == Surface::Tile
                    && [
                        (v - 1) * cw + u - 1,
                        (v - 1) * cw + u + 2,
                        (v + 2) * cw + u - 1,
                        (v + 2) * cw + u + 2,
                    ]
                    .iter()
                    .all(|&c| self.corners[c] == Surface::Tile)
            })
            .collect()
    }

    /// The surface pixel `k` (y * width + x) sees through its centre.
    pub fn surface(&self, k: usize) -> Surface {
        self.centre[k].surface
    }

    /// Whether pixel `k` sees one surface over its whole footprint.
    pub fn uniform(&self, k: usize) -> bool {
        self.edges.binary_search_by_key(&k, |e| e.0).is_err()
    }

    /// The floor's albedos measured from merged radiance (RGB interleaved, or one sample a
    /// pixel for a monochrome camera, whose one albedo is then in all three places; with
    /// its mask): per surface and channel, the median of radiance / ((n.l) / D^2) over the
    /// pixels that see only that surface and were measured.
    pub fn floor_albedo(&self, radiance: &[f32], mask: &[u8]) -> FloorAlbedo {
        let nc = if radiance.len() == self.width * self.height {
            1
        } else {
            3
        };
        let mut ratios: [[Vec<f64>; 3]; 3] = Default::default();
        for (k, hit) in self.centre.iter().enumerate() {
            let Some(s) = hit.surface.floor_index() else {
                continue;
            };
            let a = diffuse(&hit.geometry);
            if a <= 0.0 || !self.uniform(k) {
                continue;
            }
            for (c, r) in ratios[s].iter_mut().enumerate().take(nc) {
                if mask[nc * k + c] == MASK_OK && radiance[nc * k + c].is_finite() {
                    r.push(radiance[nc * k + c] as f64 / a);
                }
            }
        }
        ratios.map(|per| {
            let m = per.map(|mut v| {
                if v.is_empty() {
                    return f64::NAN;
                }
                let m = v.len() / 2;
                *v.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
            });
            if nc == 1 {
                [m[0]; 3]
            } else {
                m
            }
        })
    }

    /// Render the scene: the tile with `shading`, the floor with `floor` (NaN albedos
    /// render as 0). RGB interleaved, in the radiance's units.
    pub fn render(&self, shading: &Shading, floor: &FloorAlbedo) -> Vec<f32> {
        self.render_channels(shading, floor, 3)
    }

    /// [`View::render`] with `channels` samples a pixel: 3 (RGB interleaved) or 1 (a
    /// monochrome camera's: the shading's and the floor's first channel).
    pub fn render_channels(
        &self,
        shading: &Shading,
        floor: &FloorAlbedo,
        channels: usize,
    ) -> Vec<f32> {
        let nc = channels;
        let radiance = |h: &Hit, c: usize| -> f64 {
            match h.surface {
                Surface::Nothing => 0.0,
                Surface::Tile => shading.tile(&h.geometry, c),
                s => {
                    let a = floor[s.floor_index().expect("a floor surface")][c];
                    if a.is_finite() {
                        a * diffuse(&h.geometry)
                    } else {
                        0.0
                    }
                }
            }
        };
        let mut out = vec![0f32; self.width * self.height * nc];
        out.par_chunks_mut(nc)
            .zip(self.centre.par_iter())
            .for_each(|(o, h)| {
                for (c, v) in o.iter_mut().enumerate() {
                    *v = radiance(h, c) as f32;
                }
            });
        for (k, hits) in &self.edges {
            for c in 0..nc {
                let s: f64 = hits.iter().map(|h| radiance(h, c)).sum();
                out[nc * k + c] = (s / hits.len() as f64) as f32;
            }
        }
        out
    }
}

impl Board {
    /// The floor surface at grid point (x, y).
    pub fn surface(&self, x: f64, y: f64) -> Surface {
        let i = (x / self.square_mm).floor();
        let j = (y / self.square_mm).floor();
        let [nx, ny] = self.inner_corners;
        if i < -1.0 || j < -1.0 || i > nx as f64 - 1.0 || j > ny as f64 - 1.0 {
            return Surface::Surround;
        }
        Surface::Square {
            dark: (i as i64 + j as i64).rem_euclid(2) == 0,
        }
    }
}
