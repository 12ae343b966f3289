//! Per-pixel geometry (paper section 3.3): from the calibrated camera and the rig's lamp and
//! tile, the point on the tile each pixel sees and its light, view and normal directions.
//!
//! A pixel's ray is found by inverting the lens distortion exactly
//! ([`Intrinsics::undistort`]), turned into the grid frame with the calibrated pose, and
//! intersected with the tile's top face z = `tile_thickness_mm` (normal (0, 0, 1)).

use nalgebra::{Matrix3, Vector3};

use super::model::Geometry;
use crate::calib::camera::{project, rotation, Intrinsics, Pose};

type V3 = [f64; 3];

/// The calibrated camera, the lamp and the tile.
#[derive(Debug, Clone)]
pub struct Scene {
    pub intrinsics: Intrinsics,
    pub pose: Pose,
    /// Rotation of the pose (rows: camera axes in grid coordinates).
    r: Matrix3<f64>,
    /// Camera centre in grid coordinates, mm.
    pub centre: V3,
    pub lamp: V3,
    /// Height of the tile's top face, mm.
    pub height: f64,
    /// The tile's outline in grid (x, y), mm.
    pub outline: Vec<[f64; 2]>,
    pub width: usize,
    pub image_height: usize,
}

impl Scene {
    pub fn new(
        intrinsics: Intrinsics,
        pose: Pose,
        lamp: V3,
        height: f64,
        outline: Vec<[f64; 2]>,
        size: [usize; 2],
    ) -> Self {
        let r = rotation(pose.rvec);
        let c = -(r.transpose() * Vector3::from(pose.t));
        Scene {
            intrinsics,
            pose,
            r,
            centre: [c.x, c.y, c.z],
            lamp,
            height,
            outline,
            width: size[0],
            image_height: size[1],
        }
    }

    /// The same lamp and tile seen by another camera.
    pub fn with_camera(&self, intrinsics: Intrinsics, pose: Pose) -> Self {
        Scene::new(
            intrinsics,
            pose,
            self.lamp,
            self.height,
            self.outline.clone(),
            [self.width, self.image_height],
        )
    }

    /// The point of the tile plane (not necessarily on the tile) seen at pixel (u, v).
    pub fn on_plane(&self, u: f64, v: f64) -> Option<V3> {
        let [x, y] = self.intrinsics.undistort(u, v)?;
        let d = self.r.transpose() * Vector3::new(x, y, 1.0);
        if d.z >= 0.0 {
            return None;
        }
        let s = (self.height - self.centre[2]) / d.z;
        (s > 0.0).then(|| {
            [
                self.centre[0] + s * d.x,
                self.centre[1] + s * d.y,
                self.height,
            ]
        })
    }

    /// Whether the tile point (x, y) lies inside the outline.
    pub fn inside(&self, x: f64, y: f64) -> bool {
        let poly = &self.outline;
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

    /// Whether pixel (u, v) sees only tile, with `margin` pixels to spare on every side
    /// (its footprint grown by the margin lies wholly inside the outline): no pixel that
    /// mixes the tile with its surround, and room for a small calibration error.
    pub fn sees_tile(&self, u: f64, v: f64, margin: f64) -> bool {
        let h = 0.5 + margin;
        [(-h, -h), (h, -h), (-h, h), (h, h), (0.0, 0.0)]
            .iter()
            .all(|&(du, dv)| {
                self.on_plane(u + du, v + dv)
                    .is_some_and(|p| self.inside(p[0], p[1]))
            })
    }

    /// The geometry of the tile point `p`.
    pub fn geometry(&self, p: V3) -> Geometry {
        Geometry::at(p, [0.0, 0.0, 1.0], self.lamp, self.centre)
    }

    /// The geometry at pixel (u, v), if it sees the tile plane.
    pub fn geometry_at(&self, u: f64, v: f64) -> Option<Geometry> {
        self.on_plane(u, v).map(|p| self.geometry(p))
    }

    /// Pixel coordinates of a grid point.
    pub fn project(&self, p: V3) -> [f64; 2] {
        project(&self.intrinsics, &self.pose, p, None).uv
    }

    /// The mirror point: where the lamp's reflection in the tile plane is seen, i.e. where
    /// a perfect mirror would show the highlight (r = v there).
    pub fn mirror_point(&self) -> V3 {
        let h = self.height;
        // The lamp's image below the plane, and the line from it to the camera.
        let img = [self.lamp[0], self.lamp[1], 2.0 * h - self.lamp[2]];
        let c = self.centre;
        let s = (h - c[2]) / (img[2] - c[2]);
        [c[0] + s * (img[0] - c[0]), c[1] + s * (img[1] - c[1]), h]
    }

    /// Unit direction in the tile plane of the plane of incidence at the mirror point (from
    /// the lamp's foot towards the camera's foot); falls back to x when both stand over
    /// the same point.
    pub fn incidence_direction(&self) -> [f64; 2] {
        let d = [self.centre[0] - self.lamp[0], self.centre[1] - self.lamp[1]];
        let n = (d[0] * d[0] + d[1] * d[1]).sqrt();
        if n < 1e-9 {
            [1.0, 0.0]
        } else {
            [d[0] / n, d[1] / n]
        }
    }
}
