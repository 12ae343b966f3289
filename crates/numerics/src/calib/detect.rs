//! Chessboard detection: the inner-corner grid of a given size in a grey image, ordered to
//! the documented origin and axes, each corner refined to sub-pixel accuracy.
//!
//! Written here rather than taken from a crate: calib-targets 0.16 (the maintained Rust
//! detector) was evaluated on the 26 real photos of OpenCV's stereo chessboard set (test
//! data kept outside the project): its corners were 0.10-0.20 px (median per photo) from
//! OpenCV's refined corners, against the 0.1 px asked for, and two of its 26 labelled
//! grids held a spurious or missing corner (left12: 55 corners, a hole and two corners off
//! the board). See docs/calibration.md.
//!
//! Steps:
//! 1. Candidates: saddle points of the smoothed image (the Hessian's determinant is
//!    negative at the crossing of two edges), each checked on a ring of samples around it:
//!    the ring must be split into four sectors, dark-light-dark-light, with opposite
//!    sectors alike. The ring test compares each sample with the ring's own mean, so it
//!    holds under uneven light and shadow. They are searched for at half the search scale
//!    first (a quarter of the pixels), and at the search scale only if the grid is not
//!    found whole there or its squares are small ([`detect`]).
//! 2. Grid growing from a seed and its two nearest non-parallel neighbours: each next
//!    corner is predicted by extrapolating the last step (which follows perspective) and
//!    snapped to the nearest candidate.
//! 3. Sub-pixel refinement: every image gradient near a corner is orthogonal to the vector
//!    from the corner to where it is measured (Förstner; the method of OpenCV's
//!    cornerSubPix, with its Gaussian window weights), solved by iteration, on the
//!    full-resolution image smoothed over a box around each corner only.
//! 4. Order: x along the first grid count, y along the second, the frame right-handed with
//!    z towards the camera, and the origin the inner corner whose +x,+y square is dark.

use std::collections::{HashMap, VecDeque};
use std::fmt;

/// A grey image, values in any fixed range (0..255 for 8-bit photos).
#[derive(Debug, Clone)]
pub struct Gray {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Gray {
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), width * height);
        Gray {
            width,
            height,
            data,
        }
    }

    #[inline]
    fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Bilinear sample at (x, y) (pixel centres at integers), clamped at the border.
    #[inline]
    pub fn sample(&self, x: f64, y: f64) -> f64 {
        let xm = (self.width - 1) as f64;
        let ym = (self.height - 1) as f64;
        let x = x.clamp(0.0, xm);
        let y = y.clamp(0.0, ym);
        // x, y >= 0 here, so truncation is the floor (and no call to libm's).
        let x0 = (x as usize).min(self.width.saturating_sub(2));
        let y0 = (y as usize).min(self.height.saturating_sub(2));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let a = self.at(x0, y0) as f64;
        let b = self.at(x0 + 1, y0) as f64;
        let c = self.at(x0, y0 + 1) as f64;
        let d = self.at(x0 + 1, y0 + 1) as f64;
        a * (1.0 - fx) * (1.0 - fy) + b * fx * (1.0 - fy) + c * (1.0 - fx) * fy + d * fx * fy
    }

    /// Mean over `f` x `f` blocks (pixel centre of block k at f k + (f - 1) / 2).
    #[cfg(test)]
    fn shrink(&self, f: usize) -> Gray {
        let (w, h) = (self.width / f, self.height / f);
        let mut out = vec![0f32; w * h];
        let s = 1.0 / (f * f) as f32;
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for yy in 0..f {
                    let row = &self.data[(y * f + yy) * self.width + x * f..][..f];
                    acc += row.iter().sum::<f32>();
                }
                out[y * w + x] = acc * s;
            }
        }
        Gray::new(w, h, out)
    }

    /// Separable Gaussian blur (edges clamped).
    #[cfg(test)]
    fn blur(&self, sigma: f64) -> Gray {
        let k = gauss_taps(sigma);
        let r = k.len() / 2;
        let (w, h) = (self.width, self.height);
        // Rows: pad each row by r on both sides, then a straight dot product per pixel.
        let mut tmp = vec![0f32; w * h];
        let mut pad = vec![0f32; w + 2 * r];
        for y in 0..h {
            let row = &self.data[y * w..(y + 1) * w];
            pad[..r].fill(row[0]);
            pad[r..r + w].copy_from_slice(row);
            pad[r + w..].fill(row[w - 1]);
            let out = &mut tmp[y * w..(y + 1) * w];
            for (i, kv) in k.iter().enumerate() {
                out.iter_mut()
                    .zip(&pad[i..i + w])
                    .for_each(|(o, p)| *o += kv * p);
            }
        }
        // Columns: whole rows at a time, which vectorises.
        let mut out = vec![0f32; w * h];
        for y in 0..h {
            let o = &mut out[y * w..(y + 1) * w];
            for (i, kv) in k.iter().enumerate() {
                let yy = (y + i).saturating_sub(r).min(h - 1);
                let src = &tmp[yy * w..(yy + 1) * w];
                o.iter_mut().zip(src).for_each(|(a, b)| *a += kv * b);
            }
        }
        Gray::new(w, h, out)
    }

    /// The image shrunk `f` times (means over `f` x `f` blocks, pixel centre of block k at
    /// f k + (f - 1) / 2; `f` = 1 the image itself), then blurred with a Gaussian (edges
    /// clamped). Without intermediate images: each shrunk row is made and blurred along
    /// the row as the column pass first needs it, and the column pass keeps only the
    /// 2r + 1 rows it reads (fresh image-sized buffers cost a page fault per 4 KiB, more
    /// than the arithmetic). The same values, summed in the same order, as shrinking and
    /// then blurring whole images (`shrink_blur_is_shrink_then_blur`).
    fn shrink_blur(&self, f: usize, sigma: f64) -> Gray {
        let k = gauss_taps(sigma);
        let r = k.len() / 2;
        let (w, h) = (self.width / f, self.height / f);
        let n = 2 * r + 1;
        let s = 1.0 / (f * f) as f32;
        let mut ring = vec![0f32; n * w];
        let mut pad = vec![0f32; w + 2 * r];
        let mut out = vec![0f32; w * h];
        let mut next = 0;
        for y in 0..h {
            while next <= (y + r).min(h - 1) {
                let row = &mut pad[r..r + w];
                if f == 1 {
                    row.copy_from_slice(&self.data[next * w..(next + 1) * w]);
                } else if f == 2 {
                    let a = &self.data[2 * next * self.width..][..2 * w];
                    let b = &self.data[(2 * next + 1) * self.width..][..2 * w];
                    for ((o, a), b) in row.iter_mut().zip(a.chunks_exact(2)).zip(b.chunks_exact(2))
                    {
                        *o = ((a[0] + a[1]) + (b[0] + b[1])) * s;
                    }
                } else {
                    for (x, o) in row.iter_mut().enumerate() {
                        let mut acc = 0.0;
                        for yy in 0..f {
                            let src = &self.data[(next * f + yy) * self.width + x * f..][..f];
                            acc += src.iter().sum::<f32>();
                        }
                        *o = acc * s;
                    }
                }
                let (first, last) = (pad[r], pad[r + w - 1]);
                pad[..r].fill(first);
                pad[r + w..].fill(last);
                // LANES pixels at a time, their sums kept in registers over the taps.
                let o = &mut ring[(next % n) * w..][..w];
                let mut chunks = o.chunks_exact_mut(LANES);
                for (c, o) in (&mut chunks).enumerate() {
                    let mut acc = [0f32; LANES];
                    for (i, kv) in k.iter().enumerate() {
                        let p = &pad[c * LANES + i..][..LANES];
                        for (a, p) in acc.iter_mut().zip(p) {
                            *a += kv * p;
                        }
                    }
                    o.copy_from_slice(&acc);
                }
                let x0 = w - chunks.into_remainder().len();
                for x in x0..w {
                    let mut acc = 0f32;
                    for (i, kv) in k.iter().enumerate() {
                        acc += kv * pad[x + i];
                    }
                    ring[(next % n) * w + x] = acc;
                }
                next += 1;
            }
            let rows: Vec<&[f32]> = (0..k.len())
                .map(|i| {
                    let yy = (y + i).saturating_sub(r).min(h - 1);
                    &ring[(yy % n) * w..][..w]
                })
                .collect();
            let o = &mut out[y * w..(y + 1) * w];
            let mut chunks = o.chunks_exact_mut(LANES);
            for (c, o) in (&mut chunks).enumerate() {
                let mut acc = [0f32; LANES];
                for (kv, src) in k.iter().zip(&rows) {
                    for (a, b) in acc.iter_mut().zip(&src[c * LANES..][..LANES]) {
                        *a += kv * b;
                    }
                }
                o.copy_from_slice(&acc);
            }
            let x0 = w - chunks.into_remainder().len();
            for x in x0..w {
                let mut acc = 0f32;
                for (kv, src) in k.iter().zip(&rows) {
                    acc += kv * src[x];
                }
                o[x] = acc;
            }
        }
        Gray::new(w, h, out)
    }
}

/// Normalised Gaussian taps, radius ceil(3 sigma).
fn gauss_taps(sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as usize;
    let k: Vec<f32> = (0..=2 * r)
        .map(|i| {
            let d = i as f64 - r as f64;
            (-(d * d) / (2.0 * sigma * sigma)).exp() as f32
        })
        .collect();
    let sum: f32 = k.iter().sum();
    k.iter().map(|v| v / sum).collect()
}

fn grow_to<T: Copy + Default>(v: &mut Vec<T>, n: usize) {
    if v.len() < n {
        v.resize(n, T::default());
    }
}

/// Lanes of the blur over a box (a multiple of the SIMD width, so each row of the box is
/// whole vectors).
const LANES: usize = 8;

/// A box of the image around one corner, smoothed, with the gradient products the
/// refinement sums: worked out once per corner for both of its refinements (plain and
/// robust), in buffers reused from corner to corner.
struct Patch {
    /// Image pixel (x, y) is box pixel (x - x0, y - y0); the box is bw x bh.
    x0: usize,
    y0: usize,
    bw: usize,
    bh: usize,
    /// The image's size.
    iw: usize,
    ih: usize,
    /// Per box pixel (interior only): the five products the refinement sums, gx²,
    /// gx gy, gy², gx² x + gx gy y and gx gy x + gy² y (image coordinates), then gx, gy
    /// and 1 / (|g|² ROBUST_PX²) (0 where g = 0) for the robust weights.
    g: Vec<[f64; 8]>,
    /// Scratch: rows blurred along x (stride a multiple of LANES), the padded source
    /// row, and the smoothed box (same stride).
    tmp: Vec<f32>,
    pad: Vec<f32>,
    smooth: Vec<f32>,
}

impl Patch {
    fn new() -> Self {
        Patch {
            x0: 0,
            y0: 0,
            bw: 0,
            bh: 0,
            iw: 0,
            ih: 0,
            g: Vec::new(),
            tmp: Vec::new(),
            pad: Vec::new(),
            smooth: Vec::new(),
        }
    }

    /// The box x0..=x1, y0..=y1 of `img` blurred with the taps `k` (edges clamped at the
    /// image's border, not the box's: the values of blurring the whole image, each the
    /// same sum in the same order), and its gradient products.
    fn smoothed(&mut self, img: &Gray, k: &[f32], [x0, y0, x1, y1]: [usize; 4]) {
        let r = k.len() / 2;
        let (w, h) = (img.width, img.height);
        let bw = x1 - x0 + 1;
        let stride = bw.div_ceil(LANES) * LANES;
        // Rows ya..=yb feed the box; each padded by r on both sides.
        let (ya, yb) = (y0.saturating_sub(r), (y1 + r).min(h - 1));
        // Every element the box uses is written first: the buffers are only grown.
        grow_to(&mut self.tmp, (yb - ya + 1) * stride);
        grow_to(&mut self.pad, stride + 2 * r);
        for y in ya..=yb {
            let row = &img.data[y * w..(y + 1) * w];
            for (i, p) in self.pad.iter_mut().enumerate() {
                *p = row[(x0 + i).saturating_sub(r).min(w - 1)];
            }
            let out = &mut self.tmp[(y - ya) * stride..][..stride];
            for (x, o) in out.chunks_exact_mut(LANES).enumerate() {
                let mut acc = [0f32; LANES];
                for (i, kv) in k.iter().enumerate() {
                    let p = &self.pad[x * LANES + i..][..LANES];
                    for (a, p) in acc.iter_mut().zip(p) {
                        *a += kv * p;
                    }
                }
                o.copy_from_slice(&acc);
            }
        }
        let bh = y1 - y0 + 1;
        grow_to(&mut self.smooth, bh * stride);
        for y in y0..=y1 {
            let o = &mut self.smooth[(y - y0) * stride..][..stride];
            for x in (0..stride).step_by(LANES) {
                let mut acc = [0f32; LANES];
                for (i, kv) in k.iter().enumerate() {
                    let yy = (y + i).saturating_sub(r).min(h - 1);
                    let src = &self.tmp[(yy - ya) * stride + x..][..LANES];
                    for (a, b) in acc.iter_mut().zip(src) {
                        *a += kv * b;
                    }
                }
                o[x..x + LANES].copy_from_slice(&acc);
            }
        }
        self.tabulate([x0, y0], [bw, bh], stride, [w, h], None);
    }

    /// The box over the whole image, not smoothed.
    fn whole(&mut self, img: &Gray) {
        self.tabulate(
            [0, 0],
            [img.width, img.height],
            img.width,
            [img.width, img.height],
            Some(img),
        );
    }

    /// The gradient products from the smoothed box (or `raw`, the image itself).
    fn tabulate(
        &mut self,
        [x0, y0]: [usize; 2],
        [bw, bh]: [usize; 2],
        stride: usize,
        [iw, ih]: [usize; 2],
        raw: Option<&Gray>,
    ) {
        (self.x0, self.y0, self.bw, self.bh, self.iw, self.ih) = (x0, y0, bw, bh, iw, ih);
        let src: &[f32] = raw.map_or(&self.smooth, |g| &g.data);
        // Only interior pixels are written, and read (a window that reaches the box's
        // edge is refused).
        if self.g.len() < bw * bh {
            self.g.resize(bw * bh, [0.0; 8]);
        }
        for y in 1..bh.saturating_sub(1) {
            let row = &src[y * stride..][..bw];
            let up = &src[(y - 1) * stride..][..bw];
            let down = &src[(y + 1) * stride..][..bw];
            let yi = (y + y0) as f64;
            let cells = &mut self.g[y * bw..(y + 1) * bw];
            for x in 1..bw - 1 {
                let gx = 0.5 * (row[x + 1] - row[x - 1]) as f64;
                let gy = 0.5 * (down[x] - up[x]) as f64;
                let xi = (x + x0) as f64;
                let (gxx, gxy, gyy) = (gx * gx, gx * gy, gy * gy);
                let g2 = gxx + gyy;
                cells[x] = [
                    gxx,
                    gxy,
                    gyy,
                    gxx * xi + gxy * yi,
                    gxy * xi + gyy * yi,
                    gx,
                    gy,
                    if g2 > 0.0 {
                        1.0 / (g2 * (ROBUST_PX * ROBUST_PX))
                    } else {
                        0.0
                    },
                ];
            }
        }
    }
}

/// Why no grid was returned.
#[derive(Debug, Clone, PartialEq)]
pub enum DetectError {
    /// Nothing that looks like a chessboard.
    NoGrid,
    /// Part of the grid: `found` of `expected` corners of the `grid` looked for (inner
    /// corners).
    Partial {
        found: usize,
        expected: usize,
        grid: [usize; 2],
        touches_border: bool,
    },
    /// A complete grid of another size.
    WrongSize {
        found: [usize; 2],
        expected: [usize; 2],
    },
    /// The square colours do not single out the origin (a board with an even number of
    /// squares both ways, or an unreadable board).
    NoOrigin,
}

/// What a partial detection's message says where the grid touches the image border (the
/// lens check counts the skipped poses that say it).
pub const AT_BORDER: &str = "the grid touches the image border";

impl fmt::Display for DetectError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DetectError::NoGrid => write!(
                f,
                "no grid found: check that the whole chessboard is in view, in focus and lit"
            ),
            DetectError::Partial {
                found,
                expected,
                grid: [nx, ny],
                touches_border,
            } => {
                write!(f, "found {found} of {expected} corners")?;
                if *touches_border {
                    write!(f, ": {AT_BORDER}; move the board or the camera so the whole board is in view")
                } else if *nx > 2 && *ny > 2 {
                    // Counting squares instead of inner corners is the commonest slip: a
                    // 9x6 board given as 10x7 finds part of a grid that is not there.
                    write!(
                        f,
                        "; check the grid size (inner corners, not squares: a board of {nx}x{ny} squares has {}x{} inner corners), the focus and the lighting (glare or shadow across the board)",
                        nx - 1,
                        ny - 1
                    )
                } else {
                    write!(f, "; check the grid size (inner corners, not squares), the focus and the lighting (glare or shadow across the board)")
                }
            }
            DetectError::WrongSize { found, expected } => write!(
                f,
                "found a grid of {}x{} inner corners where {}x{} was expected; check the grid size (inner corners, not squares)",
                found[0], found[1], expected[0], expected[1]
            ),
            DetectError::NoOrigin => write!(
                f,
                "the square colours do not single out the grid's origin: use a board with an odd number of squares one way and an even number the other"
            ),
        }
    }
}

impl std::error::Error for DetectError {}

/// A detected grid: `corners[j * nx + i]` is inner corner (i, j), in pixels.
#[derive(Debug, Clone)]
pub struct Grid {
    pub nx: usize,
    pub ny: usize,
    pub corners: Vec<[f64; 2]>,
    /// Corners (indices into `corners`) that were not detected but placed midway between
    /// their neighbours (a shadow's edge or glare across them; at most a tenth of the
    /// grid, each with three of its four neighbours found). They are approximate: leave
    /// them out of any fit.
    pub filled: Vec<usize>,
    /// Corners found, but whose position moves by more than 0.3 px when image edges that
    /// miss the corner are down-weighted: something besides the board's two edges (a
    /// shadow's edge, glare, the board's rim in a foreshortened row) is in the window.
    /// Leave them out of a fit too.
    pub doubtful: Vec<usize>,
    /// Median distance between neighbouring corners, pixels.
    pub spacing_px: f64,
    /// Smallest half-size of the refinement windows, pixels (each corner's window reaches
    /// half-way to its nearest neighbour, at most 11).
    pub window: usize,
}

#[derive(Debug, Clone, Copy)]
struct Candidate {
    p: [f64; 2],
    strength: f64,
    /// Ring contrast (light minus dark), in image units.
    contrast: f64,
}

/// Largest distance of a corner from the midpoint of two opposite neighbours, as a
/// fraction of their distance apart (perspective and lens distortion stay far below it).
const MAX_MIDPOINT_ERROR: f64 = 0.1;

/// Scale of the robust weights of the refinement, pixels.
const ROBUST_PX: f64 = 2.0;

/// Largest move of a corner when edges that miss it are down-weighted, pixels.
const MAX_ROBUST_SHIFT: f64 = 0.3;

/// Largest move of a corner when its squares are levelled ([`equalised`]), pixels.
const MAX_LEVELLED_SHIFT: f64 = 0.3;

/// Smallest spacing of the grid's corners (pixels) at which its corners are levelled; a
/// grid of smaller squares is refined in linear light only. With squares 7-9 px wide (the
/// mock rig at 160x120 and 200x150) levelling halved the corners' residual but moved the
/// camera centre 2-7 mm further from the truth and f 1-2% (its planes are fitted to pixels
/// mostly blurred by the edges); from 11 px on it was as good or better. The whole grid
/// is treated alike: levelling some corners and not others (by their own windows) bent the
/// grid more than either (n -6% at 240x180 against -3% for both).
const MIN_LEVELLED_SPACING: f64 = 10.0;

/// Smoothing (pixels) before the sub-pixel refinement.
const REFINE_SIGMA: f64 = 1.0;

/// Largest side of the image the candidates are searched on.
const SEARCH_SIDE: usize = 1024;

/// Smallest spacing of the corners (pixels, at the search scale) for a grid found at the
/// coarse scale to be kept.
const COARSE_MIN_SPACING: f64 = 12.0;

/// Find the `nx` x `ny` inner-corner grid.
///
/// Coarse to fine: the grid is first searched for at half the search scale (a quarter of
/// the pixels), and kept if its squares are large there (corners at least
/// COARSE_MIN_SPACING apart) and every corner was found; else the search is made again at
/// the search scale. Either way the corners are refined on the full-resolution image.
pub fn detect(img: &Gray, nx: usize, ny: usize) -> Result<Grid, DetectError> {
    detect_refined_on(img, None, nx, ny)
}

/// [`detect`] with the corners refined on `linear`, the same photo in linear light (its
/// values proportional to the light, through the camera's response), each corner's four
/// squares first brought to one light and one dark level ([`equalised`]).
///
/// Why: a chessboard corner is located without bias only where its two light squares
/// look alike and so do its two dark ones (the corner is then symmetric about its
/// centre). Light falls off across a board, so they never do exactly; and the camera's
/// tone curve bends the partly covered pixels along the edges, which no levelling after
/// it can undo. On simulated boards under a lamp, through gamma-like responses, corners
/// refined on the photo as it is were 0.05-0.08 px (rms) from the truth, in a pattern
/// that alternates from corner to corner; linearised and levelled, 0.02 px.
pub fn detect_linear(img: &Gray, linear: &Gray, nx: usize, ny: usize) -> Result<Grid, DetectError> {
    if (linear.width, linear.height) != (img.width, img.height) {
        return Err(DetectError::NoGrid);
    }
    detect_refined_on(img, Some(linear), nx, ny)
}

fn detect_refined_on(
    img: &Gray,
    linear: Option<&Gray>,
    nx: usize,
    ny: usize,
) -> Result<Grid, DetectError> {
    let f = img.width.max(img.height).div_ceil(SEARCH_SIDE).max(1);
    if img.width.min(img.height) / (2 * f) >= 64 {
        if let Ok(g) = detect_at(img, linear, nx, ny, 2 * f) {
            if g.filled.is_empty() && g.spacing_px / (2 * f) as f64 >= COARSE_MIN_SPACING {
                return Ok(g);
            }
        }
    }
    detect_at(img, linear, nx, ny, f)
}

/// [`detect`] with the candidates searched for on the image shrunk `f` times (and the
/// corners refined on `linear` where it is given).
fn detect_at(
    img: &Gray,
    linear: Option<&Gray>,
    nx: usize,
    ny: usize,
    f: usize,
) -> Result<Grid, DetectError> {
    let small_blur = img.shrink_blur(f, 1.5);
    let cands = candidates(&small_blur);
    if cands.len() < 4 {
        return Err(DetectError::NoGrid);
    }
    let expected = nx * ny;
    let labels = grow_best(&small_blur, &cands, expected);
    if labels.len() < 4 {
        return Err(DetectError::NoGrid);
    }
    // The grid grown from the seed may carry stray corners of the background at its
    // edges; the board is the one fully populated window of the expected size.
    let grid = LabelGrid::new(&small_blur, &cands, &labels);
    let shapes = if nx == ny {
        vec![(nx, ny)]
    } else {
        vec![(nx, ny), (ny, nx)]
    };
    let touches_border = || {
        let margin = 0.75 * spacing(&cands, &labels) * f as f64;
        labels.values().any(|&k| {
            let p = scale_up(cands[k].p, f);
            p[0] < margin
                || p[1] < margin
                || p[0] > img.width as f64 - 1.0 - margin
                || p[1] > img.height as f64 - 1.0 - margin
        })
    };
    let (i0, j0, a, b) = grid.board(&shapes, [nx, ny], touches_border)?;
    // Label grid (A x B) in image positions, full resolution.
    let mut pos = vec![[f64::NAN; 2]; a * b];
    for (&(i, j), &k) in &labels {
        if (i0..i0 + a as i32).contains(&i) && (j0..j0 + b as i32).contains(&j) {
            pos[(j - j0) as usize * a + (i - i0) as usize] = scale_up(cands[k].p, f);
        }
    }
    let holes = place_missing(&mut pos, a, b, [nx, ny])?;
    let sp = spacing(&cands, &labels) * f as f64;
    let (refined, doubtful, window) = refine_corners(img, linear, &pos, &holes, a, b, sp);
    let mut pos = refined;
    let mut holes = holes;
    place_snapped(&mut pos, &mut holes, a, b, [nx, ny])?;
    let order = orient(img, &pos, a, b, nx, ny)?;
    let corners = order.iter().map(|&k| pos[k]).collect();
    let filled = order
        .iter()
        .enumerate()
        .filter(|(_, k)| holes.contains(k))
        .map(|(n, _)| n)
        .collect();
    let doubtful = order
        .iter()
        .enumerate()
        .filter(|(_, k)| doubtful.contains(k) && !holes.contains(k))
        .map(|(n, _)| n)
        .collect();
    Ok(Grid {
        nx,
        ny,
        corners,
        filled,
        doubtful,
        spacing_px: sp,
        window,
    })
}

/// A position at detection scale (the image shrunk `f` times) in the full image.
fn scale_up(p: [f64; 2], f: usize) -> [f64; 2] {
    let o = (f as f64 - 1.0) / 2.0;
    [p[0] * f as f64 + o, p[1] * f as f64 + o]
}

/// The largest grid of labels grown from one of the first 30 candidates as its seed (the
/// first that holds `expected` corners or more).
fn grow_best(
    small_blur: &Gray,
    cands: &[Candidate],
    expected: usize,
) -> HashMap<(i32, i32), usize> {
    let mut best: Option<HashMap<(i32, i32), usize>> = None;
    for seed in 0..cands.len().min(30) {
        let g = grow(small_blur, cands, seed);
        if best.as_ref().is_none_or(|b| g.len() > b.len()) {
            best = Some(g);
        }
        if best.as_ref().is_some_and(|b| b.len() >= expected) {
            break;
        }
    }
    best.unwrap_or_default()
}

/// The labels as a dense grid over their extent (the window search looks each up many
/// times), and which links between neighbouring labels run along an edge of the board:
/// bit 1 the link to (i + 1, j), bit 0 the link to (i, j + 1).
struct LabelGrid {
    i0: i32,
    i1: i32,
    j0: i32,
    j1: i32,
    gw: usize,
    grid: Vec<usize>,
    links: Vec<u8>,
}

impl LabelGrid {
    fn new(small_blur: &Gray, cands: &[Candidate], labels: &HashMap<(i32, i32), usize>) -> Self {
        let (i0, i1) = minmax(labels.keys().map(|k| k.0));
        let (j0, j1) = minmax(labels.keys().map(|k| k.1));
        let gw = (i1 - i0 + 1) as usize;
        let gh = (j1 - j0 + 1) as usize;
        let mut grid = vec![usize::MAX; gw * gh];
        for (&(i, j), &k) in labels {
            grid[(j - j0) as usize * gw + (i - i0) as usize] = k;
        }
        let mut g = LabelGrid {
            i0,
            i1,
            j0,
            j1,
            gw,
            grid,
            links: vec![0u8; gw * gh],
        };
        for (&(i, j), &k) in labels {
            for (di, dj) in [(1, 0), (0, 1)] {
                if let Some(n) = g.cell(i + di, j + dj) {
                    if is_edge(small_blur, &cands[k], &cands[n]) {
                        g.links[(j - j0) as usize * gw + (i - i0) as usize] |= 1 << di;
                    }
                }
            }
        }
        g
    }

    fn cell(&self, i: i32, j: i32) -> Option<usize> {
        if i < self.i0 || i > self.i1 || j < self.j0 || j > self.j1 {
            return None;
        }
        let k = self.grid[(j - self.j0) as usize * self.gw + (i - self.i0) as usize];
        (k != usize::MAX).then_some(k)
    }

    fn has(&self, i: i32, j: i32) -> bool {
        self.cell(i, j).is_some()
    }

    fn edge(&self, i: i32, j: i32, di: i32) -> bool {
        self.has(i, j)
            && self.links[(j - self.j0) as usize * self.gw + (i - self.i0) as usize] & (1 << di)
                != 0
    }

    /// All corners of the window present and every link between them an edge of the board
    /// (stray corners along the board's outer edge have a square on one side only).
    fn full(&self, i: i32, j: i32, w: usize, h: usize) -> bool {
        let has = |a, b| self.has(a, b);
        let edge = |a, b, d| self.edge(a, b, d);
        (0..h as i32).all(|dj| {
            (0..w as i32).all(|di| {
                let (a, b) = (i + di, j + dj);
                has(a, b)
                    && (di + 1 == w as i32 || edge(a, b, 1))
                    && (dj + 1 == h as i32 || edge(a, b, 0))
            })
        })
    }

    /// Corners present in the window.
    fn count(&self, i: i32, j: i32, w: usize, h: usize) -> usize {
        let has = |a, b| self.has(a, b);
        (0..h as i32)
            .flat_map(|dj| (0..w as i32).map(move |di| (i + di, j + dj)))
            .filter(|k| has(k.0, k.1))
            .count()
    }

    /// A window with a few corners missing (a shadow's edge or glare across a corner):
    /// accepted when each missing corner has at least three of its four neighbours, so
    /// the board's extent is certain; the missing corners are then found from where their
    /// neighbours put them. The number missing, where accepted.
    fn holes_ok(&self, i: i32, j: i32, w: usize, h: usize) -> Option<usize> {
        let has = |a, b| self.has(a, b);
        let edge = |a, b, d| self.edge(a, b, d);
        let max_missing = (w * h / 10).max(1);
        let mut missing = 0;
        for dj in 0..h as i32 {
            for di in 0..w as i32 {
                let (x, y) = (i + di, j + dj);
                if has(x, y) {
                    if di + 1 < w as i32 && has(x + 1, y) && !edge(x, y, 1) {
                        return None;
                    }
                    if dj + 1 < h as i32 && has(x, y + 1) && !edge(x, y, 0) {
                        return None;
                    }
                    continue;
                }
                missing += 1;
                let inside = |(a, b): (i32, i32)| {
                    (i..i + w as i32).contains(&a) && (j..j + h as i32).contains(&b)
                };
                let around = [(x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)]
                    .into_iter()
                    .filter(|&n| inside(n) && has(n.0, n.1))
                    .count();
                if around < 3 {
                    return None;
                }
            }
        }
        (missing <= max_missing).then_some(missing)
    }

    /// Every window of one of `shapes` (w, h) over the grid's extent, as (i, j, w, h), in
    /// the order the search has always taken them.
    fn windows<'s>(
        &'s self,
        shapes: &'s [(usize, usize)],
    ) -> impl Iterator<Item = (i32, i32, usize, usize)> + 's {
        shapes.iter().flat_map(move |&(w, h)| {
            (self.j0 - h as i32 + 1..=self.j1)
                .flat_map(move |j| (self.i0 - w as i32 + 1..=self.i1).map(move |i| (i, j, w, h)))
        })
    }

    /// The board: the one full window of one of `shapes`, or failing that the one window
    /// with the fewest corners missing ([`LabelGrid::holes_ok`]), as (i, j, A, B). Refused
    /// where there is none (`touches_border`: whether the labels reach the image's
    /// border, for the message), or where the board is bigger than `nx` x `ny`.
    fn board(
        &self,
        shapes: &[(usize, usize)],
        [nx, ny]: [usize; 2],
        touches_border: impl FnOnce() -> bool,
    ) -> Result<(i32, i32, usize, usize), DetectError> {
        let mut windows: Vec<(i32, i32, usize, usize)> = self
            .windows(shapes)
            .filter(|&(i, j, w, h)| self.full(i, j, w, h))
            .collect();
        let bigger = |found: [usize; 2]| DetectError::WrongSize {
            found: if (found[0] >= found[1]) == (nx >= ny) {
                found
            } else {
                [found[1], found[0]]
            },
            expected: [nx, ny],
        };
        if windows.is_empty() {
            let mut holed: Vec<(usize, (i32, i32, usize, usize))> = self
                .windows(shapes)
                .filter_map(|(i, j, w, h)| self.holes_ok(i, j, w, h).map(|m| (m, (i, j, w, h))))
                .collect();
            holed.sort_by_key(|x| x.0);
            if holed.len() == 1 || (holed.len() > 1 && holed[0].0 < holed[1].0) {
                windows.push(holed[0].1);
            }
        }
        match windows.as_slice() {
            [] => {
                let touches = touches_border();
                // The most corners any window of the expected size holds (counted only
                // here, for the message: it is the window search's largest cost).
                let most = self
                    .windows(shapes)
                    .map(|(i, j, w, h)| self.count(i, j, w, h))
                    .fold(0, usize::max);
                Err(DetectError::Partial {
                    found: most,
                    expected: nx * ny,
                    grid: [nx, ny],
                    touches_border: touches,
                })
            }
            [(i, j, w, h)] => {
                // A full row or column beyond the window means the board is bigger.
                let (i, j, w, h) = (*i, *j, *w, *h);
                if self.full(i - 1, j, w + 1, h) || self.full(i, j, w + 1, h) {
                    return Err(bigger([w + 1, h]));
                }
                if self.full(i, j - 1, w, h + 1) || self.full(i, j, w, h + 1) {
                    return Err(bigger([w, h + 1]));
                }
                Ok((i, j, w, h))
            }
            many => {
                let (a0, a1) = minmax(many.iter().map(|w| w.0));
                let (b0, b1) = minmax(many.iter().map(|w| w.1));
                let (w, h) = (many[0].2, many[0].3);
                Err(bigger([w + (a1 - a0) as usize, h + (b1 - b0) as usize]))
            }
        }
    }
}

/// Missing corners of the A x B grid `pos` (NaN) placed at the mean of the midpoints of
/// their opposite neighbours; returns their indices. Refused where one has no pair of
/// opposite neighbours.
fn place_missing(
    pos: &mut [[f64; 2]],
    a: usize,
    b: usize,
    [nx, ny]: [usize; 2],
) -> Result<Vec<usize>, DetectError> {
    let expected = nx * ny;
    let holes: Vec<usize> = (0..a * b).filter(|&k| pos[k][0].is_nan()).collect();
    for &k in &holes {
        let (i, j) = (k % a, k / a);
        let mut acc = [0.0; 2];
        let mut n = 0.0;
        if i > 0 && i + 1 < a {
            let (p, q) = (pos[k - 1], pos[k + 1]);
            if !p[0].is_nan() && !q[0].is_nan() {
                acc = [acc[0] + 0.5 * (p[0] + q[0]), acc[1] + 0.5 * (p[1] + q[1])];
                n += 1.0;
            }
        }
        if j > 0 && j + 1 < b {
            let (p, q) = (pos[k - a], pos[k + a]);
            if !p[0].is_nan() && !q[0].is_nan() {
                acc = [acc[0] + 0.5 * (p[0] + q[0]), acc[1] + 0.5 * (p[1] + q[1])];
                n += 1.0;
            }
        }
        if n == 0.0 {
            return Err(DetectError::Partial {
                found: expected - holes.len(),
                expected,
                grid: [nx, ny],
                touches_border: false,
            });
        }
        pos[k] = [acc[0] / n, acc[1] / n];
    }
    Ok(holes)
}

/// Every corner of the A x B grid `pos` but the placed ones (`holes`) refined to subpixel
/// accuracy, on `linear` where it is given, else on `img`: the refined corners, those a
/// robust refinement moves (doubtful), and the smallest refinement window. `sp`: the
/// board's spacing in pixels.
fn refine_corners(
    img: &Gray,
    linear: Option<&Gray>,
    pos: &[[f64; 2]],
    holes: &[usize],
    a: usize,
    b: usize,
    sp: f64,
) -> (Vec<[f64; 2]>, Vec<usize>, usize) {
    // Each corner's window reaches half-way to its nearest neighbour (at most 11 px,
    // OpenCV's usual choice): wider windows take in edges that do not pass through the
    // corner and bias it (measured on foreshortened simulated boards).
    let near = |i: usize, j: usize| {
        let p = pos[j * a + i];
        let mut d = f64::INFINITY;
        if i > 0 {
            d = d.min(dist(p, pos[j * a + i - 1]));
        }
        if i + 1 < a {
            d = d.min(dist(p, pos[j * a + i + 1]));
        }
        if j > 0 {
            d = d.min(dist(p, pos[(j - 1) * a + i]));
        }
        if j + 1 < b {
            d = d.min(dist(p, pos[(j + 1) * a + i]));
        }
        d
    };
    let windows: Vec<usize> = (0..a * b)
        .map(|k| ((0.5 * near(k % a, k / a)).floor() as usize).clamp(2, 11))
        .collect();
    let window = *windows.iter().min().unwrap_or(&2);
    // Refined on a lightly smoothed copy: on a sharp image the gradients of sampled edges
    // depend on where the edge falls within its pixel, which pulls corners towards pixel
    // rows and columns ("pixel locking"; up to 0.1 px on sharp simulated boards).
    // Only a box around each corner is smoothed: the window's reach and a few pixels for
    // the corner to move. Should the refinement leave it, the box grows.
    let taps = gauss_taps(REFINE_SIGMA);
    let smooth_near = |img: &Gray, p: [f64; 2], reach: usize, patch: &mut Patch| {
        let c = |v: f64, n: usize| (v.round().max(0.0) as usize).min(n - 1);
        let (x, y) = (c(p[0], img.width), c(p[1], img.height));
        patch.smoothed(
            img,
            &taps,
            [
                x.saturating_sub(reach),
                y.saturating_sub(reach),
                (x + reach).min(img.width - 1),
                (y + reach).min(img.height - 1),
            ],
        )
    };
    let refine_near = |img: &Gray, p: [f64; 2], half: usize, robust: bool, patch: &mut Patch| {
        if let Some(q) = refine_in(patch, p, half, robust) {
            return q;
        }
        smooth_near(img, p, img.width.max(img.height), patch);
        refine_in(patch, p, half, robust).expect("the whole image holds every window")
    };
    let base = linear.unwrap_or(img);
    // Placed corners are not refined: whatever hid them (a shadow's edge, glare) would
    // pull the refinement; they only complete the grid and are not used for fitting.
    let mut doubtful = Vec::new();
    let mut refined = Vec::with_capacity(a * b);
    let mut patch = Patch::new();
    for (k, (p, w)) in pos.iter().zip(&windows).enumerate() {
        if holes.contains(&k) {
            refined.push(*p);
            continue;
        }
        smooth_near(base, *p, w + 4, &mut patch);
        let mut q = refine_near(base, *p, *w, false, &mut patch);
        // In linear light, again with the corner's squares levelled about it (the box
        // holds the window, the corner's room to move and the smoothing's reach).
        let levelled = linear
            .filter(|_| sp >= MIN_LEVELLED_SPACING)
            .and_then(|l| equalised(l, q, w + 4 + taps.len() / 2));
        let tried = levelled.is_some();
        // Where down-weighting edges that miss the corner moves it, something besides
        // the board's two edges (a shadow's edge, glare, a mark) is in the window: the
        // corner is unreliable and is placed, not used.
        // Levelling corrects a corner by hundredths of a pixel: one that moves it further
        // (a plane fitted across the board's rim or a shadow) is not used.
        let moved = levelled.and_then(|(sub, [ox, oy])| {
            let (ox, oy) = (ox as f64, oy as f64);
            let local = [q[0] - ox, q[1] - oy];
            smooth_near(&sub, local, w + 4, &mut patch);
            let lq = refine_near(&sub, local, *w, false, &mut patch);
            let lq = [lq[0] + ox, lq[1] + oy];
            let shift = dist(lq, q);
            if shift.is_nan() || shift > MAX_LEVELLED_SHIFT {
                return None;
            }
            let lr = refine_near(&sub, [lq[0] - ox, lq[1] - oy], *w, true, &mut patch);
            Some((lq, [lr[0] + ox, lr[1] + oy]))
        });
        let r = match moved {
            Some((lq, lr)) => {
                q = lq;
                lr
            }
            None => {
                if tried {
                    // The box was smoothed from the levelled copy: smooth the image again.
                    smooth_near(base, q, w + 4, &mut patch);
                }
                refine_near(base, q, *w, true, &mut patch)
            }
        };
        if dist(q, r) > MAX_ROBUST_SHIFT {
            doubtful.push(k);
        }
        refined.push(q);
    }
    (refined, doubtful, window)
}

/// A corner far from the midpoint of its opposite neighbours (on each axis where it has
/// both) was snapped to something else near it (a shadow's edge crossing a square's
/// edge): it becomes a placed corner (moved there, and added to `holes`). Refused when
/// more than a tenth of the corners would be placed.
fn place_snapped(
    pos: &mut [[f64; 2]],
    holes: &mut Vec<usize>,
    a: usize,
    b: usize,
    [nx, ny]: [usize; 2],
) -> Result<(), DetectError> {
    let expected = nx * ny;
    let mid_error = |pos: &[[f64; 2]], k: usize| -> Option<(f64, [f64; 2])> {
        let (i, j) = (k % a, k / a);
        let mut best: Option<(f64, [f64; 2])> = None;
        for (ok, d) in [(i > 0 && i + 1 < a, 1), (j > 0 && j + 1 < b, a)] {
            if ok {
                let (p, q) = (pos[k - d], pos[k + d]);
                let m = [0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1])];
                let e = dist(m, pos[k]) / dist(p, q).max(1e-9);
                if best.is_none_or(|b| e < b.0) {
                    best = Some((e, m));
                }
            }
        }
        best
    };
    // The worst first, one at a time: a wrong corner also spoils its neighbours' midpoints.
    loop {
        let worst = (0..a * b)
            .filter(|k| !holes.contains(k))
            .filter_map(|k| mid_error(pos, k).map(|(e, m)| (e, k, m)))
            .max_by(|x, y| x.0.total_cmp(&y.0));
        match worst {
            Some((e, k, m)) if e > MAX_MIDPOINT_ERROR => {
                if holes.len() + 1 > (expected / 10).max(1) {
                    return Err(DetectError::Partial {
                        found: expected - holes.len() - 1,
                        expected,
                        grid: [nx, ny],
                        touches_border: false,
                    });
                }
                pos[k] = m;
                holes.push(k);
            }
            _ => break,
        }
    }
    Ok(())
}

fn minmax(it: impl Iterator<Item = i32>) -> (i32, i32) {
    it.fold((i32::MAX, i32::MIN), |(a, b), v| (a.min(v), b.max(v)))
}

/// Median distance between labelled neighbours (detection scale).
fn spacing(c: &[Candidate], labels: &HashMap<(i32, i32), usize>) -> f64 {
    let mut d: Vec<f64> = labels
        .iter()
        .filter_map(|(&(i, j), &k)| labels.get(&(i + 1, j)).map(|&n| dist(c[k].p, c[n].p)))
        .collect();
    if d.is_empty() {
        return 10.0;
    }
    d.sort_by(|x, y| x.total_cmp(y));
    d[d.len() / 2]
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
}

/// Saddle points that pass the ring test, strongest first.
///
/// The saddle measure is worked out twice, row by row: once for its largest value (the
/// floor below is relative to it), then into a ring of the seven rows that the
/// non-maximum suppression looks at (an image-sized buffer costs more in page faults than
/// the arithmetic).
fn candidates(b: &Gray) -> Vec<Candidate> {
    let (w, h) = (b.width, b.height);
    if w < 16 || h < 16 {
        return Vec::new();
    }
    // The saddle measure of row y (1..h-1) into `out`, zero at both ends.
    let saddle = |y: usize, out: &mut [f32]| {
        let n = w - 2;
        let up = &b.data[(y - 1) * w..y * w];
        let row = &b.data[y * w..(y + 1) * w];
        let down = &b.data[(y + 1) * w..(y + 2) * w];
        let (ul, u, ur) = (&up[..n], &up[1..n + 1], &up[2..n + 2]);
        let (l, c, r) = (&row[..n], &row[1..n + 1], &row[2..n + 2]);
        let (dl, d, dr) = (&down[..n], &down[1..n + 1], &down[2..n + 2]);
        let o = &mut out[1..n + 1];
        for i in 0..n {
            let fxx = r[i] - 2.0 * c[i] + l[i];
            let fyy = d[i] - 2.0 * c[i] + u[i];
            let fxy = (dr[i] - ur[i] - dl[i] + ul[i]) * 0.25;
            o[i] = (fxy * fxy - fxx * fyy).max(0.0);
        }
        out[0] = 0.0;
        out[w - 1] = 0.0;
    };
    let mut ring = vec![0f32; 8 * w];
    let mut max = 0.0f32;
    for y in 1..h - 1 {
        let row = &mut ring[..w];
        saddle(y, row);
        max = row.iter().cloned().fold(max, f32::max);
    }
    if max <= 0.0 {
        return Vec::new();
    }
    // Saddles weaker than 0.5% of the strongest (contrast about 7% of the strongest
    // corner's) are not looked at.
    let floor = max * 5e-3;
    const R: usize = 3;
    let ring_r = 5.0;
    let mut out = Vec::new();
    let y0 = R.max(6);
    // Rows y0 - R.. are in the ring (row y at (y % 8) * w).
    let mut next = y0 - R;
    for y in y0..h - y0 {
        while next <= y + R {
            saddle(next, &mut ring[(next % 8) * w..][..w]);
            next += 1;
        }
        let at = |yy: usize, xx: usize| ring[(yy % 8) * w + xx];
        let srow = &ring[(y % 8) * w..][..w];
        for x in y0..w - y0 {
            let v = srow[x];
            if v <= floor {
                continue;
            }
            // The 3 x 3 neighbourhood first: it rejects almost every pixel.
            if srow[x - 1] > v || srow[x + 1] > v || at(y - 1, x) > v || at(y + 1, x) > v {
                continue;
            }
            let mut is_max = true;
            'n: for yy in y - R..=y + R {
                let nrow = &ring[(yy % 8) * w..][..w];
                for (xx, &o) in nrow.iter().enumerate().take(x + R + 1).skip(x - R) {
                    if o > v || (o == v && (yy, xx) < (y, x)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if !is_max {
                continue;
            }
            // Sub-pixel peak of the saddle measure (parabola per axis).
            let px = |a: f32, c: f32, d: f32| {
                let den = a - 2.0 * c + d;
                if den.abs() > 1e-12 {
                    (0.5 * (a - d) / den).clamp(-0.5, 0.5) as f64
                } else {
                    0.0
                }
            };
            let p = [
                x as f64 + px(srow[x - 1], v, srow[x + 1]),
                y as f64 + px(at(y - 1, x), v, at(y + 1, x)),
            ];
            if let Some(contrast) = ring_test(b, p, ring_r) {
                out.push(Candidate {
                    p,
                    strength: v as f64,
                    contrast,
                });
            }
        }
    }
    out.sort_by(|a, b| b.strength.total_cmp(&a.strength));
    out.truncate(2000);
    out
}

/// Four sectors, alternately dark and light, opposite sectors alike: the ring's contrast.
fn ring_test(img: &Gray, p: [f64; 2], r: f64) -> Option<f64> {
    const N: usize = 24;
    // cos and sin of k * 15 degrees.
    const C: [f64; 7] = [
        1.0,
        0.965_925_826_289_068_3,
        0.866_025_403_784_438_6,
        std::f64::consts::FRAC_1_SQRT_2,
        0.5,
        0.258_819_045_102_520_8,
        0.0,
    ];
    let cs = |k: usize| -> (f64, f64) {
        let q = k / 6;
        let m = k % 6;
        let (c, s) = (C[m], C[6 - m]);
        match q {
            0 => (c, s),
            1 => (-s, c),
            2 => (-c, -s),
            _ => (s, -c),
        }
    };
    let v: [f64; N] = std::array::from_fn(|k| {
        let (c, s) = cs(k);
        img.sample(p[0] + r * c, p[1] + r * s)
    });
    let mean = v.iter().sum::<f64>() / N as f64;
    let (lo, hi) = v
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    let contrast = hi - lo;
    if contrast < 8.0 {
        return None;
    }
    let changes = (0..N)
        .filter(|&k| (v[k] > mean) != (v[(k + 1) % N] > mean))
        .count();
    if changes != 4 {
        return None;
    }
    let asym = (0..N / 2).map(|k| (v[k] - v[k + N / 2]).abs()).sum::<f64>() / (N / 2) as f64;
    (asym < 0.35 * contrast).then_some(contrast)
}

/// Whether the segment p-q runs along an edge of the board: dark on one side, light on
/// the other, across a quarter of its length each way.
fn is_edge(img: &Gray, p: &Candidate, q: &Candidate) -> bool {
    let m = [0.5 * (p.p[0] + q.p[0]), 0.5 * (p.p[1] + q.p[1])];
    let n = [-(q.p[1] - p.p[1]) * 0.25, (q.p[0] - p.p[0]) * 0.25];
    let a = img.sample(m[0] + n[0], m[1] + n[1]);
    let b = img.sample(m[0] - n[0], m[1] - n[1]);
    (a - b).abs() > 0.4 * p.contrast.min(q.contrast)
}

/// Grow a grid of labels from candidate `seed`.
fn grow(img: &Gray, c: &[Candidate], seed: usize) -> HashMap<(i32, i32), usize> {
    let mut labels: HashMap<(i32, i32), usize> = HashMap::new();
    let p0 = c[seed].p;
    // Nearest neighbours of the seed.
    let mut near: Vec<(f64, usize)> = c
        .iter()
        .enumerate()
        .filter(|(k, _)| *k != seed)
        .map(|(k, q)| (dist(p0, q.p), k))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.truncate(8);
    let Some(&(da, ka)) = near.iter().find(|(_, k)| is_edge(img, &c[seed], &c[*k])) else {
        return labels;
    };
    let a = [c[ka].p[0] - p0[0], c[ka].p[1] - p0[1]];
    let Some(&(_, kb)) = near.iter().skip(1).find(|(d, k)| {
        let v = [c[*k].p[0] - p0[0], c[*k].p[1] - p0[1]];
        let cos = (a[0] * v[0] + a[1] * v[1]) / (da * d);
        cos.abs() < 0.5 && *d < 2.0 * da && is_edge(img, &c[seed], &c[*k])
    }) else {
        return labels;
    };
    let b = [c[kb].p[0] - p0[0], c[kb].p[1] - p0[1]];
    labels.insert((0, 0), seed);
    labels.insert((1, 0), ka);
    labels.insert((0, 1), kb);
    let mut used = vec![false; c.len()];
    for k in [seed, ka, kb] {
        used[k] = true;
    }
    let mut queue: VecDeque<(i32, i32)> = [(0, 0), (1, 0), (0, 1)].into_iter().collect();
    let dirs = [(1, 0), (-1, 0), (0, 1), (0, -1)];
    while let Some((i, j)) = queue.pop_front() {
        let p = c[labels[&(i, j)]].p;
        for (di, dj) in dirs {
            let t = (i + di, j + dj);
            if labels.contains_key(&t) {
                continue;
            }
            // The step: the last step in this direction, or the same step one row or
            // column over, or the seed's.
            let step = if let Some(&k) = labels.get(&(i - di, j - dj)) {
                [p[0] - c[k].p[0], p[1] - c[k].p[1]]
            } else if let Some(s) = [(dj, di), (-dj, -di)].iter().find_map(|&(oi, oj)| {
                let q0 = labels.get(&(i + oi, j + oj))?;
                let q1 = labels.get(&(i + oi + di, j + oj + dj))?;
                Some([c[*q1].p[0] - c[*q0].p[0], c[*q1].p[1] - c[*q0].p[1]])
            }) {
                s
            } else {
                let s = if di != 0 { a } else { b };
                let k = (di + dj) as f64;
                [s[0] * k, s[1] * k]
            };
            let pred = [p[0] + step[0], p[1] + step[1]];
            let tol = 0.3 * step[0].hypot(step[1]);
            // The nearest unused candidate within the tolerance (the first of equals).
            let mut hit: Option<(f64, usize)> = None;
            for (k, q) in c.iter().enumerate() {
                let d = dist(pred, q.p);
                if d < tol && !used[k] && hit.is_none_or(|h| d < h.0) {
                    hit = Some((d, k));
                }
            }
            let hit = hit.filter(|(_, k)| is_edge(img, &c[labels[&(i, j)]], &c[*k]));
            if let Some((_, k)) = hit {
                labels.insert(t, k);
                used[k] = true;
                queue.push_back(t);
            }
        }
    }
    labels
}

/// Sub-pixel corner: the point q where every gradient g_p in the window satisfies
/// g_p . (q - p) = 0 (Förstner's corner; the condition OpenCV's cornerSubPix solves),
/// weighted by a Gaussian of |p - q| over the window, solved by iteration. The gradients
/// are central differences at whole pixels, so no interpolation enters them.
///
/// With `robust`, pixels whose edge does not pass near q (a shadow's edge, a mark on the
/// board) are down-weighted: Tukey's biweight of the distance from q to the pixel's edge
/// line, |g . (q - p)| / |g|, at ROBUST_PX.
pub fn refine(img: &Gray, start: [f64; 2], half: usize, robust: bool) -> [f64; 2] {
    let mut whole = Patch::new();
    whole.whole(img);
    refine_in(&whole, start, half, robust).expect("the whole image holds every window")
}

/// [`refine`] on a patch (a box of the smoothed image with its gradient products); None if
/// a window reaches outside the box.
///
/// Each iteration weighs the patch's products with the Gaussian window, row by row (the
/// weight separates into a row factor and a column factor, and each factor is one
/// Gaussian times a geometric series, so an iteration takes four exponentials, not one
/// per row and column).
fn refine_in(src: &Patch, start: [f64; 2], half: usize, robust: bool) -> Option<[f64; 2]> {
    let w = half as isize;
    let s2 = (half * half) as f64;
    let (iw, ih) = (src.iw as isize, src.ih as isize);
    let (bx0, by0) = (src.x0 as isize, src.y0 as isize);
    let bw = src.bw;
    let (bx1, by1) = (bx0 + bw as isize - 1, by0 + src.bh as isize - 1);
    let g = &src.g;
    let mut q = start;
    let n = (2 * w + 1) as usize;
    // exp(-o^2 / s2), o = -w..=w: the window's weights about a whole pixel.
    let g0: Vec<f64> = (0..n)
        .map(|k| {
            let o = k as f64 - w as f64;
            (-(o * o) / s2).exp()
        })
        .collect();
    let (mut ex, mut ey) = (vec![0.0; n], vec![0.0; n]);
    // exp(-(o + d)^2 / s2) = exp(-o^2 / s2) exp(-d^2 / s2) exp(-2 d / s2)^o.
    let weights = |d: f64, out: &mut [f64]| {
        let a = (-(d * d) / s2).exp();
        let (up, down) = ((-2.0 * d / s2).exp(), (2.0 * d / s2).exp());
        let c = half;
        out[c] = g0[c] * a;
        let (mut pu, mut pd) = (a, a);
        for o in 1..=c {
            pu *= up;
            pd *= down;
            out[c + o] = g0[c + o] * pu;
            out[c - o] = g0[c - o] * pd;
        }
    };
    for _ in 0..30 {
        let (qx, qy) = (q[0].round() as isize, q[1].round() as isize);
        let (xa, xb) = ((qx - w).max(1), (qx + w).min(iw - 2));
        let (ya, yb) = ((qy - w).max(1), (qy + w).min(ih - 2));
        if xa <= xb && ya <= yb && (xa - 1 < bx0 || xb + 1 > bx1 || ya - 1 < by0 || yb + 1 > by1) {
            return None;
        }
        // The Gaussian weight separates: exp(-dx^2/s2) exp(-dy^2/s2).
        weights(qx as f64 - q[0], &mut ex);
        weights(qy as f64 - q[1], &mut ey);
        let mut sums = [0.0f64; 5];
        for y in ya..=yb {
            let wy = ey[(y - qy + w) as usize];
            let yb_ = (y - by0) as usize * bw;
            let cells = &g[yb_ + (xa - bx0) as usize..=yb_ + (xb - bx0) as usize];
            let wx = &ex[(xa - qx + w) as usize..=(xb - qx + w) as usize];
            // Two sets of sums, even and odd pixels, so that the additions of
            // neighbouring pixels need not wait for each other.
            let mut row = [[0.0f64; 5]; 2];
            let mut add = |k: usize, c: &[f64; 8], m: f64| {
                for (r, v) in row[k].iter_mut().zip(&c[..5]) {
                    *r += m * v;
                }
            };
            if robust {
                // Down-weight pixels whose edge line misses q: Tukey's biweight of the
                // distance from q to the line, |g . (q - p)| / |g|, at ROBUST_PX.
                let dy = y as f64 - q[1];
                let m = |x: isize, c: &[f64; 8], e: f64| {
                    let dx = x as f64 - q[0];
                    let r2 = (c[5] * dx + c[6] * dy).powi(2) * c[7];
                    e * (1.0 - r2).max(0.0).powi(2)
                };
                let mut x = xa;
                for (c, e) in cells.chunks_exact(2).zip(wx.chunks_exact(2)) {
                    add(0, &c[0], m(x, &c[0], e[0]));
                    add(1, &c[1], m(x + 1, &c[1], e[1]));
                    x += 2;
                }
                if let (Some(c), Some(e)) = (
                    cells.chunks_exact(2).remainder().first(),
                    wx.chunks_exact(2).remainder().first(),
                ) {
                    add(0, c, m(x, c, *e));
                }
            } else {
                for (c, e) in cells.chunks_exact(2).zip(wx.chunks_exact(2)) {
                    add(0, &c[0], e[0]);
                    add(1, &c[1], e[1]);
                }
                if let (Some(c), Some(e)) = (
                    cells.chunks_exact(2).remainder().first(),
                    wx.chunks_exact(2).remainder().first(),
                ) {
                    add(0, c, *e);
                }
            }
            for (s, (a, b)) in sums.iter_mut().zip(row[0].iter().zip(&row[1])) {
                *s += wy * (a + b);
            }
        }
        let [a, b, cc, bb1, bb2] = sums;
        let det = a * cc - b * b;
        if det.is_nan() || det <= 1e-12 * (a * cc).max(1e-300) {
            break;
        }
        let nq = [(cc * bb1 - b * bb2) / det, (a * bb2 - b * bb1) / det];
        let moved = dist(nq, q);
        q = nq;
        // OpenCV's cornerSubPix stops at 0.001 px too.
        if moved < 1e-3 {
            break;
        }
    }
    let d = dist(q, start);
    Some(if d.is_nan() || d > half as f64 {
        start
    } else {
        q
    })
}

/// The box of `img` within `reach` of corner `c` with its squares levelled: the light
/// squares' level and the dark squares' level each fitted as a plane over the box (to the
/// pixels clearly light or dark, the edges' blur left out, outliers dropped), and each
/// pixel mapped to 255 (v - dark) / (light - dark). Returned with the box's top-left pixel;
/// None where the box has too little of either or no contrast.
fn equalised(img: &Gray, c: [f64; 2], reach: usize) -> Option<(Gray, [usize; 2])> {
    if !(c[0].is_finite() && c[1].is_finite()) {
        return None;
    }
    let at = |v: f64, n: usize| (v.round().max(0.0) as usize).min(n - 1);
    let (cx, cy) = (at(c[0], img.width), at(c[1], img.height));
    let (x0, y0) = (cx.saturating_sub(reach), cy.saturating_sub(reach));
    let (x1, y1) = (
        (cx + reach).min(img.width - 1),
        (cy + reach).min(img.height - 1),
    );
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    // Pixels as (dx, dy, v) about the corner.
    let px: Vec<[f64; 3]> = (y0..=y1)
        .flat_map(|y| {
            (x0..=x1).map(move |x| {
                [
                    x as f64 - c[0],
                    y as f64 - c[1],
                    img.data[y * img.width + x] as f64,
                ]
            })
        })
        .collect();
    let mut sorted: Vec<f64> = px.iter().map(|p| p[2]).filter(|v| v.is_finite()).collect();
    if sorted.len() < 64 {
        return None;
    }
    sorted.sort_by(f64::total_cmp);
    let (lo, hi) = (sorted[sorted.len() / 10], sorted[sorted.len() * 9 / 10]);
    let contrast = hi - lo;
    if contrast.is_nan() || contrast <= 1e-6 * hi.abs().max(1e-30) {
        return None;
    }
    let flat = |v: f64| [v, 0.0, 0.0];
    let eval = |p: &[f64; 3], a: &[f64; 3]| a[0] + a[1] * p[0] + a[2] * p[1];
    let (mut light, mut dark) = (flat(hi), flat(lo));
    for pass in 0..3 {
        let mut fits = [None, None];
        for (k, fit) in fits.iter_mut().enumerate() {
            let (l, d) = (&light, &dark);
            let pick = |p: &&[f64; 3]| {
                let (lv, dv) = (eval(p, l), eval(p, d));
                let t = (p[2] - dv) / (lv - dv);
                if k == 0 {
                    t > 0.75
                } else {
                    t < 0.25
                }
            };
            let own = if k == 0 { &light } else { &dark };
            // Outliers (glare, a mark, the board's rim) dropped from the second pass on.
            let sd = if pass == 0 {
                f64::INFINITY
            } else {
                let r: Vec<f64> = px
                    .iter()
                    .filter(pick)
                    .map(|p| p[2] - eval(p, own))
                    .collect();
                3.0 * (r.iter().map(|x| x * x).sum::<f64>() / r.len().max(1) as f64).sqrt()
            };
            *fit = plane(
                px.iter()
                    .filter(pick)
                    .filter(|p| (p[2] - eval(p, own)).abs() <= sd),
            );
        }
        match fits {
            [Some(l), Some(d)] => (light, dark) = (l, d),
            _ => return None,
        }
    }
    // Contrast at the box's corners: the planes must not cross within the box.
    let r = reach as f64 * std::f64::consts::SQRT_2;
    let span = [[-r, -r], [r, -r], [-r, r], [r, r]]
        .iter()
        .map(|[x, y]| eval(&[*x, *y, 0.0], &light) - eval(&[*x, *y, 0.0], &dark))
        .fold(f64::INFINITY, f64::min);
    if span.is_nan() || span <= 0.25 * contrast {
        return None;
    }
    let data = px
        .iter()
        .map(|p| {
            let (l, d) = (eval(p, &light), eval(p, &dark));
            (255.0 * (p[2] - d) / (l - d)) as f32
        })
        .collect();
    Some((Gray::new(bw, bh, data), [x0, y0]))
}

/// Least-squares plane v = a + b x + c y through points (x, y, v); None with fewer than
/// 12 points or a degenerate spread.
fn plane<'a>(pts: impl Iterator<Item = &'a [f64; 3]>) -> Option<[f64; 3]> {
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    let mut r = nalgebra::Vector3::<f64>::zeros();
    let mut n = 0usize;
    for p in pts {
        let u = nalgebra::Vector3::new(1.0, p[0], p[1]);
        m += u * u.transpose();
        r += u * p[2];
        n += 1;
    }
    if n < 12 {
        return None;
    }
    let s = m.try_inverse()? * r;
    s.iter().all(|v| v.is_finite()).then(|| [s[0], s[1], s[2]])
}

/// Mean of the image over the middle of the quad with corners a, b, c, d (in order).
fn quad_mean(img: &Gray, a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> f64 {
    let mut s = 0.0;
    let n = 5;
    for u in 0..n {
        for v in 0..n {
            let (fu, fv) = (
                0.25 + 0.5 * u as f64 / (n - 1) as f64,
                0.25 + 0.5 * v as f64 / (n - 1) as f64,
            );
            let lerp = |p: [f64; 2], q: [f64; 2], t: f64| {
                [p[0] + (q[0] - p[0]) * t, p[1] + (q[1] - p[1]) * t]
            };
            let top = lerp(a, b, fu);
            let bot = lerp(d, c, fu);
            let p = lerp(top, bot, fv);
            s += img.sample(p[0], p[1]);
        }
    }
    s / (n * n) as f64
}

/// Order the `a` x `b` label grid as the documented `nx` x `ny` grid.
fn orient(
    img: &Gray,
    pos: &[[f64; 2]],
    a: usize,
    b: usize,
    nx: usize,
    ny: usize,
) -> Result<Vec<usize>, DetectError> {
    let mut found = Vec::new();
    for transpose in [false, true] {
        let (da, db) = if transpose { (b, a) } else { (a, b) };
        if (da, db) != (nx, ny) {
            continue;
        }
        for (fi, fj) in [(false, false), (true, false), (false, true), (true, true)] {
            let index = |i: usize, j: usize| {
                let (i, j) = (
                    if fi { nx - 1 - i } else { i },
                    if fj { ny - 1 - j } else { j },
                );
                let (li, lj) = if transpose { (j, i) } else { (i, j) };
                lj * a + li
            };
            let get = |i: usize, j: usize| pos[index(i, j)];
            // Right-handed with z towards the camera: in the image (v down) the turn from
            // +x to +y is counter-clockwise as drawn, i.e. the cross product is negative.
            let o = get(0, 0);
            let ex = get(nx - 1, 0);
            let ey = get(0, ny - 1);
            let cross = (ex[0] - o[0]) * (ey[1] - o[1]) - (ex[1] - o[1]) * (ey[0] - o[0]);
            if cross >= 0.0 {
                continue;
            }
            let sq = |i: usize, j: usize| {
                quad_mean(
                    img,
                    get(i, j),
                    get(i + 1, j),
                    get(i + 1, j + 1),
                    get(i, j + 1),
                )
            };
            let dark = sq(0, 0) < sq(1, 0) && sq(0, 0) < sq(0, 1);
            let ordered: Vec<usize> = (0..ny)
                .flat_map(|j| (0..nx).map(move |i| (i, j)))
                .map(|(i, j)| index(i, j))
                .collect();
            found.push((dark, ordered));
        }
    }
    let dark: Vec<_> = found.into_iter().filter(|(d, _)| *d).collect();
    if dark.len() == 1 {
        Ok(dark.into_iter().next().unwrap().1)
    } else {
        Err(DetectError::NoOrigin)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grey test image: a smooth ramp with a pseudo-random texture.
    fn texture(w: usize, h: usize) -> Gray {
        let data = (0..w * h)
            .map(|i| ((i * 7919 + (i / w) * 104_729) % 251) as f32 + (i % w) as f32 * 0.37)
            .collect();
        Gray::new(w, h, data)
    }

    #[test]
    fn shrink_blur_is_shrink_then_blur() {
        let g = texture(97, 61);
        for f in [1, 2, 3] {
            assert_eq!(
                g.shrink_blur(f, 1.5).data,
                g.shrink(f).blur(1.5).data,
                "f {f}"
            );
        }
    }

    #[test]
    fn a_smoothed_patch_holds_the_blurred_image() {
        let g = texture(53, 41);
        let whole = g.blur(REFINE_SIGMA);
        let taps = gauss_taps(REFINE_SIGMA);
        let mut patch = Patch::new();
        for b in [
            [0, 0, 52, 40],
            [3, 5, 20, 17],
            [30, 20, 52, 40],
            [1, 0, 9, 39],
        ] {
            patch.smoothed(&g, &taps, b);
            let stride = patch.bw.div_ceil(LANES) * LANES;
            for y in b[1]..=b[3] {
                for x in b[0]..=b[2] {
                    assert_eq!(
                        patch.smooth[(y - b[1]) * stride + x - b[0]],
                        whole.data[y * g.width + x],
                        "box {b:?} at ({x}, {y})"
                    );
                }
            }
        }
    }
}
