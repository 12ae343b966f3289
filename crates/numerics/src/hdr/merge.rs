//! The merge: frames of a bracket -> radiance, its variance, and a mask.
//!
//! Every reading z of a frame with exposure t (seconds) is one estimate of the pixel's
//! radiance, X = (E(z) - D) / t, with variance V(z) / t^2, where E is the response, D the
//! dark level at that exposure and V the response's noise model (shot + read +
//! quantisation, in exposure units). The merge is the inverse-variance weighted mean
//! X = sum(t E / V) / sum(t^2 / V), whose variance is 1 / sum(t^2 / V) (Granados et al.
//! 2010; Hanji et al. 2020). Both sums are per-frame lookup tables indexed by z, built once
//! per frame, so a frame costs two table look-ups and two additions per sample: no log, no
//! exp, no division until the end.
//!
//! Readings outside the response's valid range carry no radiance: a pixel with no valid
//! reading in any frame is flagged, saturated or too dark, and gets no value (NaN).
//!
//! [`Merger`] folds frames in one at a time as they arrive (memory: two floats and a flag
//! byte per sample, whatever the number of exposures); [`merge`] does the same work with
//! all frames at hand, reading each frame once and writing each output once.

use rayon::prelude::*;

pub use super::bracket::show_us;
use super::bracket::{Bracket, BracketFrame};
use super::error::MergeError;
use super::response::Response;
use glint_format::image::Pixels;

/// Mask values, per pixel and channel.
pub const MASK_OK: u8 = 0;
/// Saturated in every frame: the radiance is above what the shortest exposure can show.
pub const MASK_SATURATED: u8 = 1;
/// Too dark in every frame.
pub const MASK_DARK: u8 = 2;

const FLAG_SAT: u8 = 1;
const FLAG_DARK: u8 = 2;

/// Per value: the two sums' increments, or (0, 0) and a flag for values with no radiance.
#[derive(Clone, Copy, Default)]
struct Entry {
    num: f32,
    den: f32,
}

/// Lookup tables of one frame: for each value, the three channels' increments and flags.
/// For a monochrome response the one channel's are in all three slots, so that the merge's
/// loops, which take samples three at a time and look sample k up in slot k % 3, serve
/// one-channel frames unchanged.
struct FrameLut {
    entries: Vec<[Entry; 3]>,
    flags: Vec<[u8; 3]>,
}

/// Largest increment a frame may add to a sum (and largest radiance a reading may stand
/// for): far enough below `f32::MAX` that a million frames' sums stay finite.
const LIMIT: f32 = f32::MAX / (1 << 20) as f32;

impl FrameLut {
    /// The tables of frame `name` at `exposure_us`. Refused, naming the frame and its
    /// exposure, when a reading in the valid range would add a non-finite increment, or
    /// one so small or so large that the merge's sums underflow or overflow (an exposure
    /// of 1e-300 s or 1e300 s), or stand for a radiance beyond `f32` (a response with a
    /// non-finite or non-positive value): so a merge that passes never has a non-finite
    /// radiance or variance where its mask says it measured one.
    fn new(r: &Response, name: &str, exposure_us: f64, dark: [f64; 3]) -> Result<Self, MergeError> {
        let t = exposure_us * 1e-6;
        if !(t.is_finite() && t > 0.0) {
            return Err(MergeError::Input(format!(
                "{name}: exposure time {} µs is not a positive number; it cannot be merged",
                show_us(exposure_us)
            )));
        }
        let levels = r.max_value() as usize + 1;
        let mut entries = vec![[Entry::default(); 3]; levels];
        let mut flags = vec![[0u8; 3]; levels];
        let nc = r.channels.len();
        for c in 0..nc {
            let ch = &r.channels[c];
            for z in 0..levels {
                if (z as u32) < ch.valid_min {
                    flags[z][c] = FLAG_DARK;
                } else if (z as u32) > ch.valid_max {
                    flags[z][c] = FLAG_SAT;
                } else {
                    let raw = r.exposure(c, z as f64);
                    let e = raw - dark[c];
                    let v = r.exposure_variance(c, z as f64);
                    let entry = Entry {
                        num: (t * e / v) as f32,
                        den: (t * t / v) as f32,
                    };
                    if !(raw.is_finite() && v.is_finite() && v > 0.0 && dark[c].is_finite()) {
                        return Err(MergeError::Input(format!(
                            "{name} ({} µs): the response gives value {z} of channel {} exposure {raw:e}, variance {v:e} and dark level {:e}, which the merge cannot use (not finite or not positive); recover the response again (glint response)",
                            show_us(exposure_us),
                            r.channel_name(c),
                            dark[c]
                        )));
                    }
                    let ratio = entry.num / entry.den;
                    let ok = entry.num.abs() <= LIMIT
                        && entry.den >= f32::MIN_POSITIVE
                        && entry.den <= LIMIT
                        && ratio.abs() <= LIMIT;
                    if !ok {
                        return Err(MergeError::Input(format!(
                            "{name}: exposure time {} µs ({:e} s) takes the merge beyond floating point (value {z} of channel {} stands for radiance {:e} with weight {:e}); the exposure time is wrong: check the session's manifest (or the times given to glint import)",
                            show_us(exposure_us),
                            t,
                            r.channel_name(c),
                            e / t,
                            t * t / v
                        )));
                    }
                    entries[z][c] = entry;
                }
            }
        }
        if nc == 1 {
            for (e, f) in entries.iter_mut().zip(flags.iter_mut()) {
                *e = [e[0]; 3];
                *f = [f[0]; 3];
            }
        }
        Ok(FrameLut { entries, flags })
    }
}

/// The merged result.
#[derive(Debug, Clone)]
pub struct Merged {
    pub width: usize,
    pub height: usize,
    /// Samples a pixel: 3 (RGB) or 1 (monochrome).
    pub channels: usize,
    /// Relative radiance (exposure units per second), RGB interleaved or one sample a
    /// pixel; NaN where masked.
    pub radiance: Vec<f32>,
    /// Variance of `radiance`; NaN where masked.
    pub variance: Vec<f32>,
    /// [`MASK_OK`], [`MASK_SATURATED`] or [`MASK_DARK`] per sample.
    pub mask: Vec<u8>,
}

impl Merged {
    /// Counts of (ok, saturated, too dark) samples.
    pub fn counts(&self) -> [usize; 3] {
        let mut n = [0; 3];
        for m in &self.mask {
            n[*m as usize] += 1;
        }
        n
    }
}

/// Dark level per frame and channel (exposure units), from a dark frame of the same
/// exposure where there is one: the mean exposure the dark frame's readings stand for
/// (readings below the valid range count as 0). A monochrome response's one level is in
/// all three places.
pub fn dark_levels(r: &Response, b: &Bracket, darks: &Bracket) -> Vec<[f64; 3]> {
    b.frames
        .iter()
        .map(|f| {
            darks
                .frames
                .iter()
                .find(|d| same_exposure(d.exposure_us, f.exposure_us))
                .map_or([0.0; 3], |d| dark_level(r, &d.pixels))
        })
        .collect()
}

/// Whether a dark frame at `dark_us` is taken for a frame at `us` (within 1%).
fn same_exposure(dark_us: f64, us: f64) -> bool {
    (dark_us / us - 1.0).abs() < 0.01
}

/// The dark level of one dark frame, per channel (exposure units): the mean exposure its
/// readings stand for (readings below the valid range count as 0, except on a linear
/// curve, which is unbiased there). A monochrome response's one level is in all three
/// places.
pub fn dark_level(r: &Response, pixels: &Pixels) -> [f64; 3] {
    let nc = r.channels.len();
    let levels = r.max_value() as usize + 1;
    let mut hist = vec![0u64; levels];
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate().take(nc) {
        hist.iter_mut().for_each(|h| *h = 0);
        for_each_value(pixels, c, nc, |z| {
            if let Some(h) = hist.get_mut(z) {
                *h += 1
            }
        });
        let total: u64 = hist.iter().sum();
        let ch = &r.channels[c];
        *o = if r.model == super::response::Model::Linear {
            // Values below the black level count too (they are unbiased there).
            hist.iter()
                .enumerate()
                .map(|(z, n)| *n as f64 * r.exposure(c, z as f64))
                .sum::<f64>()
                / total.max(1) as f64
        } else {
            let sum: f64 = hist
                .iter()
                .enumerate()
                .filter(|(z, n)| **n > 0 && *z as u32 >= ch.valid_min)
                .map(|(z, n)| *n as f64 * r.exposure(c, z as f64))
                .sum();
            sum / total.max(1) as f64
        };
    }
    if nc == 1 {
        out = [out[0]; 3];
    }
    out
}

/// Dark levels gathered as dark frames are read one at a time (memory: a few numbers per
/// exposure, whatever the frames' number or size): per exposure, the mean of its frames'
/// [`dark_level`]s. Frames must be added shortest exposure first.
#[derive(Debug, Clone, Default)]
pub struct DarkLevels {
    /// Per exposure (µs, shortest first): the sum of its frames' levels and their count.
    groups: Vec<(f64, [f64; 3], usize)>,
}

impl DarkLevels {
    /// Add a dark frame at `exposure_us` (no shorter than those added before).
    pub fn add(&mut self, r: &Response, exposure_us: f64, pixels: &Pixels) {
        let level = dark_level(r, pixels);
        match self.groups.last_mut() {
            Some((us, sum, n)) if *us == exposure_us => {
                for c in 0..3 {
                    sum[c] += level[c];
                }
                *n += 1;
            }
            _ => self.groups.push((exposure_us, level, 1)),
        }
    }

    /// Dark frames added.
    pub fn frames(&self) -> usize {
        self.groups.iter().map(|g| g.2).sum()
    }

    /// The dark level of a frame at `exposure_us`: that of the dark frames of the first
    /// exposure within 1% of it (as [`dark_levels`] takes the first such frame), zero
    /// without one.
    pub fn for_exposure(&self, exposure_us: f64) -> [f64; 3] {
        self.groups
            .iter()
            .find(|g| same_exposure(g.0, exposure_us))
            .map_or([0.0; 3], |(_, sum, n)| sum.map(|s| s / *n as f64))
    }
}

fn for_each_value(p: &Pixels, c: usize, channels: usize, mut f: impl FnMut(usize)) {
    match p {
        Pixels::U8(v) => v
            .iter()
            .skip(c)
            .step_by(channels)
            .for_each(|z| f(*z as usize)),
        Pixels::U16(v) => v
            .iter()
            .skip(c)
            .step_by(channels)
            .for_each(|z| f(*z as usize)),
    }
}

/// A pixel value type and its lookup in a frame's table: for 8-bit values the table is
/// seen as 256 entries, so the look-up needs no bounds check.
trait Value: Copy + Into<u32> + Send + Sync {
    type Table<'a>: Copy;
    fn table(lut: &FrameLut) -> Self::Table<'_>;
    fn get(t: Self::Table<'_>, z: Self) -> [Entry; 3];
}

impl Value for u8 {
    type Table<'a> = &'a [[Entry; 3]; 256];
    #[inline]
    fn table(lut: &FrameLut) -> Self::Table<'_> {
        lut.entries
            .as_slice()
            .try_into()
            .expect("an 8-bit table has 256 entries")
    }
    #[inline(always)]
    fn get(t: Self::Table<'_>, z: u8) -> [Entry; 3] {
        t[z as usize]
    }
}

impl Value for u16 {
    type Table<'a> = &'a [[Entry; 3]];
    #[inline]
    fn table(lut: &FrameLut) -> Self::Table<'_> {
        &lut.entries
    }
    #[inline(always)]
    fn get(t: Self::Table<'_>, z: u16) -> [Entry; 3] {
        t[z as usize]
    }
}

/// A large vector filled with `v`, in parallel. On Linux its memory is first marked for
/// transparent huge pages (where the kernel allows them on request): fresh memory costs a
/// page fault per 4 KiB page, and at 12 MP those faults cost more than the merge itself
/// (measured: 0.5 s of page faults against 0.14 s of merging on the 2-core machine).
fn big_vec<T: Copy + Send + Sync>(n: usize, v: T) -> Vec<T> {
    let mut out: Vec<T> = Vec::with_capacity(n);
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = n * std::mem::size_of::<T>();
        let start = out.as_mut_ptr() as usize;
        let aligned = start.next_multiple_of(HUGE);
        if bytes >= 2 * HUGE && aligned < start + bytes {
            let len = (start + bytes - aligned) / HUGE * HUGE;
            // SAFETY: the range lies inside the vector's allocation, which nothing has
            // touched yet; MADV_HUGEPAGE only changes how the kernel backs it.
            unsafe {
                libc::madvise(aligned as *mut libc::c_void, len, libc::MADV_HUGEPAGE);
            }
        }
    }
    out.spare_capacity_mut()
        .par_chunks_mut(1 << 16)
        .for_each(|c| {
            c.iter_mut().for_each(|x| {
                x.write(v);
            })
        });
    // SAFETY: every element of the spare capacity was written just above.
    unsafe { out.set_len(n) };
    out
}

/// Rows per parallel work item.
const CHUNK: usize = 3 * 4096;

/// Streaming merge: fold frames in as they arrive.
pub struct Merger {
    response: Response,
    width: usize,
    height: usize,
    bit_depth: u8,
    /// Per three samples (a pixel's three channels, or three pixels of a monochrome
    /// image): the two running sums (one memory stream).
    acc: Vec<[Entry; 3]>,
    flags: Vec<u8>,
    frames: usize,
}

/// Pixels per parallel work item of the streaming merge.
const PIX_CHUNK: usize = 4096;

impl Merger {
    /// A merge of `width` x `height` frames with the response's channels (3, or 1 for a
    /// monochrome camera).
    pub fn new(response: Response, width: usize, height: usize) -> Self {
        let n = width * height * response.channels.len();
        Merger {
            bit_depth: response.bit_depth,
            response,
            width,
            height,
            acc: big_vec(n.div_ceil(3), [Entry::default(); 3]),
            flags: big_vec(n, 0),
            frames: 0,
        }
    }

    /// Start a new bracket of the same size, reusing the memory.
    pub fn reset(&mut self) {
        self.acc
            .par_iter_mut()
            .for_each(|v| *v = [Entry::default(); 3]);
        self.flags.par_iter_mut().for_each(|v| *v = 0);
        self.frames = 0;
    }

    /// The response the frames are merged with.
    pub fn response(&self) -> &Response {
        &self.response
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Frames folded so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Fold one frame (RGB or, with a monochrome response, one sample a pixel;
    /// `exposure_us`; dark level per channel in exposure units).
    pub fn fold(&mut self, f: &BracketFrame, dark: [f64; 3]) -> Result<(), MergeError> {
        let lut = FrameLut::new(&self.response, &f.name, f.exposure_us, dark)?;
        self.fold_lut(f, &lut)?;
        self.frames += 1;
        Ok(())
    }

    fn fold_lut(&mut self, f: &BracketFrame, lut: &FrameLut) -> Result<(), MergeError> {
        let bits = match &f.pixels {
            Pixels::U8(_) => 8,
            Pixels::U16(_) => 16,
        };
        if f.pixels.len() != self.flags.len() || bits != self.bit_depth {
            return Err(MergeError::Input(format!(
                "{}: {} samples of {bits} bits, but the merge is {}x{} {} of {} bits",
                f.name,
                f.pixels.len(),
                self.width,
                self.height,
                if self.response.channels.len() == 1 {
                    "grey"
                } else {
                    "RGB"
                },
                self.bit_depth
            )));
        }
        let acc = self
            .acc
            .par_chunks_mut(PIX_CHUNK)
            .zip(self.flags.par_chunks_mut(3 * PIX_CHUNK))
            .enumerate();
        match &f.pixels {
            Pixels::U8(v) => acc.for_each(|(i, (a, fl))| {
                let o = i * 3 * PIX_CHUNK;
                fold_chunk(lut, &v[o..o + fl.len()], a, fl)
            }),
            Pixels::U16(v) => acc.for_each(|(i, (a, fl))| {
                let o = i * 3 * PIX_CHUNK;
                fold_chunk(lut, &v[o..o + fl.len()], a, fl)
            }),
        }
        Ok(())
    }

    /// Take a frame's dark level out after the fact, for a frame folded with a dark level
    /// of zero (frames are merged as they arrive, before the dark frames are taken): each
    /// valid reading's estimate loses t D / V, exactly the term a fold with `dark` would
    /// not have added. Flags and weights are unchanged.
    pub fn subtract_dark(&mut self, f: &BracketFrame, dark: [f64; 3]) -> Result<(), MergeError> {
        if dark == [0.0; 3] {
            return Ok(());
        }
        let mut lut = FrameLut::new(&self.response, &f.name, f.exposure_us, [0.0; 3])?;
        let with = FrameLut::new(&self.response, &f.name, f.exposure_us, dark)?;
        for (e, w) in lut.entries.iter_mut().zip(&with.entries) {
            for c in 0..3 {
                e[c] = Entry {
                    num: w[c].num - e[c].num,
                    den: 0.0,
                };
            }
        }
        lut.flags.iter_mut().for_each(|f| *f = [0; 3]);
        self.fold_lut(f, &lut)
    }

    /// The result so far.
    pub fn finish(self) -> Merged {
        let n = self.flags.len();
        let mut radiance = big_vec(n, 0.0f32);
        let mut variance = big_vec(n, 0.0f32);
        let mut mask = big_vec(n, 0u8);
        radiance
            .par_chunks_mut(3 * PIX_CHUNK)
            .zip(variance.par_chunks_mut(3 * PIX_CHUNK))
            .zip(mask.par_chunks_mut(3 * PIX_CHUNK))
            .enumerate()
            .for_each(|(i, ((r, v), m))| {
                let o = i * 3 * PIX_CHUNK;
                for k in 0..r.len() {
                    let e = self.acc[(o + k) / 3][(o + k) % 3];
                    // As [`merge`] finishes a sample, to the bit.
                    let inv = 1.0 / e.den;
                    (r[k], v[k], m[k]) = if e.den > 0.0 {
                        (e.num * inv, inv, MASK_OK)
                    } else {
                        finish_sample(0.0, 0.0, self.flags[o + k])
                    };
                }
            });
        Merged {
            width: self.width,
            height: self.height,
            channels: self.response.channels.len(),
            radiance,
            variance,
            mask,
        }
    }
}

#[inline]
fn finish_sample(num: f32, den: f32, flags: u8) -> (f32, f32, u8) {
    if den > 0.0 {
        (num / den, 1.0 / den, MASK_OK)
    } else if flags & FLAG_SAT != 0 {
        (f32::NAN, f32::NAN, MASK_SATURATED)
    } else {
        (f32::NAN, f32::NAN, MASK_DARK)
    }
}

#[inline]
fn fold_chunk<T: Value>(lut: &FrameLut, z: &[T], acc: &mut [[Entry; 3]], flags: &mut [u8]) {
    let table = T::table(lut);
    // A monochrome image's last samples (fewer than three): slot i % 3 of the last sums.
    let full = z.len() / 3;
    for i in 3 * full..z.len() {
        let c = i % 3;
        let e = T::get(table, z[i])[c];
        acc[full][c].num += e.num;
        acc[full][c].den += e.den;
        if e.den == 0.0 {
            flags[i] |= lut.flags[z[i].into() as usize][c];
        }
    }
    for ((z3, a), f3) in z
        .chunks_exact(3)
        .zip(acc.iter_mut())
        .zip(flags.chunks_exact_mut(3))
    {
        let e = [
            T::get(table, z3[0])[0],
            T::get(table, z3[1])[1],
            T::get(table, z3[2])[2],
        ];
        for c in 0..3 {
            a[c].num += e[c].num;
            a[c].den += e[c].den;
            if e[c].den == 0.0 {
                f3[c] |= lut.flags[z3[c].into() as usize][c];
            }
        }
    }
}

/// Merge a whole bracket at once (each frame read once, each output written once).
pub fn merge(r: &Response, b: &Bracket, dark: &[[f64; 3]]) -> Result<Merged, MergeError> {
    let n = b.width * b.height * b.channels;
    let mut out = Merged {
        width: b.width,
        height: b.height,
        channels: b.channels,
        radiance: big_vec(n, 0.0f32),
        variance: big_vec(n, 0.0f32),
        mask: big_vec(n, 0u8),
    };
    merge_into(r, b, dark, &mut out)?;
    Ok(out)
}

/// [`merge`] into existing buffers (reused from an earlier merge of the same size, which
/// saves the page faults of fresh memory: on the 2-core test machine these cost more than
/// the merge itself at 12 MP).
pub fn merge_into(
    r: &Response,
    b: &Bracket,
    dark: &[[f64; 3]],
    out: &mut Merged,
) -> Result<(), MergeError> {
    check_response(r, b)?;
    if dark.len() != b.frames.len() {
        return Err(MergeError::Input(format!(
            "{} dark levels for {} frames",
            dark.len(),
            b.frames.len()
        )));
    }
    merge_checked(r, b, dark, out)
}

/// Whether frames of bracket `b` (its exposures, depth and channels; its pixels are not
/// looked at) can be merged with response `r`.
pub fn check_response(r: &Response, b: &Bracket) -> Result<(), MergeError> {
    b.check_exposures()?;
    if b.bit_depth != r.bit_depth {
        return Err(MergeError::Input(format!(
            "the frames are {}-bit but the response is for {}-bit frames; recover a response for this camera (glint response)",
            b.bit_depth, r.bit_depth
        )));
    }
    if b.channels != r.channels.len() {
        return Err(MergeError::Input(format!(
            "the frames have {} but the response has {}; recover a response for this camera (glint response)",
            glint_format::image::channels_name(b.channels as u8),
            glint_format::image::channels_name(r.channels.len() as u8)
        )));
    }
    Ok(())
}

fn merge_checked(
    r: &Response,
    b: &Bracket,
    dark: &[[f64; 3]],
    out: &mut Merged,
) -> Result<(), MergeError> {
    let luts: Vec<FrameLut> = b
        .frames
        .iter()
        .zip(dark)
        .map(|(f, d)| FrameLut::new(r, &f.name, f.exposure_us, *d))
        .collect::<Result<_, _>>()?;
    let n = b.width * b.height * b.channels;
    out.width = b.width;
    out.height = b.height;
    out.channels = b.channels;
    out.radiance.resize(n, 0.0);
    out.variance.resize(n, 0.0);
    out.mask.resize(n, 0);
    let jobs = out
        .radiance
        .par_chunks_mut(CHUNK)
        .zip(out.variance.par_chunks_mut(CHUNK))
        .zip(out.mask.par_chunks_mut(CHUNK))
        .enumerate();
    let done = match b.frames[0].pixels {
        Pixels::U8(_) => {
            let frames: Vec<&[u8]> = b
                .frames
                .iter()
                .map(|f| match &f.pixels {
                    Pixels::U8(v) => v.as_slice(),
                    Pixels::U16(_) => unreachable!("checked by Bracket"),
                })
                .collect();
            jobs.try_for_each(|(i, ((rad, var), m))| {
                merge_chunk(&luts, &frames, i * CHUNK, rad, var, m)
            })
        }
        Pixels::U16(_) => {
            let frames: Vec<&[u16]> = b
                .frames
                .iter()
                .map(|f| match &f.pixels {
                    Pixels::U16(v) => v.as_slice(),
                    Pixels::U8(_) => unreachable!("checked by Bracket"),
                })
                .collect();
            jobs.try_for_each(|(i, ((rad, var), m))| {
                merge_chunk(&luts, &frames, i * CHUNK, rad, var, m)
            })
        }
    };
    // The tables keep every measured sample finite; should one not be, the merge is an
    // error naming the frame whose reading there weighs most, never a result.
    if let Err(k) = done {
        let (p, c) = (k / b.channels, k % b.channels);
        let j = (0..b.frames.len())
            .max_by(|&x, &y| {
                let w = |j: usize| {
                    let e = luts[j].entries[b.value(j, p, c) as usize][c];
                    if e.num.is_finite() && e.den.is_finite() {
                        e.num.abs() + e.den
                    } else {
                        f32::INFINITY
                    }
                };
                w(x).total_cmp(&w(y))
            })
            .unwrap_or(0);
        let f = &b.frames[j];
        return Err(MergeError::Input(format!(
            "the merge gives a non-finite radiance at pixel ({}, {}), channel {}, mostly from {} ({} µs); check that frame's exposure time and the response",
            p % b.width,
            p / b.width,
            r.channel_name(c),
            f.name,
            show_us(f.exposure_us)
        )));
    }
    Ok(())
}

/// Frames added together per pass over a block: their running sums stay in registers, so
/// a block's sums go through memory once per group rather than once per frame.
const GROUP: usize = 4;

/// Add `G` frames' increments for `m` samples into a block's sums (`first`: the sums
/// start at zero).
#[inline(always)]
fn add_frames<T: Value, const G: usize>(
    luts: &[FrameLut],
    frames: &[&[T]],
    from: usize,
    m: usize,
    sums: &mut [[Entry; 3]],
    first: bool,
) {
    let tables: [T::Table<'_>; G] = std::array::from_fn(|g| T::table(&luts[g]));
    let z: [&[T]; G] = std::array::from_fn(|g| &frames[g][from..from + m]);
    let np = m / 3;
    // A monochrome image's last samples (fewer than three): slot i % 3 of the last sums.
    for i in 3 * np..m {
        let c = i % 3;
        let mut a = if first { Entry::default() } else { sums[np][c] };
        for (t, zg) in tables.iter().zip(&z) {
            let e = T::get(*t, zg[i])[c];
            a.num += e.num;
            a.den += e.den;
        }
        sums[np][c] = a;
    }
    for (k, s3) in sums[..np].iter_mut().enumerate() {
        for (c, s) in s3.iter_mut().enumerate() {
            let mut a = if first { Entry::default() } else { *s };
            for g in 0..G {
                let e = T::get(tables[g], z[g][3 * k + c])[c];
                a.num += e.num;
                a.den += e.den;
            }
            *s = a;
        }
    }
}

fn merge_chunk<T: Value>(
    luts: &[FrameLut],
    frames: &[&[T]],
    offset: usize,
    rad: &mut [f32],
    var: &mut [f32],
    mask: &mut [u8],
) -> Result<(), usize> {
    let len = rad.len();
    // Blocks of pixels, so the partial sums stay in L1.
    const P: usize = 128;
    let mut sums = [[Entry::default(); 3]; P];
    let mut start = 0;
    while start < len {
        let m = (3 * P).min(len - start);
        let np = m.div_ceil(3);
        let from = offset + start;
        let mut g0 = 0;
        while g0 < luts.len() {
            let (l, f) = (&luts[g0..], &frames[g0..]);
            let first = g0 == 0;
            match (luts.len() - g0).min(GROUP) {
                1 => add_frames::<T, 1>(l, f, from, m, &mut sums, first),
                2 => add_frames::<T, 2>(l, f, from, m, &mut sums, first),
                3 => add_frames::<T, 3>(l, f, from, m, &mut sums, first),
                _ => add_frames::<T, GROUP>(l, f, from, m, &mut sums, first),
            }
            g0 += GROUP;
        }
        // One division per sample, branch-free (vectorised); 0 / 0 gives the NaN a sample
        // without radiance must have.
        let s = sums[..np].as_flattened();
        let (r, v, mk) = (
            &mut rad[start..start + m],
            &mut var[start..start + m],
            &mut mask[start..start + m],
        );
        for k in 0..m {
            let (n, d) = (s[k].num, s[k].den);
            let inv = 1.0 / d;
            r[k] = n * inv;
            v[k] = if d > 0.0 { inv } else { f32::NAN };
            mk[k] = if d > 0.0 { MASK_OK } else { u8::MAX };
        }
        // The rare samples with no reading: saturated if any frame saw saturation.
        for k in 0..m {
            if mk[k] == u8::MAX {
                let c = k % 3;
                let mut fl = 0;
                for (lut, f) in luts.iter().zip(frames) {
                    fl |= lut.flags[f[offset + start + k].into() as usize][c];
                }
                (r[k], v[k], mk[k]) = finish_sample(0.0, 0.0, fl);
            }
        }
        // Measured samples are finite (the block is still in L1: a cheap second look).
        if let Some(k) =
            (0..m).find(|&k| mk[k] == MASK_OK && !(r[k].is_finite() && v[k].is_finite()))
        {
            return Err(offset + start + k);
        }
        start += m;
    }
    Ok(())
}

/// The merge of a few pixels (a fit's samples) with curves that differ from a response only
/// by a change of ln E at each value, as [`Response::draws_at`] gives: the response is
/// evaluated only at the values the pixels read (and their neighbours, for the slope), never
/// as a table of every value, so that each re-merge costs microseconds at any bit depth. The
/// result equals [`merge`] with [`dark_levels`] of the changed response, up to rounding.
#[derive(Debug, Clone)]
pub struct PixelMerge {
    response: Response,
    /// Samples a pixel, pixels.
    channels: usize,
    pixels: usize,
    /// Per channel: the values needed, sorted.
    values: Vec<Vec<u32>>,
    /// Per channel: ln E (or, below the black level of a linear curve, E itself) at each
    /// value.
    base: Vec<Vec<f64>>,
    /// Per tile frame: exposure (s), the dark frame of the same exposure, and per sample
    /// (pixel-major, channels interleaved) the reading's (value, lower, upper) neighbour
    /// indices into `values[c]`, or None when the value is outside the valid range (then
    /// the flag).
    frames: Vec<PixelFrame>,
    /// Per dark frame, per sample: the index of its value.
    darks: Vec<(f64, Vec<usize>)>,
}

#[derive(Debug, Clone)]
struct PixelFrame {
    t: f64,
    dark: Option<usize>,
    readings: Vec<Result<[usize; 3], u8>>,
}

impl PixelMerge {
    /// Prepare the merge of every pixel of `tiles` (and the dark frames `darks`, same
    /// pixels) with curves drawn about `r`.
    pub fn new(r: &Response, tiles: &Bracket, darks: &Bracket) -> Result<Self, MergeError> {
        let nc = r.channels.len();
        if tiles.channels != nc || tiles.bit_depth != r.bit_depth {
            return Err(MergeError::Input(
                "the frames do not match the response (channels or bit depth)".into(),
            ));
        }
        let max = r.max_value();
        let n = tiles.width * tiles.height;
        let mut need: Vec<Vec<u32>> = vec![Vec::new(); nc];
        for j in 0..tiles.frames.len() {
            for p in 0..n {
                for (c, nd) in need.iter_mut().enumerate() {
                    let z = tiles.value(j, p, c);
                    let ch = &r.channels[c];
                    if z >= ch.valid_min && z <= ch.valid_max {
                        nd.extend([z.saturating_sub(1), z, (z + 1).min(max)]);
                    }
                }
            }
        }
        for j in 0..darks.frames.len() {
            for p in 0..darks.width * darks.height {
                for (c, nd) in need.iter_mut().enumerate() {
                    nd.push(darks.value(j, p, c));
                }
            }
        }
        for v in need.iter_mut() {
            v.sort_unstable();
            v.dedup();
        }
        let idx = |c: usize, z: u32| need[c].binary_search(&z).unwrap_or(0);
        let base = need
            .iter()
            .enumerate()
            .map(|(c, vals)| vals.iter().map(|z| base_value(r, c, *z)).collect())
            .collect();
        let frames = tiles
            .frames
            .iter()
            .enumerate()
            .map(|(j, f)| {
                let dark = darks
                    .frames
                    .iter()
                    .position(|d| (d.exposure_us / f.exposure_us - 1.0).abs() < 0.01);
                let readings = (0..n * nc)
                    .map(|k| {
                        let (p, c) = (k / nc, k % nc);
                        let z = tiles.value(j, p, c);
                        let ch = &r.channels[c];
                        if z < ch.valid_min {
                            Err(FLAG_DARK)
                        } else if z > ch.valid_max {
                            Err(FLAG_SAT)
                        } else {
                            Ok([
                                idx(c, z),
                                idx(c, z.saturating_sub(1)),
                                idx(c, (z + 1).min(max)),
                            ])
                        }
                    })
                    .collect();
                PixelFrame {
                    t: f.exposure_us * 1e-6,
                    dark,
                    readings,
                }
            })
            .collect();
        let darks = (0..darks.frames.len())
            .map(|j| {
                let k = darks.width * darks.height * nc;
                (
                    darks.frames[j].exposure_us,
                    (0..k)
                        .map(|k| idx(k % nc, darks.value(j, k / nc, k % nc)))
                        .collect(),
                )
            })
            .collect();
        Ok(PixelMerge {
            response: r.clone(),
            channels: nc,
            pixels: n,
            values: need,
            base,
            frames,
            darks,
        })
    }

    /// The values of channel `c` the merge evaluates the curve at.
    pub fn values(&self) -> &[Vec<u32>] {
        &self.values
    }

    /// Merge with the response's curve changed by `delta[c][i]` in ln E at value
    /// `values()[c][i]` (an empty or missing list: unchanged).
    pub fn merge(&self, delta: &[Vec<f64>]) -> Merged {
        let r = &self.response;
        let nc = self.channels;
        let linear = r.model == super::response::Model::Linear;
        let d = |c: usize, i: usize| delta.get(c).and_then(|v| v.get(i)).copied().unwrap_or(0.0);
        // Exposure at every needed value.
        let e: Vec<Vec<f64>> = (0..nc)
            .map(|c| {
                (0..self.values[c].len())
                    .map(|i| {
                        let b = self.base[c][i];
                        if linear {
                            b * d(c, i).exp()
                        } else {
                            (b + d(c, i)).exp()
                        }
                    })
                    .collect()
            })
            .collect();
        // Dark levels: the mean exposure of each dark frame's readings (a table curve's
        // readings below its valid range count as 0, as in `dark_levels`).
        let dark: Vec<Vec<f64>> = self
            .darks
            .iter()
            .map(|(_, idx)| {
                let mut sum = vec![0.0; nc];
                for (k, i) in idx.iter().enumerate() {
                    let c = k % nc;
                    if linear || self.values[c][*i] >= r.channels[c].valid_min {
                        sum[c] += e[c][*i];
                    }
                }
                sum.iter()
                    .map(|s| s / (idx.len() / nc).max(1) as f64)
                    .collect()
            })
            .collect();
        let len = self.pixels * nc;
        let mut num = vec![0.0f64; len];
        let mut den = vec![0.0f64; len];
        let mut flags = vec![0u8; len];
        for f in &self.frames {
            for (k, rd) in f.readings.iter().enumerate() {
                let c = k % nc;
                match rd {
                    Err(fl) => flags[k] |= fl,
                    Ok([i, lo, hi]) => {
                        let ch = &r.channels[c];
                        let x = e[c][*i];
                        let slope = if linear {
                            ch.gain * d(c, *i).exp()
                        } else {
                            let (zl, zh) = (self.values[c][*lo], self.values[c][*hi]);
                            let g = |j: usize| self.base[c][j] + d(c, j);
                            (g(*hi) - g(*lo)) / (zh - zl).max(1) as f64 * x
                        };
                        let v = r.reading_variance(c, self.values[c][*i] as f64, x, slope);
                        let dk = f.dark.map(|j| dark[j][c]).unwrap_or(0.0);
                        if v > 0.0 && v.is_finite() {
                            num[k] += f.t * (x - dk) / v;
                            den[k] += f.t * f.t / v;
                        }
                    }
                }
            }
        }
        let mut out = Merged {
            width: self.pixels,
            height: 1,
            channels: nc,
            radiance: vec![0.0; len],
            variance: vec![0.0; len],
            mask: vec![0; len],
        };
        for k in 0..len {
            (out.radiance[k], out.variance[k], out.mask[k]) =
                finish_sample(num[k] as f32, den[k] as f32, flags[k]);
        }
        out
    }
}

/// What [`PixelMerge`] keeps of a response at value z: ln E, or for a linear curve E itself
/// (it may be zero or negative below the black level).
fn base_value(r: &Response, c: usize, z: u32) -> f64 {
    match r.model {
        super::response::Model::Linear => r.exposure(c, z as f64),
        _ => r.channels[c]
            .ln_exposure
            .get(z as usize)
            .copied()
            .unwrap_or(f64::NAN),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hdr::response::{Channel, Model, Noise, FORMAT, FORMAT_VERSION};

    fn linear() -> Response {
        let ch = Channel {
            ln_exposure: Vec::new(),
            ln_exposure_sd: Vec::new(),
            coefficients: Vec::new(),
            coefficient_covariance: Vec::new(),
            black: 0.0,
            gain: 1.0 / 255.0,
            valid_min: 1,
            valid_max: 254,
            noise: Noise {
                shot: 1e-3,
                read: 1e-6,
            },
            rms_residual: 0.0,
            misfit_sd: 0.0,
            samples: 0,
        };
        Response {
            format: FORMAT.into(),
            format_version: FORMAT_VERSION,
            model: Model::Linear,
            bit_depth: 8,
            camera: None,
            recovered_from: String::new(),
            lambda: 0.0,
            choice: None,
            channels: vec![ch.clone(), ch.clone(), ch],
            alternatives: Vec::new(),
            warnings: Vec::new(),
        }
    }

    fn bracket(times_us: &[f64]) -> Bracket {
        let frames = times_us
            .iter()
            .enumerate()
            .map(|(i, t)| BracketFrame {
                name: format!("frames/{i:04}.png"),
                exposure_us: *t,
                pixels: Pixels::U8((0..8 * 6 * 3).map(|k| (20 + 30 * i + k) as u8).collect()),
            })
            .collect();
        Bracket::new(8, 6, 8, frames).unwrap()
    }

    /// A fitted curve's top counts less in the merge (its shape's sd, rising from 0.8 of
    /// full scale), a linear curve's does not: a pixel read at 0.97 of full scale and, at a
    /// quarter of the time, at a quarter of the exposure, takes its radiance mostly from
    /// the lower reading under a gamma curve; under a linear one the brighter reading
    /// counts most (less shot noise relative to it).
    #[test]
    fn a_fitted_curves_top_counts_less_than_its_middle() {
        let mut gamma = linear();
        gamma.model = Model::Debevec;
        for ch in gamma.channels.iter_mut() {
            ch.ln_exposure = (0..256)
                .map(|z| 2.2 * ((z as f64).max(0.5) / 255.0).ln())
                .collect();
            // A full well of 20 000 electrons.
            ch.noise.shot = 5e-5;
        }
        // Relative sd of one reading at value z.
        let rel = |r: &Response, z: f64| r.exposure_variance(0, z).sqrt() / r.exposure(0, z);
        let lin = linear();
        assert_eq!(lin.top_sd(250.0), 0.0);
        assert_eq!(gamma.top_sd(0.8 * 255.0), 0.0);
        assert!(gamma.top_sd(255.0) > 0.02);
        let top = 0.97 * 255.0;
        // Under gamma 2.2 a quarter of the exposure is 0.97 * 0.25^(1/2.2) of full scale.
        let low = top * 0.25f64.powf(1.0 / 2.2);
        let (a, b) = (rel(&gamma, top), rel(&gamma, low));
        assert!(a > b, "gamma: top {a}, lower {b}");
        let (a, b) = (rel(&lin, top), rel(&lin, top * 0.25));
        assert!(a < b, "linear: top {a}, lower {b}");
    }

    #[test]
    fn a_sane_bracket_merges_finite_where_measured() {
        let b = bracket(&[1000.0, 4000.0]);
        let m = merge(&linear(), &b, &[[0.0; 3]; 2]).unwrap();
        for (x, k) in m.radiance.iter().zip(&m.mask) {
            assert!(*k != MASK_OK || x.is_finite());
        }
        assert!(m.counts()[0] > 0);
    }

    #[test]
    fn absurd_exposure_times_fail_the_merge_naming_the_frame() {
        for t in [1e-300, 1e-30, 1e300, 1e25] {
            let b = bracket(&[1000.0, t]);
            let e = merge(&linear(), &b, &[[0.0; 3]; 2])
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("frames/0001.png") && e.contains(&show_us(t)),
                "{t}: {e}"
            );
            assert!(!e.contains('\n'));
            // The streaming merge refuses the frame too.
            let mut mg = Merger::new(linear(), 8, 6);
            mg.fold(&b.frames[0], [0.0; 3]).unwrap();
            let e = mg.fold(&b.frames[1], [0.0; 3]).unwrap_err().to_string();
            assert!(e.contains("frames/0001.png"), "{e}");
        }
    }

    #[test]
    fn a_response_with_a_non_finite_value_fails_the_merge() {
        for bad in [f64::NAN, f64::INFINITY, 1e300] {
            let mut r = linear();
            r.channels[1].gain = bad;
            let b = bracket(&[1000.0, 4000.0]);
            let e = merge(&r, &b, &[[0.0; 3]; 2]).unwrap_err().to_string();
            assert!(e.contains("frames/0000.png") && e.contains("µs"), "{e}");
        }
        // A non-finite dark level too.
        let b = bracket(&[1000.0, 4000.0]);
        let e = merge(&linear(), &b, &[[0.0; 3], [0.0, f64::NAN, 0.0]])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("frames/0001.png") && e.contains("dark level"),
            "{e}"
        );
    }
}
