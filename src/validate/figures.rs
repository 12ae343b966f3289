//! The validation's pictures: photograph beside renders, difference maps, and the radiance
//! profile through the highlight.

use image::ImageEncoder;
use plotters::prelude::*;

use super::loaded::Loaded;
use crate::devices::Pixels;
use crate::fit::model::{sub, unit, Model, Reflectance};
use crate::fit::mosaic::MosaicChoice;
use crate::fit::sample::SampleError;
use crate::fit::sample::{sample, SampleOptions, Saturated, Strategy};
use crate::fit::solve::{fit, Options};
use crate::hdr::merge::{MASK_OK, MASK_SATURATED};
use glint_numerics::validate::compare::predict_box;
use glint_numerics::validate::render::Shading;

/// Why a figure could not be drawn (the validation writes it as a warning, or stops).
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    /// Drawing or encoding failed (plotters' or the PNG encoder's message).
    #[error("{0}")]
    Draw(String),
    #[error(transparent)]
    Sample(#[from] SampleError),
    #[error("only {0} tile pixels on the line through the highlight")]
    FewPixels(usize),
    #[error("only {0} samples in the plane of incidence")]
    FewSamples(usize),
}

/// A drawing backend's or encoder's error, as its message.
fn draw(e: impl std::fmt::Display) -> FigureError {
    FigureError::Draw(e.to_string())
}

/// Height of the label strip above each panel.
const LABEL: usize = 30;
const GAP: usize = 8;
/// Panels wider than this are shrunk by an integer factor.
const MAX_PANEL: usize = 480;

/// An 8-bit RGB image.
struct Canvas {
    w: usize,
    h: usize,
    px: Vec<u8>,
}

impl Canvas {
    fn new(w: usize, h: usize) -> Self {
        Canvas {
            w,
            h,
            px: vec![255; w * h * 3],
        }
    }

    fn put(&mut self, x: usize, y: usize, rgb: [u8; 3]) {
        let i = 3 * (y * self.w + x);
        self.px[i..i + 3].copy_from_slice(&rgb);
    }

    /// Draw text labels at (x, y) (top left).
    fn labels(&mut self, labels: &[(usize, usize, String)]) -> Result<(), FigureError> {
        crate::hdr::files::register_font();
        let root = BitMapBackend::with_buffer(&mut self.px, (self.w as u32, self.h as u32))
            .into_drawing_area();
        let style = ("sans-serif", 18).into_font().color(&BLACK);
        for (x, y, t) in labels {
            root.draw_text(t, &style, (*x as i32, *y as i32))
                .map_err(draw)?;
        }
        root.present().map_err(draw)?;
        Ok(())
    }

    fn png(&self) -> Result<Vec<u8>, FigureError> {
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(
                &self.px,
                self.w as u32,
                self.h as u32,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(draw)?;
        Ok(out)
    }
}

/// The part of the frame a panel shows.
struct Crop {
    /// (x0, y0, x1, y1), inclusive, in the frame.
    b: [usize; 4],
    /// Shrink factor (an integer, so a panel pixel is the mean of s x s frame pixels).
    s: usize,
    /// The panel's size.
    pw: usize,
    ph: usize,
    /// The frame's width.
    width: usize,
}

/// The crop shown: the tile's bounding box grown by a third on every side, shrunk by the
/// integer factor that keeps a panel at most MAX_PANEL wide.
fn crop(l: &Loaded) -> Crop {
    let [x0, y0, x1, y1] = l.region.bbox;
    let (w, h) = (l.region.width, l.region.height);
    let gx = (x1 - x0) / 3;
    let gy = (y1 - y0) / 3;
    let b = [
        x0.saturating_sub(gx),
        y0.saturating_sub(gy),
        (x1 + gx).min(w - 1),
        (y1 + gy).min(h - 1),
    ];
    let s = (b[2] - b[0] + 1).div_ceil(MAX_PANEL).max(1);
    Crop {
        b,
        s,
        pw: (b[2] - b[0] + 1) / s,
        ph: (b[3] - b[1] + 1) / s,
        width: w,
    }
}

/// 8-bit display values of a frame (16-bit frames shown by their high byte).
fn frame_u8(p: &Pixels) -> Vec<u8> {
    match p {
        Pixels::U8(v) => v.clone(),
        Pixels::U16(v) => v.iter().map(|z| (z >> 8) as u8).collect(),
    }
}

/// Paste the crop of an RGB image `src` (pixel index in the frame -> RGB) at (ox, oy).
fn paste(c: &mut Canvas, src: &dyn Fn(usize) -> [f64; 3], crop: &Crop, ox: usize, oy: usize) {
    let Crop { b, s, width, .. } = *crop;
    for y in 0..crop.ph {
        for x in 0..crop.pw {
            let mut acc = [0.0; 3];
            for dy in 0..s {
                for dx in 0..s {
                    let k = (b[1] + y * s + dy) * width + b[0] + x * s + dx;
                    let v = src(k);
                    for i in 0..3 {
                        acc[i] += v[i];
                    }
                }
            }
            let n = (s * s) as f64;
            c.put(
                ox + x,
                oy + y,
                acc.map(|a| (a / n).round().clamp(0.0, 255.0) as u8),
            );
        }
    }
}

/// The photograph at exposure `j` beside the render of each model at the same exposure,
/// through the camera's response (the paper's figures 4 to 7).
pub fn compare_png(
    l: &Loaded,
    j: usize,
    renders: &[Vec<f32>],
    labels: &[String],
) -> Result<Vec<u8>, FigureError> {
    let cr = crop(l);
    let (pw, ph) = (cr.pw, cr.ph);
    let panels = renders.len() + 1;
    let mut c = Canvas::new(panels * pw + (panels - 1) * GAP, ph + LABEL);
    let f = &l.tiles.frames[j];
    let scale = if l.tiles.bit_depth > 8 {
        1.0 / 257.0
    } else {
        1.0
    };
    let photo = frame_u8(&f.pixels);
    // A monochrome camera's one channel is shown grey (in all three of the panel's).
    let nc = l.inputs.channels;
    let ch = |i: usize| i.min(nc - 1);
    paste(
        &mut c,
        &|k| [0, 1, 2].map(|i| photo[nc * k + ch(i)] as f64),
        &cr,
        0,
        LABEL,
    );
    let mut text = vec![(4, 6, format!("photograph, {} µs", f.exposure_us))];
    for (m, r) in renders.iter().enumerate() {
        let pred = predict_box(r, &l.response, f.exposure_us, l.dark[j], cr.b, cr.width);
        let ox = (m + 1) * (pw + GAP);
        paste(
            &mut c,
            &|k| [0, 1, 2].map(|i| pred[nc * k + ch(i)] as f64 * scale),
            &cr,
            ox,
            LABEL,
        );
        text.push((ox + 4, 6, labels[m].clone()));
    }
    c.labels(&text)?;
    c.png()
}

/// Blue (negative) - white - red (positive) for t in [-1, 1].
fn diverging(t: f64) -> [u8; 3] {
    let t = t.clamp(-1.0, 1.0);
    let end: [f64; 3] = if t < 0.0 {
        [33.0, 102.0, 172.0]
    } else {
        [178.0, 24.0, 43.0]
    };
    end.map(|e| (255.0 + (e - 255.0) * t.abs()).round() as u8)
}

/// A value in 1, 2, 5 x 10^k at or above x.
fn nice(x: f64) -> f64 {
    let e = x.log10().floor();
    let base = 10f64.powf(e);
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * base)
        .find(|v| *v >= x * (1.0 - 1e-9))
        .unwrap_or(10.0 * base)
}

/// Per model: the relative radiance difference (model - measured) / measured over the
/// tile, averaged over the channels, on one colour scale for all models (set by the chosen
/// model's spread); around the tile the photograph at exposure `j`, dimmed.
pub fn difference_png(
    l: &Loaded,
    j: usize,
    renders: &[Vec<f32>],
    labels: &[String],
    chosen: usize,
) -> Result<Vec<u8>, FigureError> {
    let cr = crop(l);
    let (pw, ph) = (cr.pw, cr.ph);
    let width = l.region.width;
    let x = &l.inputs.radiance;
    let mask = &l.inputs.mask;
    let nc = l.inputs.channels;
    let rel = |r: &[f32], k: usize| -> Option<f64> {
        if !l.region.inside[k] {
            return None;
        }
        let (mut sum, mut n) = (0.0, 0);
        for c in 0..nc {
            let i = nc * k + c;
            if mask[i] == MASK_OK && x[i] > 0.0 {
                sum += (r[i] - x[i]) as f64 / x[i] as f64;
                n += 1;
            }
        }
        (n > 0).then(|| sum / n as f64)
    };
    let spread = {
        let v: Vec<f64> = (0..width * l.region.height)
            .filter_map(|k| rel(&renders[chosen], k))
            .collect();
        (v.iter().map(|d| d * d).sum::<f64>() / v.len().max(1) as f64).sqrt()
    };
    let range = nice((3.0 * spread).max(0.01));
    let bar = 16;
    let panels = renders.len();
    let mut c = Canvas::new(
        (panels * pw + (panels - 1) * GAP).max(320),
        ph + 2 * LABEL + bar + 8,
    );
    let photo = frame_u8(&l.tiles.frames[j].pixels);
    let mut text = Vec::new();
    for (m, r) in renders.iter().enumerate() {
        let ox = m * (pw + GAP);
        paste(
            &mut c,
            &|k| match rel(r, k) {
                Some(d) => diverging(d / range).map(|v| v as f64),
                None => {
                    let g = photo[nc * k..nc * k + nc]
                        .iter()
                        .map(|v| *v as f64)
                        .sum::<f64>()
                        / nc as f64;
                    [0.4 * g + 40.0; 3]
                }
            },
            &cr,
            ox,
            LABEL,
        );
        text.push((ox + 4, 6, labels[m].clone()));
    }
    // The colour bar.
    let y0 = LABEL + ph + 4;
    let bw = 240.min(c.w - 8);
    for xb in 0..bw {
        let t = 2.0 * xb as f64 / (bw - 1) as f64 - 1.0;
        for yb in 0..bar - 4 {
            c.put(4 + xb, y0 + yb, diverging(t));
        }
    }
    let pct = 100.0 * range;
    text.push((
        4,
        y0 + bar + 2,
        format!("−{pct}%   (model − measured) / measured   +{pct}%"),
    ));
    c.labels(&text)?;
    c.png()
}

/// The radiance (green channel, or a monochrome camera's one) along the line through the
/// highlight in the plane of incidence: measured, every fitted model, and the chosen model
/// fitted to this line with its saturated pixels clipped (the paper's way) and with
/// unsaturated pixels only (paper figure 3).
pub fn profile_svg(
    l: &Loaded,
    fitted: &[Shading],
    chosen: Model,
    factor: Option<&[f64]>,
) -> Result<(String, String), FigureError> {
    let img = l.inputs.image();
    let scene = &l.inputs.scene;
    let opts = |saturated| SampleOptions {
        strategy: Strategy::Line,
        count: Some(100_000),
        saturated,
        saturation_level: l.inputs.saturation_level,
        ..SampleOptions::default()
    };
    let clipped = sample(scene, &img, &opts(Saturated::Clip))?;
    // The same colour filter layout (read once, from the first).
    let unsat = sample(
        scene,
        &img,
        &SampleOptions {
            mosaic: match clipped.mosaic {
                Some(m) => MosaicChoice::Given(m),
                None => MosaicChoice::Off,
            },
            ..opts(Saturated::Exclude)
        },
    )?;
    if clipped.samples.len() < 10 {
        return Err(FigureError::FewPixels(clipped.samples.len()));
    }
    let nc = l.inputs.channels;
    let fit_on = |s: &crate::fit::sample::Sampled| {
        let v: Vec<_> = s.samples.iter().map(|p| p.sample).collect();
        fit(
            chosen,
            &v,
            &Options {
                channels: nc,
                ..Options::default()
            },
        )
    };
    let with_clipped = fit_on(&clipped);
    let without = fit_on(&unsat);
    let c = if nc == 1 { 0 } else { 1 };
    let mut line: Vec<_> = clipped.samples.iter().collect();
    line.sort_by(|a, b| a.along_mm.total_cmp(&b.along_mm));
    let sat_px =
        |u: usize, v: usize| l.inputs.mask[nc * (v * l.inputs.width + u) + c] == MASK_SATURATED;
    // The values the samples hold (a demosaicked camera's samples hold their photosite's
    // channel only).
    let holds = |p: &crate::fit::sample::PixelSample| p.sample.variance[c].is_finite();
    let measured: Vec<(f64, f64)> = unsat
        .samples
        .iter()
        .filter(|p| holds(p))
        .map(|p| (p.along_mm, p.sample.radiance[c]))
        .collect();
    let clipped_pts: Vec<(f64, f64)> = line
        .iter()
        .filter(|p| sat_px(p.u, p.v))
        .filter(|p| holds(p))
        .map(|p| (p.along_mm, p.sample.radiance[c]))
        .collect();
    let curve = |f: &dyn Fn(&crate::fit::model::Geometry) -> f64| -> Vec<(f64, f64)> {
        line.iter()
            .map(|p| (p.along_mm, f(&p.sample.geometry)))
            .collect()
    };
    let mut series: Vec<Series> = Vec::new();
    let palette = PALETTE;
    for (k, f) in fitted.iter().enumerate() {
        let chosen_mark = if f.model == chosen { " (chosen)" } else { "" };
        series.push((
            format!("{}{chosen_mark}, fit.json", f.model.name()),
            curve(&|g| f.tile(g, c)),
            palette[k % palette.len()],
            if f.model == chosen { 3 } else { 1 },
        ));
    }
    series.push((
        format!(
            "{} fitted to this line, unsaturated pixels only (n = {:.1})",
            chosen.name(),
            without.n.value
        ),
        curve(&|g| without.predict(g, c)),
        RGBColor(23, 190, 207),
        2,
    ));
    series.push((
        format!(
            "{} fitted to this line, saturated pixels clipped (n = {:.1}){}",
            chosen.name(),
            with_clipped.n.value,
            if clipped_pts.is_empty() {
                ": none saturated, the two fits coincide"
            } else {
                ""
            }
        ),
        curve(&|g| with_clipped.predict(g, c)),
        RGBColor(255, 127, 14),
        2,
    ));
    let (x_lo, x_hi) = (line[0].along_mm, line[line.len() - 1].along_mm);
    let y_hi = series
        .iter()
        .flat_map(|s| s.1.iter().map(|p| p.1))
        .chain(measured.iter().map(|p| p.1))
        .filter(|y| y.is_finite())
        .fold(0.0f64, f64::max)
        * 1.08;
    crate::hdr::files::register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 520)).into_drawing_area();
        root.fill(&WHITE).map_err(draw)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                if nc == 1 {
                    "Radiance along the line through the highlight (mono)"
                } else {
                    "Radiance along the line through the highlight (green channel)"
                },
                ("sans-serif", 20),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(80)
            .build_cartesian_2d(x_lo..x_hi, 0.0..y_hi.max(1e-30))
            .map_err(draw)?;
        chart
            .configure_mesh()
            .x_desc("position along the plane of incidence, mm from the highlight")
            .y_desc("radiance (exposure units / s)")
            .y_label_formatter(&|v| sig3(*v))
            .draw()
            .map_err(draw)?;
        // Each measured value with its 95% interval (the HDR stage's variance).
        chart
            .draw_series(unsat.samples.iter().filter(|p| holds(p)).map(|p| {
                let (y, sd) = (p.sample.radiance[c], p.sample.variance[c].max(0.0).sqrt());
                ErrorBar::new_vertical(
                    p.along_mm,
                    y - 1.96 * sd,
                    y,
                    y + 1.96 * sd,
                    BLACK.mix(0.35).stroke_width(1),
                    3,
                )
            }))
            .map_err(draw)?;
        chart
            .draw_series(measured.iter().map(|p| Circle::new(*p, 2, BLACK.filled())))
            .map_err(draw)?
            .label("measured (HDR), with its 95% interval")
            .legend(|(x, y)| Circle::new((x + 10, y), 3, BLACK.filled()));
        if !clipped_pts.is_empty() {
            chart
                .draw_series(
                    clipped_pts
                        .iter()
                        .map(|p| Cross::new(*p, 3, RED.stroke_width(1))),
                )
                .map_err(draw)?
                .label("saturated in every exposure (clipped at the saturation level)")
                .legend(|(x, y)| Cross::new((x + 10, y), 3, RED.stroke_width(1)));
        }
        curves_and_legend(&mut chart, series, |p| p, SeriesLabelPosition::LowerLeft)?;
        root.present().map_err(draw)?;
    }
    let polar = polar_svg(
        l,
        fitted,
        chosen,
        &unsat,
        c,
        factor.map(|f| f[c.min(f.len() - 1)]),
    )?;
    Ok((svg, polar))
}

/// A curve to draw: label, points, colour, line width.
type Series = (String, Vec<(f64, f64)>, RGBColor, u32);

/// A chart on f64 axes drawn into an SVG string.
type Chart<'a, 'b> = ChartContext<
    'a,
    SVGBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

/// Draw each curve (its points mapped by `to_xy`) with its legend entry, then the legend
/// at `position`: the profile's and the polar plot's curves alike.
fn curves_and_legend<'a, 'b: 'a>(
    chart: &mut Chart<'a, 'b>,
    curves: Vec<Series>,
    to_xy: impl Fn((f64, f64)) -> (f64, f64),
    position: SeriesLabelPosition,
) -> Result<(), FigureError> {
    for (name, pts, colour, width) in curves {
        chart
            .draw_series(LineSeries::new(
                pts.into_iter().map(&to_xy),
                colour.stroke_width(width),
            ))
            .map_err(draw)?
            .label(name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(width))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(position)
        .label_font(("sans-serif", 13))
        .draw()
        .map_err(draw)
}

/// One colour per candidate model.
const PALETTE: [RGBColor; 5] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
];

/// The BRDF in the plane of incidence, as a polar plot: for each tile point on the line
/// through the highlight, f_r (the radiance over the lamp's irradiance there, n.l / D²)
/// at the angle of the view direction from the normal (positive towards the camera's
/// side) as if lit from the highlight's lamp direction (the mirror angle of that light
/// plus the point's own view offset from its mirror direction: the near lamp lights each
/// point from another angle), measured with its 95% interval and every fitted model's; in
/// 1/sr where the fit measured a reference standard (`factor`: fit.json's, per unit BRDF),
/// else in the radiance's relative units.
fn polar_svg(
    l: &Loaded,
    fitted: &[Shading],
    chosen: Model,
    line: &crate::fit::sample::Sampled,
    c: usize,
    factor: Option<f64>,
) -> Result<String, FigureError> {
    let scene = &l.inputs.scene;
    let t = scene.incidence_direction();
    let scale = factor.unwrap_or(1.0);
    let angle = |d: [f64; 3]| (d[0] * t[0] + d[1] * t[1]).atan2(d[2]);
    let towards = |to: [f64; 3], from: [f64; 3]| unit(sub(to, from));
    // The lamp's direction seen from the highlight (the line's middle point), and its
    // mirror direction.
    let mid = &line.samples[line.samples.len() / 2];
    let lamp = towards(scene.lamp, mid.point);
    let mirror0 = -angle(lamp);
    // (view angle, f_r, its sd, geometry), sorted by angle. The lamp is near, so the light
    // comes in at another angle at each point: each point is drawn at the mirror angle of
    // the highlight's light plus its own view's offset from its own mirror direction, as if
    // every point were lit from the highlight's direction.
    let mut pts: Vec<(f64, f64, f64, crate::fit::model::Geometry)> = line
        .samples
        .iter()
        // (Values the sample holds: a demosaicked camera's hold their photosite's only.)
        .filter(|p| p.sample.geometry.cos_l > 0.0 && p.sample.variance[c].is_finite())
        .map(|p| {
            let g = p.sample.geometry;
            let to_irr = g.d2 / g.cos_l / scale;
            let v = towards(scene.centre, p.point);
            let l = towards(scene.lamp, p.point);
            (
                mirror0 + angle(v) + angle(l),
                p.sample.radiance[c] * to_irr,
                p.sample.variance[c].max(0.0).sqrt() * to_irr,
                g,
            )
        })
        .collect();
    if pts.len() < 10 {
        return Err(FigureError::FewSamples(pts.len()));
    }
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let curves: Vec<Series> = fitted
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let pts: Vec<(f64, f64)> = pts
                .iter()
                .map(|(a, _, _, g)| (*a, f.tile(g, c) * g.d2 / g.cos_l / scale))
                .collect();
            (
                format!(
                    "{}{}",
                    f.model.name(),
                    if f.model == chosen { " (chosen)" } else { "" }
                ),
                pts,
                PALETTE[k % PALETTE.len()],
                if f.model == chosen { 3 } else { 1 },
            )
        })
        .collect();
    let r_max = pts
        .iter()
        .map(|p| p.1 + 1.96 * p.2)
        .chain(curves.iter().flat_map(|c| c.1.iter().map(|p| p.1)))
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-30)
        * 1.1;
    let xy = |a: f64, r: f64| (r * a.sin(), r * a.cos());
    let units = if factor.is_some() {
        "f_r, 1/sr (absolute: the reference standard)"
    } else {
        "f_r, the radiance's relative units (no reference standard)"
    };
    crate::hdr::files::register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 560)).into_drawing_area();
        root.fill(&WHITE).map_err(draw)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!(
                    "BRDF in the plane of incidence ({} channel): {units}",
                    if l.inputs.channels == 1 {
                        "mono"
                    } else {
                        "green"
                    }
                ),
                ("sans-serif", 18),
            )
            .margin(12)
            .build_cartesian_2d(-r_max..r_max, -0.04 * r_max..r_max)
            .map_err(draw)?;
        // Rings at nice radii and rays every 30 degrees, labelled.
        let step = nice(r_max / 4.0);
        let mut r = step;
        let grey = BLACK.mix(0.15);
        while r < r_max {
            let ring: Vec<(f64, f64)> = (0..=90)
                .map(|k| xy((k as f64 * 2.0 - 90.0).to_radians(), r))
                .collect();
            chart
                .draw_series(std::iter::once(PathElement::new(ring, grey)))
                .map_err(draw)?;
            chart
                .draw_series(std::iter::once(Text::new(
                    sig3(r),
                    (0.01 * r_max, r),
                    ("sans-serif", 11),
                )))
                .map_err(draw)?;
            r += step;
        }
        for deg in [-90.0f64, -60.0, -30.0, 0.0, 30.0, 60.0, 90.0] {
            let end = xy(deg.to_radians(), r_max);
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(0.0, 0.0), end],
                    grey,
                )))
                .map_err(draw)?;
            chart
                .draw_series(std::iter::once(Text::new(
                    format!("{deg:+.0}°"),
                    (end.0 * 0.97, end.1 * 0.97),
                    ("sans-serif", 11),
                )))
                .map_err(draw)?;
        }
        let la = angle(lamp);
        chart
            .draw_series(std::iter::once(PathElement::new(
                vec![(0.0, 0.0), xy(la, r_max)],
                RGBColor(230, 160, 0).stroke_width(2),
            )))
            .map_err(draw)?
            .label("towards the lamp (from the highlight)")
            .legend(|(x, y)| {
                PathElement::new(
                    vec![(x, y), (x + 20, y)],
                    RGBColor(230, 160, 0).stroke_width(2),
                )
            });
        chart
            .draw_series(pts.iter().map(|&(a, f, sd, _)| {
                PathElement::new(
                    vec![xy(a, (f - 1.96 * sd).max(0.0)), xy(a, f + 1.96 * sd)],
                    BLACK.mix(0.35),
                )
            }))
            .map_err(draw)?;
        chart
            .draw_series(
                pts.iter()
                    .map(|&(a, f, _, _)| Circle::new(xy(a, f), 2, BLACK.filled())),
            )
            .map_err(draw)?
            .label("measured, with its 95% interval")
            .legend(|(x, y)| Circle::new((x + 10, y), 3, BLACK.filled()));
        curves_and_legend(
            &mut chart,
            curves,
            |(a, r)| xy(a, r),
            SeriesLabelPosition::UpperLeft,
        )?;
        root.present().map_err(draw)?;
    }
    Ok(svg)
}

/// Three significant digits, plainly where the magnitude allows.
fn sig3(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let e = v.abs().log10().floor() as i32;
    if (-3..6).contains(&e) {
        let d = (2 - e).max(0) as usize;
        format!("{v:.d$}")
    } else {
        format!("{v:.2e}")
    }
}
