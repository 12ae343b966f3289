//! The lab's optics: a pinhole camera with radial distortion looking at the grid floor,
//! with or without the tile on it, lit by a point lamp.
//!
//! The radiance each pixel sees at full lamp output is computed once per scene
//! ([`render_radiance`]): frames then only need the sensor model, so they are cheap.
//! Pixels whose footprint straddles an edge (a chessboard square, the tile outline) are
//! supersampled so corner positions are sub-pixel exact; every other pixel takes one ray
//! through its centre. This is the simulator's own forward model, written apart from
//! Glint's fitter on purpose: shared formulas would hide shared bugs.

use crate::config::{GridAlbedo, Reflectance, TrueCamera, TrueTile};

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
fn unit(a: V3) -> V3 {
    let n = norm(a);
    [a[0] / n, a[1] / n, a[2] / n]
}

/// Geometry shared with the rig file (grid coordinates, millimetres).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneGeometry {
    pub lamp_position_mm: V3,
    pub tile_thickness_mm: f64,
    /// Polygon of the tile's top face in grid (x, y), in order.
    pub tile_outline_mm: Vec<[f64; 2]>,
    /// Inner corners of the chessboard along x and y.
    pub grid_inner_corners: [u32; 2],
    pub grid_square_mm: f64,
    /// A diffuse reflectance standard beside the tile (placed and removed with it), if the
    /// rig has one.
    pub reference: Option<ReferenceTarget>,
}

/// A Lambertian reflectance standard: a block whose top face (`outline_mm` at height
/// `thickness_mm`) has albedo `albedo` per channel (the lab's truth; its sides are not
/// rendered, as the tile's are not).
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceTarget {
    pub outline_mm: Vec<[f64; 2]>,
    pub thickness_mm: f64,
    pub albedo: [f64; 3],
}

/// Which scene the camera sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SceneKind {
    /// The chessboard alone (the tile removed), for calibration.
    Grid,
    /// The tile resting on the grid.
    Tile,
    /// The chessboard lifted off the floor and held in a rigid pose (the tile removed),
    /// for the lens calibration; the floor beneath is bare.
    Board(BoardPose),
}

/// A pose of the chessboard, held by the lab's operator: the board is lifted by `lift`
/// and turned about its own centre, first by `tilt_x` about the grid's x axis, then by
/// `tilt_y` about y, then by `rotate` about z: a board point p (grid coordinates, z = 0)
/// is at R (p - c) + c + (0, 0, lift), c the board's centre, R = Rz Ry Rx. Angles in
/// millidegrees and the lift in micrometres, so that a pose is an exact key.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct BoardPose {
    pub tilt_x_mdeg: i32,
    pub tilt_y_mdeg: i32,
    pub rotate_mdeg: i32,
    pub lift_um: i32,
}

impl BoardPose {
    /// From degrees and millimetres (rounded to the key's units).
    pub fn new(tilt_x_deg: f64, tilt_y_deg: f64, rotate_deg: f64, lift_mm: f64) -> Self {
        let r = |x: f64| (x * 1000.0).round().clamp(-1e9, 1e9) as i32;
        BoardPose {
            tilt_x_mdeg: r(tilt_x_deg),
            tilt_y_mdeg: r(tilt_y_deg),
            rotate_mdeg: r(rotate_deg),
            lift_um: r(lift_mm),
        }
    }

    /// The rotation R = Rz Ry Rx (rows).
    pub fn rotation(&self) -> [V3; 3] {
        let a = (self.tilt_x_mdeg as f64 / 1000.0).to_radians();
        let b = (self.tilt_y_mdeg as f64 / 1000.0).to_radians();
        let g = (self.rotate_mdeg as f64 / 1000.0).to_radians();
        let rx = [
            [1.0, 0.0, 0.0],
            [0.0, a.cos(), -a.sin()],
            [0.0, a.sin(), a.cos()],
        ];
        let ry = [
            [b.cos(), 0.0, b.sin()],
            [0.0, 1.0, 0.0],
            [-b.sin(), 0.0, b.cos()],
        ];
        let rz = [
            [g.cos(), -g.sin(), 0.0],
            [g.sin(), g.cos(), 0.0],
            [0.0, 0.0, 1.0],
        ];
        mul(rz, mul(ry, rx))
    }

    /// The board's centre (grid coordinates, on the floor) for a grid.
    pub fn centre(g: &SceneGeometry) -> V3 {
        let [nx, ny] = g.grid_inner_corners;
        [
            (nx as f64 - 1.0) / 2.0 * g.grid_square_mm,
            (ny as f64 - 1.0) / 2.0 * g.grid_square_mm,
            0.0,
        ]
    }

    /// Where board point `p` (grid coordinates of the board lying flat) is in this pose.
    pub fn place(&self, g: &SceneGeometry, p: V3) -> V3 {
        let r = self.rotation();
        let c = Self::centre(g);
        let d = sub(p, c);
        let q = [dot(r[0], d), dot(r[1], d), dot(r[2], d)];
        [
            q[0] + c[0],
            q[1] + c[1],
            q[2] + c[2] + self.lift_um as f64 / 1000.0,
        ]
    }
}

fn mul(a: [V3; 3], b: [V3; 3]) -> [V3; 3] {
    let mut o = [[0.0; 3]; 3];
    for (i, row) in o.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    o
}

/// A posed pinhole camera with radial distortion (docs/design.md conventions).
#[derive(Debug, Clone)]
pub struct PosedCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    /// Rows are the camera's x (right), y (down), z (forward) axes in grid coordinates.
    pub r: [V3; 3],
    /// Camera centre in grid coordinates.
    pub centre: V3,
}

impl PosedCamera {
    /// Build from the configured truth for an image of `width` x `height`.
    pub fn new(c: &TrueCamera, width: u32, height: u32) -> Self {
        let fwd = unit(sub(c.look_at_mm, c.position_mm));
        let right0 = unit(cross(fwd, [0.0, 0.0, 1.0]));
        let down0 = cross(fwd, right0);
        let (s, co) = c.roll_deg.to_radians().sin_cos();
        let right = [
            co * right0[0] + s * down0[0],
            co * right0[1] + s * down0[1],
            co * right0[2] + s * down0[2],
        ];
        let down = cross(fwd, right);
        PosedCamera {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx.unwrap_or((width as f64 - 1.0) / 2.0),
            cy: c.cy.unwrap_or((height as f64 - 1.0) / 2.0),
            k1: c.k1,
            k2: c.k2,
            r: [right, down, fwd],
            centre: c.position_mm,
        }
    }

    /// Rotation R and translation t with X_cam = R X_world + t.
    pub fn extrinsics(&self) -> ([V3; 3], V3) {
        let rc = [
            dot(self.r[0], self.centre),
            dot(self.r[1], self.centre),
            dot(self.r[2], self.centre),
        ];
        (self.r, [-rc[0], -rc[1], -rc[2]])
    }

    /// Project a grid point to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: V3) -> Option<[f64; 2]> {
        let d = sub(p, self.centre);
        let (x, y, z) = (dot(self.r[0], d), dot(self.r[1], d), dot(self.r[2], d));
        if z <= 0.0 {
            return None;
        }
        let (x, y) = (x / z, y / z);
        let r2 = x * x + y * y;
        let k = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        Some([self.fx * k * x + self.cx, self.fy * k * y + self.cy])
    }

    /// Unit ray direction (grid coordinates) through pixel (u, v), undistorting by
    /// fixed-point iteration.
    pub fn ray(&self, u: f64, v: f64) -> V3 {
        let xd = (u - self.cx) / self.fx;
        let yd = (v - self.cy) / self.fy;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let k = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
            let (nx, ny) = (xd / k, yd / k);
            let done = (nx - x).abs() + (ny - y).abs() < 1e-13;
            x = nx;
            y = ny;
            if done {
                break;
            }
        }
        let r = &self.r;
        unit([
            r[0][0] * x + r[1][0] * y + r[2][0],
            r[0][1] * x + r[1][1] * y + r[2][1],
            r[0][2] * x + r[1][2] * y + r[2][2],
        ])
    }
}

/// What a ray hits; pixels whose corners hit different materials are supersampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Material {
    Sky,
    Surround,
    Square(bool),
    Tile,
    /// The reflectance standard's top face.
    Reference,
    /// The bare floor under a lifted board.
    Floor,
    /// A square of the lifted board (dark or not), its margin (the surround's albedo, as
    /// around the board on the floor), or its back.
    BoardSquare(bool),
    BoardMargin,
    BoardBack,
}

/// The lit world: geometry, reflectances and the lamp.
pub struct World<'a> {
    pub geometry: &'a SceneGeometry,
    pub tile: &'a TrueTile,
    pub albedo: &'a GridAlbedo,
    pub intensity: f64,
    pub kind: SceneKind,
}

impl World<'_> {
    fn hit(&self, origin: V3, dir: V3) -> (Material, V3) {
        let g = self.geometry;
        if let SceneKind::Board(pose) = self.kind {
            return self.hit_board(&pose, origin, dir);
        }
        if self.kind == SceneKind::Tile && dir[2] < 0.0 {
            // The tile's top face and the reference's: the nearer one hit.
            let face = |height: f64, outline: &[[f64; 2]], m: Material| {
                let s = (height - origin[2]) / dir[2];
                let p = [origin[0] + s * dir[0], origin[1] + s * dir[1], height];
                (s > 0.0 && inside(outline, p[0], p[1])).then_some((s, m, p))
            };
            let tile = face(g.tile_thickness_mm, &g.tile_outline_mm, Material::Tile);
            let reference = g
                .reference
                .as_ref()
                .and_then(|r| face(r.thickness_mm, &r.outline_mm, Material::Reference));
            let nearer = match (tile, reference) {
                (Some(a), Some(b)) => Some(if a.0 <= b.0 { a } else { b }),
                (a, b) => a.or(b),
            };
            if let Some((_, m, p)) = nearer {
                return (m, p);
            }
        }
        if dir[2] >= 0.0 {
            return (Material::Sky, origin);
        }
        let s = -origin[2] / dir[2];
        let p = [origin[0] + s * dir[0], origin[1] + s * dir[1], 0.0];
        let sq = g.grid_square_mm;
        let i = (p[0] / sq).floor();
        let j = (p[1] / sq).floor();
        let [nx, ny] = g.grid_inner_corners;
        // The board has one square beyond the outermost inner corners on every side.
        if i < -1.0 || j < -1.0 || i > nx as f64 - 1.0 || j > ny as f64 - 1.0 {
            return (Material::Surround, p);
        }
        // The square on the +x, +y side of the origin corner, (0, 0), is dark.
        let dark = (i as i64 + j as i64).rem_euclid(2) == 0;
        (Material::Square(dark), p)
    }

    /// A ray against the lifted board (a plate with one square and a margin of half a
    /// square beyond the outermost inner corners) and the bare floor.
    fn hit_board(&self, pose: &BoardPose, origin: V3, dir: V3) -> (Material, V3) {
        let g = self.geometry;
        let r = pose.rotation();
        let n = [r[0][2], r[1][2], r[2][2]];
        let c0 = BoardPose::centre(g);
        let c = pose.place(g, c0);
        let dn = dot(dir, n);
        let floor = (dir[2] < 0.0).then(|| -origin[2] / dir[2]);
        let board = (dn.abs() > 1e-12)
            .then(|| dot(sub(c, origin), n) / dn)
            .filter(|s| *s > 0.0);
        if let Some(s) = board.filter(|s| floor.is_none_or(|f| *s <= f * (1.0 + 1e-9))) {
            let p = [
                origin[0] + s * dir[0],
                origin[1] + s * dir[1],
                origin[2] + s * dir[2],
            ];
            // Back into the board's own (flat) coordinates: q = R^T (p - c) + c0.
            let d = sub(p, c);
            let q = [
                r[0][0] * d[0] + r[1][0] * d[1] + r[2][0] * d[2] + c0[0],
                r[0][1] * d[0] + r[1][1] * d[1] + r[2][1] * d[2] + c0[1],
            ];
            let sq = g.grid_square_mm;
            let [nx, ny] = g.grid_inner_corners;
            let (i, j) = ((q[0] / sq).floor(), (q[1] / sq).floor());
            let on = |v: f64, k: u32| v >= -1.5 * sq && v <= (k as f64 + 0.5) * sq;
            if on(q[0], nx) && on(q[1], ny) {
                if dn > 0.0 {
                    return (Material::BoardBack, p);
                }
                if i < -1.0 || j < -1.0 || i > nx as f64 - 1.0 || j > ny as f64 - 1.0 {
                    return (Material::BoardMargin, p);
                }
                let dark = (i as i64 + j as i64).rem_euclid(2) == 0;
                return (Material::BoardSquare(dark), p);
            }
        }
        match floor {
            Some(s) => (
                Material::Floor,
                [origin[0] + s * dir[0], origin[1] + s * dir[1], 0.0],
            ),
            None => (Material::Sky, origin),
        }
    }

    /// Radiance leaving `p` (on material `m`) towards `eye`, per channel.
    fn radiance(&self, m: Material, p: V3, eye: V3) -> [f64; 3] {
        let to_lamp = sub(self.geometry.lamp_position_mm, p);
        let d2 = dot(to_lamp, to_lamp);
        let l = unit(to_lamp);
        if let (Material::BoardSquare(_) | Material::BoardMargin, SceneKind::Board(pose)) =
            (m, self.kind)
        {
            // The board's own normal: R z.
            let r = pose.rotation();
            let cos_l = dot(l, [r[0][2], r[1][2], r[2][2]]);
            if cos_l <= 0.0 {
                return [0.0; 3];
            }
            let a = match m {
                Material::BoardSquare(true) => self.albedo.dark,
                Material::BoardSquare(false) => self.albedo.light,
                _ => self.albedo.surround,
            };
            return [a / std::f64::consts::PI * cos_l * self.intensity / d2; 3];
        }
        let cos_l = l[2]; // n = (0, 0, 1) on the floor and the tile top
        if cos_l <= 0.0 {
            return [0.0; 3];
        }
        let e = self.intensity / d2;
        let lambert = |a: f64| a / std::f64::consts::PI * cos_l * e;
        match m {
            Material::Sky | Material::BoardBack => [0.0; 3],
            Material::Surround | Material::Floor => [lambert(self.albedo.surround); 3],
            Material::Reference => {
                let a = self
                    .geometry
                    .reference
                    .as_ref()
                    .map_or([0.0; 3], |r| r.albedo);
                [lambert(a[0]), lambert(a[1]), lambert(a[2])]
            }
            Material::BoardSquare(_) | Material::BoardMargin => [0.0; 3],
            Material::Square(dark) => {
                [lambert(if dark {
                    self.albedo.dark
                } else {
                    self.albedo.light
                }); 3]
            }
            Material::Tile => {
                let v = unit(sub(eye, p));
                let t = self.tile;
                // Reflected light vector r = 2 (n.l) n - l with n = z.
                let r = [-l[0], -l[1], l[2]];
                let rv = dot(r, v).max(0.0);
                let h = unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
                let nh = h[2].max(0.0);
                let mut out = [0.0; 3];
                for (c, o) in out.iter_mut().enumerate() {
                    // f_r * cos(n, l), with the cosine cancelled where the model divides by it.
                    let fr_cos = match t.model {
                        Reflectance::Lambert => t.kd[c] * cos_l,
                        Reflectance::Phong => t.kd[c] * cos_l + t.ks[c] * rv.powf(t.n),
                        Reflectance::BlinnPhong => t.kd[c] * cos_l + t.ks[c] * nh.powf(t.n),
                        Reflectance::CosineLobe => {
                            (t.kd[c]
                                + t.ks[c] * (t.n + 2.0) / (2.0 * std::f64::consts::PI)
                                    * rv.powf(t.n))
                                * cos_l
                        }
                        Reflectance::Ggx => {
                            // Cook-Torrance: D G F / (4 (n.l) (n.v)), times n.l.
                            let a2 = t.alpha.unwrap_or(0.2).powi(2);
                            let cos_v = v[2];
                            let lobe = if cos_v > 0.0 {
                                let den = nh * nh * (a2 - 1.0) + 1.0;
                                let d = a2 / (std::f64::consts::PI * den * den);
                                let g1 = |x: f64| 2.0 * x / (x + (a2 + (1.0 - a2) * x * x).sqrt());
                                let vh = dot(v, h).max(0.0);
                                let f = t.ks[c] + (1.0 - t.ks[c]) * (1.0 - vh).powi(5);
                                d * g1(cos_l) * g1(cos_v) * f / (4.0 * cos_v)
                            } else {
                                0.0
                            };
                            t.kd[c] * cos_l + lobe
                        }
                    };
                    *o = fr_cos * e;
                }
                out
            }
        }
    }
}

fn inside(poly: &[[f64; 2]], x: f64, y: f64) -> bool {
    let mut inside = false;
    let n = poly.len();
    for i in 0..n {
        let [xi, yi] = poly[i];
        let [xj, yj] = poly[(i + n - 1) % n];
        if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
            inside = !inside;
        }
    }
    inside
}

/// Supersampling factor per axis for edge pixels.
const SUPERSAMPLE: usize = 6;

/// Radiance (RGB, interleaved, f32) each pixel receives at full lamp output.
pub fn render_radiance(cam: &PosedCamera, world: &World, width: u32, height: u32) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    // Materials at pixel corners: corner (i, j) sits at (i - 0.5, j - 0.5).
    let mut corners = vec![Material::Sky; (w + 1) * (h + 1)];
    for j in 0..=h {
        for i in 0..=w {
            let d = cam.ray(i as f64 - 0.5, j as f64 - 0.5);
            corners[j * (w + 1) + i] = world.hit(cam.centre, d).0;
        }
    }
    let mut out = vec![0f32; w * h * 3];
    for j in 0..h {
        for i in 0..w {
            let c = [
                corners[j * (w + 1) + i],
                corners[j * (w + 1) + i + 1],
                corners[(j + 1) * (w + 1) + i],
                corners[(j + 1) * (w + 1) + i + 1],
            ];
            let uniform = c.iter().all(|m| *m == c[0]);
            let mut acc = [0.0f64; 3];
            let n = if uniform { 1 } else { SUPERSAMPLE };
            for sj in 0..n {
                for si in 0..n {
                    let (du, dv) = if n == 1 {
                        (0.0, 0.0)
                    } else {
                        (
                            (si as f64 + 0.5) / n as f64 - 0.5,
                            (sj as f64 + 0.5) / n as f64 - 0.5,
                        )
                    };
                    let d = cam.ray(i as f64 + du, j as f64 + dv);
                    let (m, p) = world.hit(cam.centre, d);
                    let l = world.radiance(m, p, cam.centre);
                    for k in 0..3 {
                        acc[k] += l[k];
                    }
                }
            }
            let s = 1.0 / (n * n) as f64;
            let o = &mut out[(j * w + i) * 3..(j * w + i) * 3 + 3];
            for k in 0..3 {
                o[k] = (acc[k] * s) as f32;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> PosedCamera {
        PosedCamera::new(&TrueCamera::default(), 640, 480)
    }

    #[test]
    fn ray_and_project_are_inverse() {
        let c = cam();
        for &(u, v) in &[(0.0, 0.0), (320.0, 240.0), (639.0, 479.0), (100.5, 400.25)] {
            let d = c.ray(u, v);
            let p = [
                c.centre[0] + 300.0 * d[0],
                c.centre[1] + 300.0 * d[1],
                c.centre[2] + 300.0 * d[2],
            ];
            let q = c.project(p).unwrap();
            assert!(
                (q[0] - u).abs() < 1e-7 && (q[1] - v).abs() < 1e-7,
                "{u},{v} -> {q:?}"
            );
        }
    }

    #[test]
    fn look_at_point_projects_to_principal_point() {
        let c = cam();
        let q = c.project(TrueCamera::default().look_at_mm).unwrap();
        assert!((q[0] - c.cx).abs() < 1e-9 && (q[1] - c.cy).abs() < 1e-9);
    }

    #[test]
    fn grid_axes_in_the_default_view_x_right_y_up_the_image() {
        // Camera at negative y looking towards +y: grid +y recedes, i.e. goes up the image.
        let c = cam();
        let a = c.project([0.0, 0.0, 0.0]).unwrap();
        let b = c.project([0.0, 100.0, 0.0]).unwrap();
        assert!(b[1] < a[1]);
        let x = c.project([100.0, 0.0, 0.0]).unwrap();
        assert!(x[0] > a[0]);
    }

    #[test]
    fn point_in_polygon() {
        let sq = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]];
        assert!(inside(&sq, 5.0, 5.0));
        assert!(!inside(&sq, 15.0, 5.0));
        assert!(!inside(&sq, -0.1, 5.0));
    }
}
