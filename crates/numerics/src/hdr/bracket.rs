//! The shared types of the HDR half: a bracket of frames ([`Bracket`]) and the dark frames'
//! medians. It names nothing else of `hdr` but its errors, so the merge and the response
//! recovery both build on it without a circle.

use glint_format::image::Pixels;

use super::error::MergeError;

/// One frame of a bracket.
#[derive(Debug, Clone)]
pub struct BracketFrame {
    /// Where it came from (for messages).
    pub name: String,
    pub exposure_us: f64,
    /// RGB interleaved, or one sample a pixel (a monochrome camera).
    pub pixels: Pixels,
}

impl BracketFrame {
    /// The frame's readings at `pixels` only (pixel indices, row-major; `channels` samples
    /// a pixel), in that order: one row of them, to merge a few pixels again.
    pub fn pick(&self, pixels: &[usize], channels: usize) -> BracketFrame {
        let idx = pixels
            .iter()
            .flat_map(|&p| channels * p..channels * p + channels);
        BracketFrame {
            name: self.name.clone(),
            exposure_us: self.exposure_us,
            pixels: match &self.pixels {
                Pixels::U8(p) => Pixels::U8(idx.map(|i| p[i]).collect()),
                Pixels::U16(p) => Pixels::U16(idx.map(|i| p[i]).collect()),
            },
        }
    }
}

/// Frames of one scene at several exposures, all the same size, bit depth and channels.
#[derive(Debug, Clone)]
pub struct Bracket {
    pub width: usize,
    pub height: usize,
    pub bit_depth: u8,
    /// Samples a pixel: 3 (RGB interleaved) or 1 (a monochrome camera).
    pub channels: usize,
    pub frames: Vec<BracketFrame>,
}

impl Bracket {
    /// The median step between neighbouring exposures, in ln (None for fewer than two
    /// distinct exposures).
    pub fn step(&self) -> Option<f64> {
        let mut t: Vec<f64> = self
            .frames
            .iter()
            .map(|f| f.exposure_us)
            .filter(|t| t.is_finite() && *t > 0.0)
            .collect();
        t.sort_by(f64::total_cmp);
        t.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-6);
        let mut steps: Vec<f64> = t.windows(2).map(|w| (w[1] / w[0]).ln()).collect();
        steps.sort_by(f64::total_cmp);
        steps.get(steps.len() / 2).copied()
    }

    /// An empty RGB bracket of this size (e.g. no dark frames).
    pub fn empty(width: usize, height: usize, bit_depth: u8) -> Self {
        Bracket::empty_with(width, height, bit_depth, 3)
    }

    /// An empty bracket of this size with `channels` samples a pixel.
    pub fn empty_with(width: usize, height: usize, bit_depth: u8, channels: usize) -> Self {
        Bracket {
            width,
            height,
            bit_depth,
            channels,
            frames: Vec::new(),
        }
    }

    /// Build an RGB bracket, checking that every frame has the same size and depth.
    pub fn new(
        width: usize,
        height: usize,
        bit_depth: u8,
        frames: Vec<BracketFrame>,
    ) -> Result<Self, MergeError> {
        Bracket::new_with(width, height, bit_depth, 3, frames)
    }

    /// Build a bracket of `channels` samples a pixel (3: RGB, 1: monochrome), checking
    /// that every frame has the same size and depth.
    pub fn new_with(
        width: usize,
        height: usize,
        bit_depth: u8,
        channels: usize,
        frames: Vec<BracketFrame>,
    ) -> Result<Self, MergeError> {
        if channels != 1 && channels != 3 {
            return Err(MergeError::Input(format!(
                "{channels} channels: a bracket's frames are RGB (3) or monochrome (1)"
            )));
        }
        for f in &frames {
            let bits = match f.pixels {
                Pixels::U8(_) => 8,
                Pixels::U16(_) => 16,
            };
            if bits != bit_depth {
                return Err(MergeError::Input(format!(
                    "{} is {bits}-bit but the bracket is {bit_depth}-bit; all frames of a bracket must have one bit depth",
                    f.name
                )));
            }
            if f.pixels.len() != width * height * channels {
                return Err(MergeError::Input(format!(
                    "{} does not have {width}x{height} {} pixels; all frames of a bracket must have one size",
                    f.name,
                    if channels == 1 { "grey" } else { "RGB" }
                )));
            }
        }
        Ok(Bracket {
            width,
            height,
            bit_depth,
            channels,
            frames,
        })
    }

    pub fn max_value(&self) -> u32 {
        (1u32 << self.bit_depth) - 1
    }

    /// The value at which each channel clips: [`Bracket::max_value`], or lower where the
    /// camera saturates below its format's top (a 12-bit sensor's values shifted into 16
    /// bits clip at 65520, a sensor whose black level was subtracted after clipping clips
    /// at full scale less the black level). Read off the longest exposure, one pass over it:
    /// the highest value present, where at least 0.05% of the pixels (and 20) hold exactly
    /// it and it holds at least five times as many as any of the eight occupied values below
    /// it (a pile-up, not the top of a smooth histogram).
    pub fn clip_levels(&self) -> Vec<u32> {
        let max = self.max_value();
        let Some(longest) = self
            .frames
            .iter()
            .max_by(|a, b| a.exposure_us.total_cmp(&b.exposure_us))
        else {
            return vec![max; self.channels];
        };
        let mut hist = vec![vec![0usize; max as usize + 1]; self.channels];
        let mut count = |k: usize, v: u32| hist[k % self.channels][v as usize] += 1;
        match &longest.pixels {
            Pixels::U8(v) => v.iter().enumerate().for_each(|(k, x)| count(k, *x as u32)),
            Pixels::U16(v) => v.iter().enumerate().for_each(|(k, x)| count(k, *x as u32)),
        }
        let n = self.width * self.height;
        hist.iter()
            .map(|h| {
                let mut occupied = h.iter().enumerate().rev().filter(|(_, c)| **c > 0);
                let Some((top, &at_top)) = occupied.next() else {
                    return max;
                };
                let top = top as u32;
                if top >= max || at_top < 20 || (at_top as f64) < 5e-4 * n as f64 {
                    return max;
                }
                let below = occupied.take(8).map(|(_, c)| *c).max().unwrap_or(0);
                if at_top >= 5 * below.max(1) {
                    top
                } else {
                    max
                }
            })
            .collect()
    }

    /// Value of pixel `p` (y * width + x), channel `c`, in frame `j`.
    #[inline]
    pub fn value(&self, j: usize, p: usize, c: usize) -> u32 {
        let k = p * self.channels + c;
        match &self.frames[j].pixels {
            Pixels::U8(v) => v[k] as u32,
            Pixels::U16(v) => v[k] as u32,
        }
    }

    /// Median value of channel `c` in frame `j`.
    pub fn channel_median(&self, j: usize, c: usize) -> f64 {
        channel_median(&self.frames[j].pixels, self.bit_depth, self.channels, c)
    }

    /// Exposure times must be positive, with at least two different ones. Several frames
    /// of one exposure (a rig's `frames_per_exposure`) are fine: each is one more reading.
    pub fn check_exposures(&self) -> Result<(), MergeError> {
        if self.frames.len() < 2 {
            return Err(MergeError::Input(format!(
                "a bracket needs at least 2 exposures, got {}",
                self.frames.len()
            )));
        }
        for f in &self.frames {
            if !(f.exposure_us.is_finite() && f.exposure_us > 0.0) {
                return Err(MergeError::Input(format!(
                    "{}: exposure time {} µs is not positive",
                    f.name,
                    show_us(f.exposure_us)
                )));
            }
            if !(MIN_EXPOSURE_US..=MAX_EXPOSURE_US).contains(&f.exposure_us) {
                return Err(MergeError::Input(format!(
                    "{}: exposure time {} µs is outside the 1 µs .. 1 hour an exposure can be; the session's manifest (or the times given to glint import) is wrong",
                    f.name,
                    show_us(f.exposure_us)
                )));
            }
        }
        let first = self.frames[0].exposure_us;
        if self
            .frames
            .iter()
            .all(|f| (f.exposure_us / first - 1.0).abs() < 1e-6)
        {
            return Err(MergeError::Input(format!(
                "every frame has the same exposure time ({first} µs); a bracket needs at least two different times"
            )));
        }
        Ok(())
    }

    /// Sort by exposure time, shortest first.
    pub fn sort(&mut self) {
        self.frames
            .sort_by(|a, b| a.exposure_us.total_cmp(&b.exposure_us));
    }
}

/// Shortest exposure time a bracket may have, µs.
pub const MIN_EXPOSURE_US: f64 = 1.0;
/// Longest exposure time a bracket may have, µs (1 hour).
pub const MAX_EXPOSURE_US: f64 = 3.6e9;

/// One dark frame as response recovery uses it: its exposure and each channel's median
/// value (one channel for a monochrome camera: the rest 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DarkMedian {
    pub exposure_us: f64,
    pub median: [f64; 3],
}

impl DarkMedian {
    /// The medians of frame `f` (`bit_depth`, `channels` samples a pixel).
    pub fn of(f: &BracketFrame, bit_depth: u8, channels: usize) -> Self {
        let mut median = [0.0; 3];
        for (c, m) in median.iter_mut().enumerate().take(channels) {
            *m = channel_median(&f.pixels, bit_depth, channels, c);
        }
        DarkMedian {
            exposure_us: f.exposure_us,
            median,
        }
    }

    /// The medians of every frame of a bracket.
    pub fn of_bracket(b: &Bracket) -> Vec<DarkMedian> {
        b.frames
            .iter()
            .map(|f| DarkMedian::of(f, b.bit_depth, b.channels))
            .collect()
    }
}

/// Median value of channel `c` of `pixels` (`channels` samples a pixel).
fn channel_median(pixels: &Pixels, bit_depth: u8, channels: usize, c: usize) -> f64 {
    let levels = 1usize << bit_depth;
    let mut hist = vec![0u64; levels];
    let mut n = 0u64;
    match pixels {
        Pixels::U8(v) => v.iter().skip(c).step_by(channels).for_each(|z| {
            hist[*z as usize] += 1;
            n += 1;
        }),
        Pixels::U16(v) => v.iter().skip(c).step_by(channels).for_each(|z| {
            hist[(*z as usize).min(levels - 1)] += 1;
            n += 1;
        }),
    }
    let mut acc = 0;
    for (z, h) in hist.iter().enumerate() {
        acc += h;
        if acc * 2 >= n {
            return z as f64;
        }
    }
    0.0
}

/// An exposure time (µs) for a message: plain where people read it so, else `1e300`.
pub fn show_us(x: f64) -> String {
    if x == 0.0 || (1e-3..1e12).contains(&x.abs()) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hdr::response::{recover, RecoverOptions};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    use rand_xoshiro::Xoshiro256PlusPlus;

    /// A 16-bit bracket of a linear camera whose 12-bit readings are shifted up by four
    /// bits (a black level of 64), clipping at 4095 x 16 = 65520: a smooth gradient of
    /// radiance with read noise, seeded.
    fn twelve_bits_in_sixteen(times: &[f64]) -> Bracket {
        let (w, h) = (160usize, 120usize);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(12);
        let noise = Normal::new(0.0, 2.0).unwrap();
        let frames = times
            .iter()
            .map(|t| {
                let mut v = Vec::with_capacity(w * h * 3);
                for y in 0..h {
                    for x in 0..w {
                        let radiance = 0.05 * (1.0 + 40.0 * (x + y * w) as f64 / (w * h) as f64);
                        for c in 0..3 {
                            let e = radiance * t * (0.6 + 0.2 * c as f64)
                                + 64.0
                                + noise.sample(&mut rng);
                            let dn = e.round().clamp(0.0, 4095.0) as u16;
                            v.push(dn << 4);
                        }
                    }
                }
                BracketFrame {
                    name: format!("{t} us"),
                    exposure_us: *t,
                    pixels: Pixels::U16(v),
                }
            })
            .collect();
        Bracket::new(w, h, 16, frames).unwrap()
    }

    #[test]
    fn a_camera_clipping_below_its_formats_top_is_found_and_its_clip_counts_as_saturated() {
        let b = twelve_bits_in_sixteen(&[100.0, 400.0, 1600.0, 6400.0]);
        assert_eq!(b.clip_levels(), vec![65520; 3]);
        let r = recover(
            &b,
            &Bracket::empty(b.width, b.height, 16),
            &RecoverOptions::default(),
        )
        .unwrap();
        for (c, ch) in r.channels.iter().enumerate() {
            assert!(
                ch.valid_max < 65520,
                "channel {c}: valid to {}",
                ch.valid_max
            );
            assert!(ch.valid_min < ch.valid_max);
        }
        // Exposure ratios between frames come out as the times' (4x) on pixels read in
        // both of the two shortest frames, well inside the valid range.
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for p in (0..b.width * b.height).step_by(7) {
            let (z0, z1) = (b.value(0, p, 1), b.value(1, p, 1));
            if z0 > 8000 && z1 < 60000 {
                let q = r.exposure(1, z1 as f64) / r.exposure(1, z0 as f64);
                lo = lo.min(q);
                hi = hi.max(q);
            }
        }
        assert!(lo > 3.6 && hi < 4.4, "ratios {lo}..{hi}");
    }

    #[test]
    fn a_camera_clipping_at_its_formats_top_or_not_at_all_keeps_the_top() {
        // Most of the longest frame at 65535, the format's top.
        let mut b = twelve_bits_in_sixteen(&[100.0, 6400.0]);
        for f in &mut b.frames {
            if let Pixels::U16(v) = &mut f.pixels {
                for x in v.iter_mut() {
                    if *x == 65520 {
                        *x = 65535;
                    }
                }
            }
        }
        assert_eq!(b.clip_levels()[0], 65535);
        // Nothing clips: the brightest value is the top of a smooth histogram.
        let b = twelve_bits_in_sixteen(&[100.0]);
        assert_eq!(b.clip_levels()[1], 65535);
    }
    /// A Bayer camera (RGGB, 12-bit readings shifted to 16 bits, black level 64) of a
    /// gradient with a bright spot that clips in the longer frames, demosaicked bilinearly
    /// from the clipped photosites, as a camera's pipeline does: beside each clipped
    /// photosite the interpolated channels read too low, neither clipped nor measured.
    fn demosaicked(times: &[f64]) -> Bracket {
        let (w, h) = (192usize, 144usize);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(21);
        let noise = Normal::new(0.0, 2.0).unwrap();
        let colour = |x: usize, y: usize| match (y % 2, x % 2) {
            (0, 0) => 0,
            (1, 1) => 2,
            _ => 1,
        };
        let frames = times
            .iter()
            .map(|t| {
                let mut raw = vec![0.0f64; w * h];
                for y in 0..h {
                    for x in 0..w {
                        let (dx, dy) = (x as f64 - 96.0, y as f64 - 72.0);
                        let radiance = 0.05 * (1.0 + 30.0 * (x + y * w) as f64 / (w * h) as f64)
                            + 40.0 * (-(dx * dx + dy * dy) / (2.0 * 12.0f64.powi(2))).exp();
                        let e = radiance * t * (0.6 + 0.2 * colour(x, y) as f64)
                            + 64.0
                            + noise.sample(&mut rng);
                        raw[y * w + x] = e.round().clamp(0.0, 4095.0);
                    }
                }
                let mut v = Vec::with_capacity(w * h * 3);
                for y in 0..h {
                    for x in 0..w {
                        for c in 0..3 {
                            let (mut sum, mut n) = (0.0, 0.0);
                            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                                    if colour(xx, yy) == c
                                        && (colour(x, y) != c || (xx, yy) == (x, y))
                                    {
                                        sum += raw[yy * w + xx];
                                        n += 1.0;
                                    }
                                }
                            }
                            v.push(((sum / n).round() as u16) << 4);
                        }
                    }
                }
                BracketFrame {
                    name: format!("{t} us"),
                    exposure_us: *t,
                    pixels: Pixels::U16(v),
                }
            })
            .collect();
        Bracket::new(w, h, 16, frames).unwrap()
    }

    #[test]
    fn a_demosaicked_linear_camera_with_a_clipped_spot_is_recovered_linear() {
        // Readings beside clipped photosites count as clipped: the curve stays linear and
        // the exposure ratios come out as the times' (the second scene family's Bayer
        // cameras got a bent polynomial from them, 1.8-3.8% off the true radiance).
        let b = demosaicked(&[100.0, 400.0, 1600.0]);
        let r = recover(
            &b,
            &Bracket::empty(b.width, b.height, 16),
            &RecoverOptions::default(),
        )
        .unwrap();
        assert_eq!(
            r.model,
            crate::hdr::response::Model::Linear,
            "{:?}",
            r.choice
        );
        // The exposure ratio of every two neighbouring frames, over the pixels read well
        // in both (a median: single readings carry their noise).
        for c in 0..3 {
            for j in 0..2 {
                let mut q: Vec<f64> = (0..b.width * b.height)
                    .filter_map(|p| {
                        let (z0, z1) = (b.value(j, p, c), b.value(j + 1, p, c));
                        (z0 > 4000 && z1 < 60000)
                            .then(|| r.exposure(c, z1 as f64) / r.exposure(c, z0 as f64))
                    })
                    .collect();
                assert!(q.len() > 500, "channel {c}: {} pixels", q.len());
                q.sort_by(f64::total_cmp);
                let m = q[q.len() / 2];
                assert!(
                    (m / 4.0 - 1.0).abs() < 0.01,
                    "channel {c}, frames {j}, {}: ratio {m}",
                    j + 1
                );
            }
        }
    }
}
