//! A demosaicked camera's colour filter layout, read from the radiance's own noise.
//!
//! Most colour cameras measure one channel per photosite (a Bayer mosaic) and interpolate
//! the other two from the neighbours. An interpolated value is the neighbours' average: it
//! smooths a highlight a few pixels wide differently in each channel (the second scene
//! family's Bayer cameras moved a sharp Phong lobe's n by −0.9% where the true radiance at
//! the pixels gives −0.3%, ks/kd by up to 9%; docs/results/accuracy.md), and its noise is
//! the neighbours' noise again, so the fit would count the same reading up to three times.
//! Where the layout is known, each sample keeps only its photosite's own channel.
//!
//! The layout shows in the noise. A value measured at its photosite carries its own noise;
//! one interpolated from two (or four) neighbours carries half (a quarter) of their
//! variance, and its difference from the mean of its eight neighbours is small. So the
//! median squared difference, relative to the value, per channel and per position in the
//! 2x2 cell, is largest where the channel is measured: by about 4 (red and blue, against
//! the diagonal average) and 2 or more elsewhere on 12–16-bit cameras, 2.8 on an 8-bit
//! one behind a tone curve; about 1 everywhere on a camera that measures every channel at
//! every pixel.

use crate::hdr::merge::MASK_OK;
use serde::{Deserialize, Serialize};

/// The colour of each photosite of the 2x2 cell, named by its top row then its bottom row
/// (the image's top-left pixel first).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Mosaic {
    Rggb,
    Grbg,
    Gbrg,
    Bggr,
}

impl Mosaic {
    pub const ALL: [Mosaic; 4] = [Mosaic::Rggb, Mosaic::Grbg, Mosaic::Gbrg, Mosaic::Bggr];

    /// The channel (0 R, 1 G, 2 B) the photosite at pixel (u, v) measures.
    pub fn native(self, u: usize, v: usize) -> usize {
        let cell = match self {
            Mosaic::Rggb => [0, 1, 1, 2],
            Mosaic::Grbg => [1, 0, 2, 1],
            Mosaic::Gbrg => [1, 2, 0, 1],
            Mosaic::Bggr => [2, 1, 1, 0],
        };
        cell[2 * (v % 2) + (u % 2)]
    }

    pub fn name(self) -> &'static str {
        match self {
            Mosaic::Rggb => "RGGB",
            Mosaic::Grbg => "GRBG",
            Mosaic::Gbrg => "GBRG",
            Mosaic::Bggr => "BGGR",
        }
    }

    /// The layout whose red photosite sits at position `p` (2 * row + column) of the cell.
    fn with_red_at(p: usize) -> Mosaic {
        match p {
            0 => Mosaic::Rggb,
            1 => Mosaic::Grbg,
            2 => Mosaic::Gbrg,
            _ => Mosaic::Bggr,
        }
    }
}

/// Whether samples keep only their photosite's channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MosaicChoice {
    /// Read the layout from the radiance's noise ([`detect`]).
    #[default]
    Auto,
    /// Every channel of every pixel is a measurement (a three-chip or Foveon camera, or
    /// the user's say).
    Off,
    /// This layout, as the camera's documentation gives it.
    Given(Mosaic),
}

/// What [`detect`] found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Detection {
    /// The layout, where every channel shows it.
    pub layout: Option<Mosaic>,
    /// The weakest channel's contrast: the median squared residual at the positions its
    /// layout measures over the largest at the positions it interpolates (about 1 where
    /// nothing is interpolated; [`DETECTED`] and more where a layout was found).
    pub contrast: f64,
    /// Pixels whose neighbourhood entered the medians.
    pub pixels: usize,
}

/// Contrast from which a layout counts as found: 2.8 and more on the second scene family's
/// 8-bit Bayer cameras, 0.98–1.02 on its cameras without a mosaic and on the simulated
/// lab's.
pub const DETECTED: f64 = 1.5;

/// Fewest pixels per cell position a detection stands on.
const MIN_PIXELS: usize = 500;

/// Largest number of pixels read (rows are taken in pairs, evenly spread, beyond it).
const MAX_PIXELS: usize = 1_000_000;

/// The layout of a demosaicked camera, from the radiance's noise (see the module's text):
/// `radiance` and `mask` RGB interleaved, `w` x `h` pixels. `None` for a monochrome image
/// or one too small or too masked to tell.
pub fn detect(w: usize, h: usize, radiance: &[f32], mask: &[u8]) -> Option<Detection> {
    if w < 8 || h < 8 || radiance.len() != 3 * w * h || mask.len() != radiance.len() {
        return None;
    }
    let ok = |i: usize| {
        mask[3 * i..3 * i + 3].iter().all(|m| *m == MASK_OK)
            && radiance[3 * i..3 * i + 3]
                .iter()
                .all(|x| x.is_finite() && *x > 0.0)
    };
    // Row pairs taken: every k-th, so that at most MAX_PIXELS pixels are read.
    let pairs = (h - 2) / 2;
    let k = (w * h).div_ceil(MAX_PIXELS).max(1);
    let mut buckets: [[Vec<f32>; 4]; 3] = Default::default();
    for pair in (0..pairs).step_by(k) {
        for v in [1 + 2 * pair, 2 + 2 * pair] {
            if v + 1 >= h {
                continue;
            }
            for u in 1..w - 1 {
                let i = v * w + u;
                let around = [
                    i - w - 1,
                    i - w,
                    i - w + 1,
                    i - 1,
                    i + 1,
                    i + w - 1,
                    i + w,
                    i + w + 1,
                ];
                if !ok(i) || !around.iter().all(|j| ok(*j)) {
                    continue;
                }
                let p = 2 * (v % 2) + (u % 2);
                for (c, b) in buckets.iter_mut().enumerate() {
                    let x = radiance[3 * i + c] as f64;
                    let mean = around
                        .iter()
                        .map(|j| radiance[3 * j + c] as f64)
                        .sum::<f64>()
                        / 8.0;
                    let r = (x - mean) / x;
                    b[p].push((r * r) as f32);
                }
            }
        }
    }
    let pixels = buckets[0].iter().map(Vec::len).min().unwrap_or(0);
    if pixels < MIN_PIXELS {
        return None;
    }
    let s: Vec<[f64; 4]> = buckets
        .iter_mut()
        .map(|b| {
            let mut out = [0.0; 4];
            for (o, v) in out.iter_mut().zip(b.iter_mut()) {
                *o = median(v);
            }
            out
        })
        .collect();
    if s.iter().flatten().any(|x| !(x.is_finite() && *x > 0.0)) {
        // Quantised flat: no noise to read.
        return None;
    }
    let argmax = |a: &[f64; 4]| (0..4).max_by(|x, y| a[*x].total_cmp(&a[*y])).unwrap_or(0);
    let (red, blue) = (argmax(&s[0]), argmax(&s[2]));
    // Green is measured on the other diagonal: positions 0 and 3, or 1 and 2.
    let green = if red == 0 || red == 3 { [1, 2] } else { [0, 3] };
    let single = |a: &[f64; 4], at: usize| {
        a[at]
            / (0..4)
                .filter(|p| *p != at)
                .map(|p| a[p])
                .fold(0.0, f64::max)
    };
    let pair = |a: &[f64; 4], at: [usize; 2]| {
        a[at[0]].min(a[at[1]])
            / (0..4)
                .filter(|p| !at.contains(p))
                .map(|p| a[p])
                .fold(0.0, f64::max)
    };
    // Red and blue diagonal to each other (so green's pair is the rest).
    let consistent = blue == 3 - red;
    let contrast = single(&s[0], red)
        .min(single(&s[2], blue))
        .min(pair(&s[1], green));
    let contrast = if consistent {
        contrast
    } else {
        contrast.min(1.0)
    };
    Some(Detection {
        layout: (consistent && contrast >= DETECTED).then(|| Mosaic::with_red_at(red)),
        contrast,
        pixels,
    })
}

fn median(v: &mut [f32]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let m = v.len() / 2;
    let (_, x, _) = v.select_nth_unstable_by(m, |a, b| a.total_cmp(b));
    *x as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_xoshiro::Xoshiro256PlusPlus;

    /// A smooth scene (a slow gradient and a soft spot, colours apart), photographed with
    /// 1% noise per photosite: measured through `layout` and demosaicked bilinearly (each
    /// missing channel the mean of its nearest photosites of that colour), or, with
    /// `None`, measured at every pixel in every channel.
    fn photo(layout: Option<Mosaic>, w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let truth = |u: usize, v: usize, c: usize| {
            let (x, y) = (u as f64 / w as f64, v as f64 / h as f64);
            let spot = (-((x - 0.5).powi(2) + (y - 0.4).powi(2)) / 0.02).exp();
            (0.2 + 0.3 * x + 0.1 * y + spot) * [0.8, 1.0, 0.6][c]
        };
        let mut noisy = |x: f64| x * (1.0 + 0.01 * (rng.random::<f64>() * 2.0 - 1.0) * 3f64.sqrt());
        let mut out = vec![0.0f32; 3 * w * h];
        match layout {
            None => {
                for v in 0..h {
                    for u in 0..w {
                        for c in 0..3 {
                            out[3 * (v * w + u) + c] = noisy(truth(u, v, c)) as f32;
                        }
                    }
                }
            }
            Some(m) => {
                let mut raw = vec![0.0f64; w * h];
                for v in 0..h {
                    for u in 0..w {
                        raw[v * w + u] = noisy(truth(u, v, m.native(u, v)));
                    }
                }
                for v in 0..h {
                    for u in 0..w {
                        for c in 0..3 {
                            // The nearest photosites of colour c (itself, two or four).
                            let (mut s, mut k) = (0.0, 0);
                            for dv in -1i64..=1 {
                                for du in -1i64..=1 {
                                    let (x, y) = (u as i64 + du, v as i64 + dv);
                                    if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                                        continue;
                                    }
                                    let (x, y) = (x as usize, y as usize);
                                    if m.native(x, y) != c {
                                        continue;
                                    }
                                    if m.native(u, v) == c && (du, dv) != (0, 0) {
                                        continue;
                                    }
                                    // Green at a red or blue site: the four edge neighbours.
                                    if c == 1 && du != 0 && dv != 0 {
                                        continue;
                                    }
                                    s += raw[y * w + x];
                                    k += 1;
                                }
                            }
                            out[3 * (v * w + u) + c] = (s / k as f64) as f32;
                        }
                    }
                }
            }
        }
        out
    }

    /// A mask with every value measured.
    fn measured(radiance: &[f32]) -> Vec<u8> {
        vec![MASK_OK; radiance.len()]
    }

    #[test]
    fn each_layout_is_read_from_a_demosaicked_photo_and_none_from_a_full_one() {
        let (w, h) = (96, 80);
        for (seed, m) in Mosaic::ALL.into_iter().enumerate() {
            let rad = photo(Some(m), w, h, seed as u64);
            let mask = measured(&rad);
            let d = detect(w, h, &rad, &mask).expect("enough pixels");
            assert_eq!(d.layout, Some(m), "{m:?}: {d:?}");
            assert!(d.contrast > 1.8, "{m:?}: {d:?}");
        }
        let rad = photo(None, w, h, 9);
        let mask = measured(&rad);
        let d = detect(w, h, &rad, &mask).expect("enough pixels");
        assert_eq!(d.layout, None, "{d:?}");
        assert!((0.8..1.25).contains(&d.contrast), "{d:?}");
    }

    #[test]
    fn a_masked_or_tiny_image_tells_nothing() {
        let (w, h) = (96, 80);
        let rad = photo(Some(Mosaic::Rggb), w, h, 1);
        let mask = vec![crate::hdr::merge::MASK_SATURATED; rad.len()];
        assert_eq!(detect(w, h, &rad, &mask), None);
        assert_eq!(detect(4, 4, &rad[..48], &mask[..48]), None);
    }

    #[test]
    fn the_layouts_put_red_and_blue_on_one_diagonal_and_green_on_the_other() {
        for m in Mosaic::ALL {
            let cell: Vec<usize> = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .iter()
                .map(|&(u, v)| m.native(u, v))
                .collect();
            let (a, b) = if cell[0] == 1 {
                ([0, 3], [1, 2])
            } else {
                ([1, 2], [0, 3])
            };
            assert_eq!((cell[a[0]], cell[a[1]]), (1, 1), "{m:?}");
            assert_eq!(cell[b[0]] + cell[b[1]], 2, "{m:?}");
            assert_ne!(cell[b[0]], 1, "{m:?}");
            assert_eq!(
                Mosaic::with_red_at(cell.iter().position(|c| *c == 0).unwrap()),
                m
            );
            assert_eq!(m.native(2, 2), m.native(0, 0));
        }
    }
}
