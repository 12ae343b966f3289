//! A sketch of the rig's geometry for the report (`report/rig.svg`): the grid, the tile,
//! the reference standard, the camera and the lamp, and the highlight's mirror point, seen
//! from above and from the side, to scale. It is drawn from the session's rig (what the
//! operator measured) and the calibration (where the camera really is), so that a lamp
//! position typed wrong, a camera that looks past the tile or a mirror point off the tile
//! shows at a glance.

use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::fit::model::{dot, sub, unit};
use crate::rig::{Geometry, ReferenceSection};

/// What the sketch shows. Coordinates are the grid's, in mm (docs/design.md).
#[derive(Debug, Clone)]
pub struct RigSketch<'a> {
    pub geometry: &'a Geometry,
    pub reference: Option<&'a ReferenceSection>,
    /// The calibrated camera's centre.
    pub camera: [f64; 3],
    /// The camera's optical axis (unit, pointing into the scene), where known.
    pub axis: Option<[f64; 3]>,
    /// Where the fit refined the camera with the highlight, where it did.
    pub refined: Option<[f64; 3]>,
}

/// Why the sketch cannot be drawn.
#[derive(Debug, thiserror::Error)]
pub enum SketchError {
    #[error("a coordinate of the rig or the camera is not a number of mm Glint can draw")]
    NotDrawable,
    #[error("the rig's grid or tile outline is empty")]
    Empty,
    #[error("a grid of {nx} x {ny} inner corners of {square_mm} mm is not drawn")]
    GridTooLarge { nx: u32, ny: u32, square_mm: f64 },
    #[error("the camera or the lamp is not above the tile")]
    NotAbove,
    #[error(transparent)]
    Draw(#[from] crate::hdr::files::PlotError),
}

/// A plotters call, its value dropped (its error becomes a [`SketchError`] by `?`).
macro_rules! d {
    ($x:expr) => {
        $x.map(|_| ())
    };
}

/// A text beside a point (x, y), 9 pixels to its right, or to its left where the point
/// lies in the right third of the x range `xr` (so that the text stays inside the chart).
macro_rules! label {
    ($xr:expr, $p:expr, $t:expr, $col:expr $(,)?) => {{
        let (xr, (x, y), col): ((f64, f64), (f64, f64), RGBColor) = ($xr, $p, $col);
        let right = x > xr.0 + 0.66 * (xr.1 - xr.0);
        let pos = Pos::new(if right { HPos::Right } else { HPos::Left }, VPos::Center);
        let style = ("sans-serif", 13).into_font().color(&col).pos(pos);
        EmptyElement::at((x, y))
            + Text::new(
                {
                    let t: String = $t;
                    t
                },
                (if right { -9 } else { 9 }, 0),
                style,
            )
    }};
}

/// Largest coordinate (mm) the sketch draws: beyond it the numbers are not a lab's.
const MAX_MM: f64 = 1e6;

/// The point of the plane z = `height` where light from `lamp` is mirrored into `camera`
/// (None when either is not above the plane).
pub fn mirror_point(camera: [f64; 3], lamp: [f64; 3], height: f64) -> Option<[f64; 3]> {
    let (a, b) = (camera[2] - height, lamp[2] - height);
    if !(a > 0.0 && b > 0.0) {
        return None;
    }
    // Along the line from the lamp to the camera's mirror image below the plane.
    let s = b / (a + b);
    Some([
        lamp[0] + s * (camera[0] - lamp[0]),
        lamp[1] + s * (camera[1] - lamp[1]),
        height,
    ])
}

/// The angle (degrees) between the tile's normal and the direction from `p` to `q`.
fn from_normal_deg(p: [f64; 3], q: [f64; 3]) -> f64 {
    unit(sub(q, p))[2].clamp(-1.0, 1.0).acos().to_degrees()
}

/// The distance between two points.
fn distance(p: [f64; 3], q: [f64; 3]) -> f64 {
    let d = sub(q, p);
    dot(d, d).sqrt()
}

/// A range holding every value, padded by a tenth, widened about its middle to at least
/// `min_span`.
fn span(values: impl Iterator<Item = f64>, min_span: f64) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    let pad = 0.1 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let mid = 0.5 * (lo + hi);
    let half = (0.5 * (hi - lo)).max(0.5 * min_span);
    (mid - half, mid + half)
}

/// Ranges (x, y) holding the given ones with the same mm per pixel on both axes of a
/// `w` x `h` pixel plotting area.
fn equal_aspect(x: (f64, f64), y: (f64, f64), w: f64, h: f64) -> ((f64, f64), (f64, f64)) {
    let (sx, sy) = ((x.1 - x.0) / w, (y.1 - y.0) / h);
    let s = sx.max(sy);
    let grow = |r: (f64, f64), px: f64| {
        let mid = 0.5 * (r.0 + r.1);
        (mid - 0.5 * s * px, mid + 0.5 * s * px)
    };
    (grow(x, w), grow(y, h))
}

/// What both views draw: the sketch's numbers, checked, and what follows from them.
struct Scene<'a> {
    s: &'a RigSketch<'a>,
    cam: [f64; 3],
    lamp: [f64; 3],
    /// Where the highlight must be, on the tile's top face.
    mirror: [f64; 3],
    on_tile: bool,
    /// The board: its squares reach one square beyond the inner corners.
    board: [(f64, f64); 4],
    /// Where the optical axis meets the grid (when it points down to it).
    axis_hit: Option<[f64; 3]>,
    /// The side view's horizontal axis: along the plane of incidence, from the camera's
    /// foot towards the lamp's.
    dir: [f64; 2],
}

impl Scene<'_> {
    /// A point's place along the side view's axis, 0 at the mirror point.
    fn along(&self, p: [f64; 2]) -> f64 {
        (p[0] - self.mirror[0]) * self.dir[0] + (p[1] - self.mirror[1]) * self.dir[1]
    }
}

const TILE_C: RGBColor = RGBColor(66, 133, 244);
const LAMP_C: RGBColor = RGBColor(230, 140, 0);
const CAM_C: RGBColor = RGBColor(30, 70, 200);
const RAY_C: RGBColor = RGBColor(210, 30, 30);
/// The picture's size, pixels; each view takes half its width.
const SIZE: (u32, u32) = (960, 480);
/// A view's caption, label areas and margin, pixels.
const CAPTION: f64 = 28.0;
const X_LABELS: f64 = 36.0;
const Y_LABELS: f64 = 52.0;
const MARGIN: f64 = 10.0;

/// A view's plotting area, pixels (width, height).
fn plot_size() -> (f64, f64) {
    (
        SIZE.0 as f64 / 2.0 - Y_LABELS - 2.0 * MARGIN,
        SIZE.1 as f64 - CAPTION - X_LABELS - 2.0 * MARGIN,
    )
}

type Area<'b> = DrawingArea<SVGBackend<'b>, plotters::coord::Shift>;

/// The sketch as SVG, or why it cannot be drawn (a coordinate not finite or beyond a
/// kilometre, a camera or lamp not above the tile).
pub fn rig_svg(s: &RigSketch) -> Result<String, SketchError> {
    let scene = scene(s)?;
    crate::hdr::files::register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        root.fill(&WHITE)?;
        let (left, right) = root.split_horizontally(SIZE.0 / 2);
        top_view(&left, &scene)?;
        side_view(&right, &scene)?;
        root.present()?;
    }
    Ok(svg)
}

/// Check the sketch's numbers and work out what the views draw.
fn scene<'a>(s: &'a RigSketch<'a>) -> Result<Scene<'a>, SketchError> {
    let g = s.geometry;
    let h_tile = g.tile_thickness_mm;
    let sq = g.grid_square_mm;
    let [nx, ny] = g.grid_inner_corners;
    let mut all: Vec<f64> = vec![h_tile, sq, nx as f64, ny as f64];
    all.extend(s.camera);
    all.extend(g.lamp_position_mm);
    all.extend(s.refined.into_iter().flatten());
    all.extend(g.tile_outline_mm.iter().flatten());
    if let Some(r) = s.reference {
        all.extend(r.outline_mm.iter().flatten());
        all.push(r.thickness_mm);
    }
    if !all.iter().all(|v| v.is_finite() && v.abs() < MAX_MM) {
        return Err(SketchError::NotDrawable);
    }
    if sq <= 0.0 || g.tile_outline_mm.len() < 3 || nx == 0 || ny == 0 {
        return Err(SketchError::Empty);
    }
    // A board of more squares than a sketch can show (or than any lab prints).
    if nx > 200 || ny > 200 || (nx as f64 + 1.0) * sq > MAX_MM || (ny as f64 + 1.0) * sq > MAX_MM {
        return Err(SketchError::GridTooLarge {
            nx,
            ny,
            square_mm: sq,
        });
    }
    let cam = s.camera;
    let lamp = g.lamp_position_mm;
    let mirror = mirror_point(cam, lamp, h_tile).ok_or(SketchError::NotAbove)?;
    let on_tile = crate::rig::inside_polygon(&g.tile_outline_mm, mirror[0], mirror[1]);
    let board = [
        (-sq, -sq),
        (nx as f64 * sq, -sq),
        (nx as f64 * sq, ny as f64 * sq),
        (-sq, ny as f64 * sq),
    ];
    let axis_hit = s.axis.and_then(|a| {
        (a[2] < -1e-6 && a.iter().all(|v| v.is_finite())).then(|| {
            let t = -cam[2] / a[2];
            [cam[0] + t * a[0], cam[1] + t * a[1], 0.0]
        })
    });
    let (dx, dy) = (lamp[0] - cam[0], lamp[1] - cam[1]);
    let dl = (dx * dx + dy * dy).sqrt();
    let dir = if dl > 1e-9 {
        [dx / dl, dy / dl]
    } else {
        [0.0, 1.0]
    };
    Ok(Scene {
        s,
        cam,
        lamp,
        mirror,
        on_tile,
        board,
        axis_hit,
        dir,
    })
}

/// The view from above: the board, the tile, the reference, the camera, the lamp and the
/// mirror point.
fn top_view(area: &Area, sc: &Scene) -> Result<(), SketchError> {
    let (s, g) = (sc.s, sc.s.geometry);
    let (cam, lamp, mirror, board) = (sc.cam, sc.lamp, sc.mirror, sc.board);
    let sq = g.grid_square_mm;
    let [nx, ny] = g.grid_inner_corners;
    let (pw, ph) = plot_size();
    let xs = board
        .iter()
        .map(|p| p.0)
        .chain([cam[0], lamp[0], mirror[0]])
        .chain(sc.axis_hit.map(|p| p[0]));
    let ys = board
        .iter()
        .map(|p| p.1)
        .chain([cam[1], lamp[1], mirror[1]])
        .chain(sc.axis_hit.map(|p| p[1]));
    let (xr, yr) = equal_aspect(span(xs, 10.0), span(ys, 10.0), pw, ph);
    let mut c = ChartBuilder::on(area)
        .caption("From above (grid x, y; mm)", ("sans-serif", 17))
        .margin(MARGIN as u32)
        .x_label_area_size(X_LABELS as u32)
        .y_label_area_size(Y_LABELS as u32)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)?;
    c.configure_mesh()
        .disable_mesh()
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .x_desc("x, mm")
        .y_desc("y, mm")
        .draw()?;
    d!(c.draw_series(std::iter::once(Polygon::new(
        board.to_vec(),
        RGBColor(225, 225, 225),
    ))))?;
    // The chessboard's dark squares, lightly.
    let mut dark = Vec::new();
    for i in -1..nx as i64 {
        for j in -1..ny as i64 {
            // The inner corner at the origin has its +x,+y square dark.
            if (i + j).rem_euclid(2) == 0 {
                let (x0, y0) = (i as f64 * sq, j as f64 * sq);
                dark.push(Rectangle::new(
                    [(x0, y0), (x0 + sq, y0 + sq)],
                    RGBColor(190, 190, 190).filled(),
                ));
            }
        }
    }
    d!(c.draw_series(dark))?;
    let poly = |o: &[[f64; 2]]| o.iter().map(|p| (p[0], p[1])).collect::<Vec<_>>();
    let closed = |o: &[[f64; 2]]| {
        let mut v = poly(o);
        v.push(v[0]);
        v
    };
    let tile = poly(&g.tile_outline_mm);
    d!(c.draw_series(std::iter::once(Polygon::new(
        tile.clone(),
        TILE_C.mix(0.35),
    ))))?;
    d!(c.draw_series(std::iter::once(PathElement::new(
        closed(&g.tile_outline_mm),
        TILE_C.stroke_width(2),
    ))))?;
    // The tile's name beside its lowest corner, clear of the mirror point.
    let tc =
        tile.iter().copied().fold(
            (f64::INFINITY, 0.0),
            |a, p| if p.1 < a.0 { (p.1, p.0) } else { a },
        );
    let tc = (tc.1, tc.0 - 0.04 * (yr.1 - yr.0));
    d!(c.draw_series(std::iter::once(label!(
        xr,
        tc,
        "tile".into(),
        RGBColor(20, 60, 150),
    ))))?;
    if let Some(r) = s.reference {
        if r.outline_mm.len() >= 3 {
            d!(c.draw_series(std::iter::once(Polygon::new(poly(&r.outline_mm), WHITE))))?;
            d!(c.draw_series(std::iter::once(PathElement::new(
                closed(&r.outline_mm),
                BLACK.stroke_width(1),
            ))))?;
            let p = r.outline_mm[0];
            d!(c.draw_series(std::iter::once(label!(
                xr,
                (p[0], p[1]),
                "reference".into(),
                BLACK,
            ))))?;
        }
    }
    // The plane of incidence's trace: camera's foot, mirror point, lamp's foot.
    d!(c.draw_series(std::iter::once(PathElement::new(
        vec![(cam[0], cam[1]), (mirror[0], mirror[1]), (lamp[0], lamp[1])],
        RAY_C.mix(0.6).stroke_width(1),
    ))))?;
    if let Some(a) = sc.axis_hit {
        d!(c.draw_series(std::iter::once(PathElement::new(
            vec![(cam[0], cam[1]), (a[0], a[1])],
            CAM_C.mix(0.5).stroke_width(1),
        ))))?;
        d!(c.draw_series(std::iter::once(Cross::new(
            (a[0], a[1]),
            4,
            CAM_C.stroke_width(1),
        ))))?;
    }
    d!(c.draw_series(std::iter::once(TriangleMarker::new(
        (cam[0], cam[1]),
        7,
        CAM_C.filled(),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        xr,
        (cam[0], cam[1]),
        format!("camera, z {:.0} mm", cam[2]),
        CAM_C,
    ))))?;
    if let Some(r) = s.refined {
        d!(c.draw_series(std::iter::once(Circle::new(
            (r[0], r[1]),
            5,
            CAM_C.stroke_width(1),
        ))))?;
    }
    d!(c.draw_series(std::iter::once(Circle::new(
        (lamp[0], lamp[1]),
        6,
        LAMP_C.filled(),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        xr,
        (lamp[0], lamp[1]),
        format!("lamp, z {:.0} mm", lamp[2]),
        LAMP_C,
    ))))?;
    d!(c.draw_series(std::iter::once(Cross::new(
        (mirror[0], mirror[1]),
        6,
        RAY_C.stroke_width(2),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        xr,
        (mirror[0], mirror[1]),
        if sc.on_tile {
            "mirror point".into()
        } else {
            "mirror point (off the tile!)".into()
        },
        RAY_C,
    ))))?;
    Ok(())
}

/// The view from the side, in the plane of incidence: the grid, the tile, the reference,
/// the light's path by the mirror point, the camera and the lamp.
fn side_view(area: &Area, sc: &Scene) -> Result<(), SketchError> {
    let (s, g) = (sc.s, sc.s.geometry);
    let (cam, lamp, mirror) = (sc.cam, sc.lamp, sc.mirror);
    let h_tile = g.tile_thickness_mm;
    let (pw, ph) = plot_size();
    let mut tile_s: Vec<f64> = g.tile_outline_mm.iter().map(|p| sc.along(*p)).collect();
    tile_s.sort_by(f64::total_cmp);
    let board_s: Vec<f64> = sc.board.iter().map(|p| sc.along([p.0, p.1])).collect();
    let (bs0, bs1) = (
        board_s.iter().copied().fold(f64::INFINITY, f64::min),
        board_s.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    );
    let cs = sc.along([cam[0], cam[1]]);
    let ls = sc.along([lamp[0], lamp[1]]);
    let xs = [bs0, bs1, cs, ls].into_iter();
    let zs = [0.0, cam[2], lamp[2], h_tile].into_iter();
    let (sr, zr) = equal_aspect(span(xs, 10.0), span(zs, 10.0), pw, ph);
    let mut c = ChartBuilder::on(area)
        .caption(
            "From the side, in the plane of incidence (mm)",
            ("sans-serif", 17),
        )
        .margin(MARGIN as u32)
        .x_label_area_size(X_LABELS as u32)
        .y_label_area_size(Y_LABELS as u32)
        .build_cartesian_2d(sr.0..sr.1, zr.0..zr.1)?;
    c.configure_mesh()
        .disable_mesh()
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .x_desc("along the plane of incidence, from the mirror point, mm")
        .y_desc("height z, mm")
        .draw()?;
    d!(c.draw_series(std::iter::once(PathElement::new(
        vec![(bs0, 0.0), (bs1, 0.0)],
        RGBColor(150, 150, 150).stroke_width(3),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        sr,
        (bs0, -0.02 * (zr.1 - zr.0)),
        "grid".into(),
        RGBColor(110, 110, 110),
    ))))?;
    d!(c.draw_series(std::iter::once(Rectangle::new(
        [(tile_s[0], 0.0), (tile_s[tile_s.len() - 1], h_tile)],
        TILE_C.filled(),
    ))))?;
    if let Some(r) = s.reference {
        if r.outline_mm.len() >= 3 {
            let mut rs: Vec<f64> = r.outline_mm.iter().map(|p| sc.along(*p)).collect();
            rs.sort_by(f64::total_cmp);
            d!(c.draw_series(std::iter::once(Rectangle::new(
                [(rs[0], 0.0), (rs[rs.len() - 1], r.thickness_mm)],
                BLACK.stroke_width(1),
            ))))?;
        }
    }
    // The mirror point is the side view's 0.
    d!(c.draw_series(std::iter::once(PathElement::new(
        vec![(ls, lamp[2]), (0.0, h_tile), (cs, cam[2])],
        RAY_C.stroke_width(2),
    ))))?;
    if let Some(a) = sc.axis_hit {
        d!(c.draw_series(std::iter::once(PathElement::new(
            vec![(cs, cam[2]), (sc.along([a[0], a[1]]), 0.0)],
            CAM_C.mix(0.5).stroke_width(1),
        ))))?;
    }
    d!(c.draw_series(std::iter::once(TriangleMarker::new(
        (cs, cam[2]),
        7,
        CAM_C.filled(),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        sr,
        (cs, cam[2]),
        format!(
            "camera, {:.0} mm from the mirror point",
            distance(mirror, cam)
        ),
        CAM_C,
    ))))?;
    d!(c.draw_series(std::iter::once(Circle::new(
        (ls, lamp[2]),
        6,
        LAMP_C.filled(),
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        sr,
        (ls, lamp[2]),
        format!("lamp, {:.0} mm", distance(mirror, lamp)),
        LAMP_C,
    ))))?;
    d!(c.draw_series(std::iter::once(label!(
        sr,
        (0.0, h_tile + 0.04 * (zr.1 - zr.0)),
        format!("θ = {:.1}° from the normal", from_normal_deg(mirror, lamp)),
        RAY_C,
    ))))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry() -> Geometry {
        Geometry {
            lamp_position_mm: [100.0, 350.0, 300.0],
            tile_thickness_mm: 5.0,
            tile_outline_mm: vec![[50.0, 30.0], [150.0, 30.0], [150.0, 130.0], [50.0, 130.0]],
            grid_inner_corners: [9, 6],
            grid_square_mm: 25.0,
        }
    }

    #[test]
    fn the_mirror_point_reflects_the_lamp_into_the_camera() {
        let (cam, lamp) = ([100.0, -250.0, 380.0], [130.0, 350.0, 300.0]);
        let m = mirror_point(cam, lamp, 5.0).unwrap();
        assert_eq!(m[2], 5.0);
        // Equal angles from the normal, and camera, mirror point and lamp in one vertical
        // plane.
        assert!((from_normal_deg(m, cam) - from_normal_deg(m, lamp)).abs() < 1e-9);
        let cross = (cam[0] - m[0]) * (lamp[1] - m[1]) - (cam[1] - m[1]) * (lamp[0] - m[0]);
        assert!(cross.abs() < 1e-6);
        assert!(mirror_point([0.0, 0.0, 3.0], lamp, 5.0).is_none());
    }

    #[test]
    fn the_sketch_draws_and_refuses_numbers_it_cannot_draw() {
        let g = geometry();
        let s = RigSketch {
            geometry: &g,
            reference: None,
            camera: [100.0, -250.0, 380.0],
            axis: Some([0.0, 0.64, -0.77]),
            refined: None,
        };
        let svg = rig_svg(&s).unwrap();
        assert!(svg.contains("<svg") && svg.contains("mirror point"));
        assert!(!svg.contains("off the tile"));
        // A lamp typed wrong puts the mirror point off the tile, and the sketch says so.
        let mut far = geometry();
        far.lamp_position_mm = [900.0, 350.0, 300.0];
        assert!(rig_svg(&RigSketch {
            geometry: &far,
            ..s.clone()
        })
        .unwrap()
        .contains("off the tile"));
        for bad in [f64::NAN, f64::INFINITY, 1e300] {
            let t = std::time::Instant::now();
            let e = rig_svg(&RigSketch {
                camera: [bad, 0.0, 380.0],
                ..s.clone()
            })
            .unwrap_err()
            .to_string();
            assert!(e.contains("mm"), "{e}");
            assert!(t.elapsed() < std::time::Duration::from_secs(2));
        }
        assert!(rig_svg(&RigSketch {
            camera: [100.0, -250.0, 2.0],
            ..s.clone()
        })
        .is_err());
        // A hostile session's board of 4e9 x 4e9 squares is refused at once.
        let mut huge = geometry();
        huge.grid_inner_corners = [u32::MAX, u32::MAX];
        huge.grid_square_mm = 1e-9;
        let t = std::time::Instant::now();
        assert!(rig_svg(&RigSketch {
            geometry: &huge,
            ..s
        })
        .is_err());
        assert!(t.elapsed() < std::time::Duration::from_secs(2));
    }
}
