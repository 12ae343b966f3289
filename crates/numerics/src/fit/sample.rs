//! Sampling (paper section 3.4): which tile pixels the fit uses.
//!
//! The highlight centre is found automatically (the peak of the unsaturated radiance, or
//! the centre of the saturated patch) and checked against the mirror point the geometry
//! predicts. The default samples lie on a line through it along the plane of incidence,
//! where the lobe changes fastest; a perpendicular line, a user line, a rectangle around
//! the highlight and uniform-random tile pixels are there for comparison.
//!
//! A pixel is sampled at most once: asking for more samples than a line has pixels gives
//! the line's pixels (a pixel counted twice would count its noise twice and make the
//! intervals too narrow). Saturated pixels, and a blooming margin around them, are left
//! out; optionally they are kept as censored samples (the model must predict at least the
//! saturation level there), or, for comparison with the paper, as if measured.

use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use super::geometry::Scene;
use super::mosaic::{Detection, Mosaic, MosaicChoice};
use super::solve::Sample;
use crate::hdr::merge::{MASK_OK, MASK_SATURATED};

/// The merged radiance of a session: RGB interleaved, or one sample a pixel (a monochrome
/// camera's; [`RadianceImage::channels`] tells them apart by the samples' count).
pub struct RadianceImage<'a> {
    pub width: usize,
    pub height: usize,
    pub radiance: &'a [f32],
    pub variance: &'a [f32],
    pub mask: &'a [u8],
}

impl RadianceImage<'_> {
    /// Samples a pixel: 1 for a monochrome image (width x height samples), else 3.
    pub fn channels(&self) -> usize {
        if self.radiance.len() == self.width * self.height {
            1
        } else {
            3
        }
    }
}

/// Where the samples lie.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    /// A line through the highlight along the plane of incidence.
    Line,
    /// A line through the highlight across the plane of incidence.
    Perpendicular,
    /// Both lines, half the samples each (the default): the line along the plane of
    /// incidence alone cannot tell Phong from Blinn-Phong (there the angle between r and v
    /// is exactly twice that between n and h, so the two lobes coincide with n scaled).
    Cross,
    /// A line between two pixels (u0, v0, u1, v1).
    UserLine([f64; 4]),
    /// A regular grid over a square around the highlight.
    Rect,
    /// Uniformly random tile pixels (seeded).
    Random,
}

impl Strategy {
    pub fn name(&self) -> &'static str {
        match self {
            Strategy::Line => "line",
            Strategy::Perpendicular => "perpendicular",
            Strategy::Cross => "cross",
            Strategy::UserLine(_) => "user-line",
            Strategy::Rect => "rect",
            Strategy::Random => "random",
        }
    }
}

/// What becomes of saturated pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Saturated {
    /// Left out, with a blooming margin around them (the default).
    Exclude,
    /// Kept as censored samples: the radiance is at least the saturation level.
    Censor,
    /// Kept as if measured at the saturation level, margin included (the naive way; for
    /// comparison only: it biases the fit).
    Clip,
}

#[derive(Debug, Clone)]
pub struct SampleOptions {
    pub strategy: Strategy,
    /// Samples asked for; `None` chooses by the image's size ([`default_count`]).
    pub count: Option<usize>,
    /// Pixels kept clear of the tile's outline.
    pub edge_margin_px: f64,
    /// Pixels left out around saturated ones (blooming spreads charge into neighbours).
    pub bloom_margin_px: usize,
    pub saturated: Saturated,
    /// The smallest radiance a saturated pixel can have, per channel (the top of the
    /// response's valid range in the shortest exposure).
    pub saturation_level: [f64; 3],
    pub seed: u64,
    /// Whether each sample keeps only its photosite's own channel (a demosaicked camera;
    /// [`super::mosaic`]).
    pub mosaic: MosaicChoice,
}

impl Default for SampleOptions {
    fn default() -> Self {
        SampleOptions {
            strategy: Strategy::Cross,
            count: None,
            edge_margin_px: 1.0,
            bloom_margin_px: 2,
            saturated: Saturated::Exclude,
            saturation_level: [f64::INFINITY; 3],
            seed: 1,
            mosaic: MosaicChoice::Auto,
        }
    }
}

/// The highlight as found and as predicted.
#[derive(Debug, Clone, Serialize)]
pub struct Highlight {
    /// Where the samples are centred (pixels).
    pub centre_px: [f64; 2],
    /// Peak of the radiance on the tile, or centre of the saturated patch.
    pub found_px: Option<[f64; 2]>,
    /// The mirror point the geometry predicts.
    pub predicted_px: [f64; 2],
    pub offset_px: f64,
    /// Tile pixels saturated in every exposure.
    pub saturated_pixels: usize,
    /// Of those, the ones at the highlight (within a fifth of the tile's size of its
    /// centre): the peak is clipped.
    pub saturated_at_highlight: usize,
    /// The predicted mirror point lies on the tile's usable pixels (else the highlight is
    /// off the tile and the samples see only its flank).
    pub mirror_on_tile: bool,
    /// The radiance peaks near the predicted mirror point (within a tenth of the tile's
    /// size): the highlight is where the geometry puts it.
    pub found_near_mirror: bool,
}

/// One sampled pixel.
#[derive(Debug, Clone, Serialize)]
pub struct PixelSample {
    pub u: usize,
    pub v: usize,
    /// The tile point, grid mm.
    pub point: [f64; 3],
    pub sample: Sample,
    /// Position along a line, mm from the highlight centre (0 for area strategies).
    pub along_mm: f64,
}

/// The samples and what was left out.
#[derive(Debug, Clone, Serialize)]
pub struct Sampled {
    pub strategy: Strategy,
    pub requested: usize,
    pub used: usize,
    #[serde(skip)]
    pub samples: Vec<PixelSample>,
    pub highlight: Highlight,
    /// The lines' end points in pixels (u0, v0, u1, v1), for line strategies.
    pub lines_px: Vec<[f64; 4]>,
    pub tile_pixels: usize,
    pub left_out_saturated: usize,
    pub left_out_bloom: usize,
    pub left_out_no_radiance: usize,
    pub censored: usize,
    /// What became of saturated pixels.
    pub saturated: Saturated,
    /// The camera's colour filter layout, where the samples keep only their photosite's
    /// channel.
    pub mosaic: Option<Mosaic>,
    /// What the radiance's noise said of the layout (`None` where it was given or turned
    /// off, or the image cannot tell: monochrome, too small or too masked).
    pub mosaic_detection: Option<Detection>,
    /// Where the layout came from: "detected", "given", "none seen", "off" or
    /// "unreadable".
    pub mosaic_source: &'static str,
    pub warnings: Vec<String>,
}

/// Errors that stop sampling.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    #[error(
        "no pixel of the image sees the tile: check the rig's tile_outline_mm and the calibration"
    )]
    NoTile,
    #[error("{0}")]
    Input(String),
}

/// Which pixels see the tile, with their tile points.
pub struct TileMap {
    pub width: usize,
    pub height: usize,
    /// Tile point per pixel where the pixel (grown by the margin) sees only tile.
    pub points: Vec<Option<[f64; 3]>>,
    pub count: usize,
}

impl TileMap {
    pub fn new(scene: &Scene, width: usize, height: usize, margin: f64) -> Self {
        // Bounding box of the outline's projection, grown a little: pixels outside it
        // cannot see the tile.
        let (mut u0, mut v0, mut u1, mut v1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let n = scene.outline.len();
        for i in 0..n {
            let [a, b] = [scene.outline[i], scene.outline[(i + 1) % n]];
            for k in 0..=32 {
                let t = k as f64 / 32.0;
                let p = [
                    a[0] + t * (b[0] - a[0]),
                    a[1] + t * (b[1] - a[1]),
                    scene.height,
                ];
                let [u, v] = scene.project(p);
                u0 = u0.min(u);
                v0 = v0.min(v);
                u1 = u1.max(u);
                v1 = v1.max(v);
            }
        }
        let clamp = |x: f64, hi: usize| x.clamp(0.0, hi as f64 - 1.0) as usize;
        let (iu0, iu1) = (
            clamp(u0.floor() - 2.0, width),
            clamp(u1.ceil() + 2.0, width),
        );
        let (iv0, iv1) = (
            clamp(v0.floor() - 2.0, height),
            clamp(v1.ceil() + 2.0, height),
        );
        let mut points = vec![None; width * height];
        let mut count = 0;
        if u0.is_finite() && u1 >= u0 {
            for v in iv0..=iv1 {
                for u in iu0..=iu1 {
                    let (uf, vf) = (u as f64, v as f64);
                    if scene.sees_tile(uf, vf, margin) {
                        points[v * width + u] = scene.on_plane(uf, vf);
                        count += 1;
                    }
                }
            }
        }
        TileMap {
            width,
            height,
            points,
            count,
        }
    }

    fn at(&self, u: i64, v: i64) -> Option<[f64; 3]> {
        if u < 0 || v < 0 || u >= self.width as i64 || v >= self.height as i64 {
            return None;
        }
        self.points[v as usize * self.width + u as usize]
    }
}

/// Find the highlight: the centre of the saturated tile pixels if there are any, else the
/// peak of the 5x5-averaged luminance divided by the diffuse basis (n.l) / D^2 (so that
/// the lamp's falloff, which moves the peak of the radiance itself towards the lamp's
/// foot, does not move it). None when the tile shows no radiance at all.
fn find_highlight(
    scene: &Scene,
    img: &RadianceImage,
    tile: &TileMap,
    saturated: &[bool],
) -> Option<[f64; 2]> {
    let w = img.width;
    let nc = img.channels();
    let (mut su, mut sv, mut sn) = (0.0, 0.0, 0usize);
    for (i, s) in saturated.iter().enumerate() {
        if *s && tile.points[i].is_some() {
            su += (i % w) as f64;
            sv += (i / w) as f64;
            sn += 1;
        }
    }
    if sn > 0 {
        return Some([su / sn as f64, sv / sn as f64]);
    }
    let lum = |i: usize| -> Option<f64> {
        let m = &img.mask[nc * i..nc * i + nc];
        let p = tile.points[i]?;
        if m.iter().all(|x| *x == MASK_OK) {
            let a = super::model::Model::diffuse(&scene.geometry(p));
            (a > 0.0).then(|| {
                img.radiance[nc * i..nc * i + nc]
                    .iter()
                    .map(|x| *x as f64)
                    .sum::<f64>()
                    / a
            })
        } else {
            None
        }
    };
    let mut best: Option<(f64, usize)> = None;
    for i in 0..tile.points.len() {
        if lum(i).is_none() {
            continue;
        }
        let (u, v) = ((i % w) as i64, (i / w) as i64);
        let (mut s, mut k) = (0.0, 0);
        for dv in -2..=2 {
            for du in -2..=2 {
                let (x, y) = (u + du, v + dv);
                if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < img.height {
                    if let Some(l) = lum(y as usize * w + x as usize) {
                        s += l;
                        k += 1;
                    }
                }
            }
        }
        let m = s / k as f64;
        if best.is_none_or(|(b, _)| m > b) {
            best = Some((m, i));
        }
    }
    best.map(|(_, i)| [(i % w) as f64, (i / w) as f64])
}

/// How far the tile line through `centre` in direction `d` stays on usable tile pixels,
/// each way (mm, the first negative), walked in 0.1 mm steps.
fn line_reach(scene: &Scene, tile: &TileMap, centre: [f64; 3], d: [f64; 2]) -> [f64; 2] {
    let on_tile = |s: f64| {
        let [u, v] = scene.project([centre[0] + s * d[0], centre[1] + s * d[1], scene.height]);
        tile.at(u.round() as i64, v.round() as i64).is_some()
    };
    [-1.0, 1.0].map(|sign| {
        let mut s = 0.0;
        while on_tile(sign * (s + 0.1)) && s < 1e4 {
            s += 0.1;
        }
        sign * s
    })
}

/// Fewest samples a fit is asked for: below about ten the four models' parameters and their
/// intervals have nothing left to stand on.
pub const MIN_COUNT: usize = 10;

/// What is wrong with asking for `k` samples, where anything is (fewer than [`MIN_COUNT`],
/// or more than `max` where there is one: the daemon caps a job's samples; the command line
/// does not), as the end of a one-line message ("must be at least 10 (got 5)").
pub fn count_problem(k: usize, max: Option<usize>) -> Option<String> {
    match max {
        None if k < MIN_COUNT => Some(format!("must be at least {MIN_COUNT} (got {k})")),
        Some(max) if !(MIN_COUNT..=max).contains(&k) => {
            Some(format!("must be {MIN_COUNT} to {max} (got {k})"))
        }
        _ => None,
    }
}

/// Samples asked for by default: 400 per 640 pixels of the image's longer side, and no
/// fewer than 400 (800 at 1280x960, 1200 at 1920x1080). The default lines cross a tile about
/// as many pixels as the image is wide, so the samples lie as densely along them at every
/// size: a sharper camera gives a fitted n with less noise, not the same samples spread
/// wider (at 1280x960 with a lens profile, the scene family's n = 66 tile went from +2.2% at
/// 400 to within 2% at 800; docs/results/accuracy.md). 400 is where the defaults were measured at
/// 640x480.
pub fn default_count(width: usize, height: usize) -> usize {
    400usize
        .saturating_mul(width.max(height))
        .div_ceil(640)
        .max(400)
}

/// Choose the samples.
pub fn sample(
    scene: &Scene,
    img: &RadianceImage,
    opts: &SampleOptions,
) -> Result<Sampled, SampleError> {
    let (w, h) = (img.width, img.height);
    let count = opts.count.unwrap_or_else(|| default_count(w, h));
    if count == 0 {
        return Err(SampleError::Input("ask for at least one sample".into()));
    }
    let tile = TileMap::new(scene, w, h, opts.edge_margin_px);
    if tile.count == 0 {
        return Err(SampleError::NoTile);
    }
    let nc = img.channels();
    let saturated: Vec<bool> = (0..w * h)
        .map(|i| img.mask[nc * i..nc * i + nc].contains(&MASK_SATURATED))
        .collect();
    let bloom = bloom_margin(&saturated, w, h, opts.bloom_margin_px as i64);
    let mut warnings = Vec::new();
    let highlight = locate_highlight(scene, img, &tile, &saturated, &mut warnings);
    let centre_px = highlight.centre_px;
    // Candidate pixels in order, each with its position along the line.
    let mut lines_px = Vec::new();
    let pixels = candidate_pixels(scene, &tile, opts, count, centre_px, &mut lines_px)?;
    let (mosaic, mosaic_detection, mosaic_source) = match opts.mosaic {
        MosaicChoice::Off => (None, None, "off"),
        MosaicChoice::Given(m) => (Some(m), None, "given"),
        MosaicChoice::Auto => match super::mosaic::detect(w, h, img.radiance, img.mask) {
            Some(d) if d.layout.is_some() => (d.layout, Some(d), "detected"),
            Some(d) => (None, Some(d), "none seen"),
            None => (None, None, "unreadable"),
        },
    };
    if mosaic.is_some() && nc != 3 {
        return Err(SampleError::Input(
            "a colour filter mosaic was given for a monochrome image; leave --mosaic off".into(),
        ));
    }
    let mut taken = take_samples(scene, img, &tile, opts, &saturated, &bloom, pixels)?;
    if let Some(mosaic) = mosaic {
        keep_own_channels(&mut taken, mosaic);
    }
    let samples = taken.samples;
    let (left_sat, left_bloom, left_none, censored) = (
        taken.left_sat,
        taken.left_bloom,
        taken.left_none,
        taken.censored,
    );
    // (Asked for; the default by the image's size may exceed what a small tile's lines
    // cross, and then simply takes every pixel they cross.)
    if opts.count.is_some()
        && (samples.len() as f64) < 0.9 * count as f64
        && matches!(
            opts.strategy,
            Strategy::Line | Strategy::Perpendicular | Strategy::Cross | Strategy::UserLine(_)
        )
    {
        warnings.push(format!(
            "{} samples asked for, {} distinct usable pixels on the line(s): each pixel is used once (a larger image, or --strategy rect, gives more)",
            count,
            samples.len()
        ));
    }
    if left_sat > 0 {
        warnings.push(format!(
            "{left_sat} saturated samples and {left_bloom} in the blooming margin were left out; add a shorter exposure, or keep them as censored samples (--saturated censor)"
        ));
    }
    if samples.len() < 10 {
        // What left the pixels out, each with what would bring them back.
        let why: Vec<String> = [
            (left_sat, "saturated even at the shortest exposure, or read above where the response curve is known (add a shorter exposure, or keep them with --saturated censor)"),
            (left_bloom, "in the blooming margin of saturated pixels"),
            (left_none, "without radiance in a channel (too dark: add a longer exposure)"),
        ]
        .iter()
        .filter(|(k, _)| *k > 0)
        .map(|(k, what)| format!("{k} {what}"))
        .collect();
        let why = if why.is_empty() {
            "the tile shows too few measured pixels".to_string()
        } else {
            format!("of the tile pixels sampled, {}", why.join("; "))
        };
        return Err(SampleError::Input(format!(
            "only {} usable samples: {why}; check hdr/mask.png",
            samples.len()
        )));
    }
    Ok(Sampled {
        strategy: opts.strategy,
        requested: count,
        used: samples.len(),
        samples,
        highlight,
        lines_px,
        tile_pixels: tile.count,
        left_out_saturated: left_sat,
        left_out_bloom: left_bloom,
        left_out_no_radiance: left_none,
        censored,
        saturated: opts.saturated,
        mosaic,
        mosaic_detection,
        mosaic_source,
        warnings,
    })
}

/// The blooming margin: pixels within `b` pixels (Chebyshev) of a saturated one, not
/// saturated themselves.
fn bloom_margin(saturated: &[bool], w: usize, h: usize, b: i64) -> Vec<bool> {
    let mut bloom = vec![false; w * h];
    for (i, s) in saturated.iter().enumerate() {
        if !*s {
            continue;
        }
        let (u, v) = ((i % w) as i64, (i / w) as i64);
        for y in (v - b).max(0)..=(v + b).min(h as i64 - 1) {
            for x in (u - b).max(0)..=(u + b).min(w as i64 - 1) {
                let j = y as usize * w + x as usize;
                bloom[j] = !saturated[j];
            }
        }
    }
    bloom
}

/// Where the samples centre: the radiance's peak on the tile where it is near the mirror
/// point, else the mirror point (or the peak, where the mirror point is off the tile),
/// with a warning that says which; and how much is saturated there.
fn locate_highlight(
    scene: &Scene,
    img: &RadianceImage,
    tile: &TileMap,
    saturated: &[bool],
    warnings: &mut Vec<String>,
) -> Highlight {
    let (w, h) = (img.width, img.height);
    let mirror = scene.mirror_point();
    let predicted_px = scene.project(mirror);
    let found = find_highlight(scene, img, tile, saturated);
    // How far the found peak may sit from the predicted mirror point: a tenth of the
    // tile's size in the image (the peak of a broad lobe times the falloff of the lamp
    // is not exactly at the mirror point; a peak further off is not the highlight).
    let size = (tile.count as f64).sqrt();
    let offset = found.map_or(f64::INFINITY, |f| {
        ((f[0] - predicted_px[0]).powi(2) + (f[1] - predicted_px[1]).powi(2)).sqrt()
    });
    let mirror_on_tile = tile
        .at(
            predicted_px[0].round() as i64,
            predicted_px[1].round() as i64,
        )
        .is_some();
    let found_near_mirror = found.is_some() && offset <= 0.1 * size;
    // Where the peak is not where the geometry puts it, this says so and no more: whether
    // the tile is matte or its lobe broader than the tile is for the fit to tell (the
    // report's warnings name it).
    let centre_px = match found {
        Some(f) if found_near_mirror => f,
        _ => {
            if mirror_on_tile {
                warnings.push(format!(
                    "the radiance does not peak near the mirror point at ({:.0}, {:.0}) px (it peaks {}): the samples are centred on the mirror point",
                    predicted_px[0],
                    predicted_px[1],
                    found.map_or("nowhere on the tile".into(), |f| format!("at ({:.0}, {:.0}), {offset:.0} px away", f[0], f[1]))
                ));
                predicted_px
            } else {
                warnings.push(format!(
                    "the highlight is off the tile: the mirror point ({:.0}, {:.0}) px lies outside the tile's outline, so the samples see only the lobe's flank and n and ks trade off; move the lamp or the camera so the lamp's reflection falls on the tile",
                    predicted_px[0], predicted_px[1]
                ));
                found.unwrap_or(predicted_px)
            }
        }
    };
    let saturated_pixels = (0..w * h)
        .filter(|&i| saturated[i] && tile.points[i].is_some())
        .count();
    let near = 0.2 * size;
    let saturated_at_highlight = (0..w * h)
        .filter(|&i| {
            let (du, dv) = ((i % w) as f64 - centre_px[0], (i / w) as f64 - centre_px[1]);
            saturated[i] && tile.points[i].is_some() && du * du + dv * dv <= near * near
        })
        .count();
    Highlight {
        centre_px,
        found_px: found,
        predicted_px,
        offset_px: offset,
        saturated_pixels,
        saturated_at_highlight,
        mirror_on_tile,
        found_near_mirror,
    }
}

/// The candidate pixels of `opts.strategy` around `centre_px`, in order, each with its
/// position along its line (mm; 0 where there is no line); the lines drawn go to
/// `lines_px`.
fn candidate_pixels(
    scene: &Scene,
    tile: &TileMap,
    opts: &SampleOptions,
    count: usize,
    centre_px: [f64; 2],
    lines_px: &mut Vec<[f64; 4]>,
) -> Result<Vec<(usize, f64)>, SampleError> {
    let mirror = scene.mirror_point();
    let centre_pt = scene.on_plane(centre_px[0], centre_px[1]).unwrap_or(mirror);
    Ok(match opts.strategy {
        Strategy::Line | Strategy::Perpendicular | Strategy::Cross => {
            line_pixels(scene, tile, opts.strategy, count, centre_pt, lines_px)
        }
        Strategy::UserLine(line) => {
            user_line_pixels(scene, tile, line, count, centre_px, lines_px)?
        }
        Strategy::Rect => rect_pixels(scene, tile, count, centre_pt, centre_px),
        Strategy::Random => {
            let all: Vec<usize> = (0..tile.width * tile.height)
                .filter(|&i| tile.points[i].is_some())
                .collect();
            let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(opts.seed);
            let k = count.min(all.len());
            let mut idx: Vec<usize> = rand::seq::index::sample(&mut rng, all.len(), k)
                .into_iter()
                .map(|j| all[j])
                .collect();
            idx.sort_unstable();
            idx.into_iter().map(|i| (i, 0.0)).collect()
        }
    })
}

/// The pixels of the default lines (`strategy` Line, Perpendicular or Cross) through
/// `centre_pt` on the tile.
fn line_pixels(
    scene: &Scene,
    tile: &TileMap,
    strategy: Strategy,
    count: usize,
    centre_pt: [f64; 3],
    lines_px: &mut Vec<[f64; 4]>,
) -> Vec<(usize, f64)> {
    let w = tile.width;
    let d0 = scene.incidence_direction();
    let across = [-d0[1], d0[0]];
    // Samples along the tile line through the centre in direction d, out to the
    // tile's usable edge (walked in 0.1 mm steps), regular in mm.
    let tile_line = |d: [f64; 2], n: usize, lines: &mut Vec<[f64; 4]>| {
        let at = |s: f64| {
            [
                centre_pt[0] + s * d[0],
                centre_pt[1] + s * d[1],
                scene.height,
            ]
        };
        let [s0, s1] = line_reach(scene, tile, centre_pt, d);
        let p0 = scene.project(at(s0));
        let p1 = scene.project(at(s1));
        lines.push([p0[0], p0[1], p1[0], p1[1]]);
        let mut out = Vec::new();
        for k in 0..n {
            let s = if n == 1 {
                0.0
            } else {
                s0 + (s1 - s0) * k as f64 / (n - 1) as f64
            };
            let [u, v] = scene.project(at(s));
            let (u, v) = (u.round() as i64, v.round() as i64);
            if tile.at(u, v).is_some() {
                out.push((v as usize * w + u as usize, s));
            }
        }
        out
    };
    match strategy {
        Strategy::Line => tile_line(d0, count, lines_px),
        Strategy::Perpendicular => tile_line(across, count, lines_px),
        _ => {
            let mut out = tile_line(d0, count.div_ceil(2), lines_px);
            out.extend(tile_line(across, count / 2, lines_px));
            out
        }
    }
}

/// The pixels of a line the user drew, `[u0, v0, u1, v1]` in pixels.
fn user_line_pixels(
    scene: &Scene,
    tile: &TileMap,
    [u0, v0, u1, v1]: [f64; 4],
    count: usize,
    centre_px: [f64; 2],
    lines_px: &mut Vec<[f64; 4]>,
) -> Result<Vec<(usize, f64)>, SampleError> {
    let w = tile.width;
    lines_px.push([u0, v0, u1, v1]);
    let n = count;
    let c = scene.on_plane(centre_px[0], centre_px[1]);
    let mut out = Vec::new();
    for k in 0..n {
        let t = if n == 1 {
            0.5
        } else {
            k as f64 / (n - 1) as f64
        };
        let (u, v) = (u0 + t * (u1 - u0), v0 + t * (v1 - v0));
        let (ui, vi) = (u.round() as i64, v.round() as i64);
        if let Some(p) = tile.at(ui, vi) {
            let s = c.map_or(0.0, |c| {
                ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt()
            });
            out.push((vi as usize * w + ui as usize, s));
        }
    }
    if out.is_empty() {
        return Err(SampleError::Input(format!(
                "the line ({u0}, {v0})-({u1}, {v1}) does not cross the tile: give pixel coordinates on the tile (it spans {} pixels around ({:.0}, {:.0}))",
                tile.count, centre_px[0], centre_px[1]
            )));
    }
    Ok(out)
}

/// The square around the highlight as wide as the default line is long, clipped to the
/// tile, on a regular grid with about `count` pixels.
fn rect_pixels(
    scene: &Scene,
    tile: &TileMap,
    count: usize,
    centre_pt: [f64; 3],
    centre_px: [f64; 2],
) -> Vec<(usize, f64)> {
    let w = tile.width;
    // The square around the highlight as wide as the default line is long, clipped
    // to the tile, on a regular grid with about `count` pixels.
    let d = scene.incidence_direction();
    let half = line_reach(scene, tile, centre_pt, d)
        .iter()
        .map(|&s| {
            let [u, v] = scene.project([
                centre_pt[0] + s * d[0],
                centre_pt[1] + s * d[1],
                scene.height,
            ]);
            ((u - centre_px[0]).powi(2) + (v - centre_px[1]).powi(2)).sqrt()
        })
        .fold(0.0f64, f64::max);
    let (cu, cv) = (centre_px[0].round() as i64, centre_px[1].round() as i64);
    let hh = half.ceil() as i64;
    let inside: Vec<usize> = (cv - hh..=cv + hh)
        .flat_map(|v| (cu - hh..=cu + hh).map(move |u| (u, v)))
        .filter(|&(u, v)| tile.at(u, v).is_some())
        .map(|(u, v)| v as usize * w + u as usize)
        .collect();
    // The grid step whose count is nearest the one asked for.
    let per = |s: usize| inside.len() as f64 / (s * s) as f64;
    let s0 = ((inside.len() as f64 / count as f64).sqrt().floor() as usize).max(1);
    let stride = if (per(s0 + 1) - count as f64).abs() < (per(s0) - count as f64).abs() {
        s0 + 1
    } else {
        s0
    };
    inside
        .into_iter()
        .filter(|&i| {
            let (u, v) = ((i % w) as i64 - cu, (i / w) as i64 - cv);
            u.rem_euclid(stride as i64) == 0 && v.rem_euclid(stride as i64) == 0
        })
        .map(|i| (i, 0.0))
        .collect()
}

/// The samples of the candidate pixels: each pixel once, those saturated, in the blooming
/// margin or with no radiance left out (or kept censored, as `opts.saturated` says), with
/// the counts of each.
struct Taken {
    samples: Vec<PixelSample>,
    left_sat: usize,
    left_bloom: usize,
    left_none: usize,
    censored: usize,
}

fn take_samples(
    scene: &Scene,
    img: &RadianceImage,
    tile: &TileMap,
    opts: &SampleOptions,
    saturated: &[bool],
    bloom: &[bool],
    pixels: Vec<(usize, f64)>,
) -> Result<Taken, SampleError> {
    let (w, nc) = (img.width, img.channels());
    let mut seen = std::collections::HashSet::new();
    let mut samples = Vec::new();
    let (mut left_sat, mut left_bloom, mut left_none, mut censored) = (0, 0, 0, 0);
    for (i, along) in pixels {
        if !seen.insert(i) {
            continue;
        }
        let p = tile.points[i].expect("tile pixel");
        let g = scene.geometry(p);
        let (u, v) = (i % w, i / w);
        let sat = saturated[i];
        match opts.saturated {
            Saturated::Exclude if sat => {
                left_sat += 1;
                continue;
            }
            Saturated::Exclude | Saturated::Censor if bloom[i] => {
                left_bloom += 1;
                continue;
            }
            _ => {}
        }
        let m = &img.mask[nc * i..nc * i + nc];
        if !sat && m.iter().any(|x| *x != MASK_OK) {
            left_none += 1;
            continue;
        }
        if sat && !opts.saturation_level[..nc].iter().all(|x| x.is_finite()) {
            return Err(SampleError::Input(
                "saturated pixels can be kept only when the saturation level is known (the session's hdr/response.json)".into(),
            ));
        }
        // A monochrome sample's channels 1 and 2 hold nothing (no weight).
        let mut radiance = [0.0; 3];
        let mut variance = [f64::INFINITY; 3];
        for c in 0..nc {
            if m[c] == MASK_OK {
                radiance[c] = img.radiance[nc * i + c] as f64;
                variance[c] = img.variance[nc * i + c] as f64;
            } else {
                // Saturated: the level, with one percent for the level's own uncertainty.
                radiance[c] = opts.saturation_level[c];
                variance[c] = (0.01 * opts.saturation_level[c]).powi(2);
            }
        }
        let cens = opts.saturated == Saturated::Censor;
        let is_censored = [0, 1, 2].map(|c| c < nc && cens && m[c] != MASK_OK);
        censored += is_censored.contains(&true) as usize;
        samples.push(PixelSample {
            u,
            v,
            point: p,
            sample: Sample {
                geometry: g,
                radiance,
                variance,
                censored: is_censored,
            },
            along_mm: along,
        });
    }
    Ok(Taken {
        samples,
        left_sat,
        left_bloom,
        left_none,
        censored,
    })
}

/// A demosaicked camera: the channels a sample's photosite did not measure are its
/// neighbours' average, neither a reading of this pixel nor independent of theirs; they
/// get no weight (radiance 0, variance infinite, not censored).
fn keep_own_channels(taken: &mut Taken, mosaic: Mosaic) {
    for p in &mut taken.samples {
        let own = mosaic.native(p.u, p.v);
        let s = &mut p.sample;
        for c in (0..3).filter(|c| *c != own) {
            s.radiance[c] = 0.0;
            s.variance[c] = f64::INFINITY;
            s.censored[c] = false;
        }
    }
    taken.censored = taken
        .samples
        .iter()
        .filter(|p| p.sample.censored.contains(&true))
        .count();
}

#[cfg(test)]
mod tests {
    use super::{count_problem, default_count};

    #[test]
    fn a_sample_count_outside_its_range_is_named() {
        assert_eq!(count_problem(10, None), None);
        assert_eq!(count_problem(100_000, Some(100_000)), None);
        assert_eq!(
            count_problem(9, None).as_deref(),
            Some("must be at least 10 (got 9)")
        );
        assert_eq!(
            count_problem(9, Some(100_000)).as_deref(),
            Some("must be 10 to 100000 (got 9)")
        );
        assert_eq!(
            count_problem(100_001, Some(100_000)).as_deref(),
            Some("must be 10 to 100000 (got 100001)")
        );
    }

    #[test]
    fn the_default_count_keeps_the_samples_density_along_the_lines() {
        // 400 where the defaults were measured, in proportion above, never fewer.
        assert_eq!(default_count(640, 480), 400);
        assert_eq!(default_count(320, 240), 400);
        assert_eq!(default_count(1280, 960), 800);
        assert_eq!(default_count(960, 1280), 800);
        assert_eq!(default_count(1920, 1080), 1200);
        assert_eq!(default_count(4000, 3000), 2500);
    }
}
