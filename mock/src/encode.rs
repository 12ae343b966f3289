//! Pixel encoders: the simulated sensor's output as a camera sends it over V4L2.
//!
//! The sensor gives RGB (interleaved) or mono samples of 8 or 16 bits; a V4L2 camera sends
//! one of these formats (the simulated lab's own code: Glint decodes them independently):
//!
//! - `GREY`: 8-bit luma (a 16-bit sample is rounded to 8 bits: `(v + 128) / 257`).
//! - `Y16`: 16-bit luma, little-endian (an 8-bit sample is widened: `v * 257`).
//! - `Y10`, `Y12`: 10 or 12 significant bits in 16-bit little-endian words, low-aligned:
//!   the 16-bit value `>> 6` or `>> 4`.
//! - `YUYV`: packed 4:2:2 Y'CbCr, ITU-R BT.601 limited range, from 8-bit R'G'B' (the
//!   sensor's values are already gamma-encoded):
//!   `Y' = 16 + (65.481 R' + 128.553 G' + 24.966 B')`,
//!   `Cb = 128 + (-37.797 R' - 74.203 G' + 112.0 B')`,
//!   `Cr = 128 + (112.0 R' - 93.786 G' - 18.214 B')` with R', G', B' in [0, 1], rounded;
//!   each pair of pixels shares one Cb and one Cr: those of the pair's mean R'G'B' (the
//!   average of the two pixels' chroma). An odd last column pairs with itself.
//! - `RGB3`, `BGR3`: 8-bit R'G'B' or B'G'R'.
//! - `MJPG`: baseline JPEG, 4:2:2 as UVC cameras send it, quality 90; by default the DHT
//!   (Huffman table) segments are removed, as many UVC cameras do ("Huffman-less" frames:
//!   the decoder must use the standard tables of JPEG Annex K.3, which the encoder used).
//!
//! A mono sensor feeds the colour formats with R' = G' = B'; an RGB sensor feeds the luma
//! formats with its BT.601 luma (`0.299 R' + 0.587 G' + 0.114 B'`).

use crate::camera::SimPixels;

/// A V4L2 pixel format the simulated camera can send.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Encoding {
    Grey,
    Y16,
    Y10,
    Y12,
    Yuyv,
    Rgb3,
    Bgr3,
    Mjpg,
}

impl Encoding {
    pub const ALL: [Encoding; 8] = [
        Encoding::Grey,
        Encoding::Y16,
        Encoding::Y10,
        Encoding::Y12,
        Encoding::Yuyv,
        Encoding::Rgb3,
        Encoding::Bgr3,
        Encoding::Mjpg,
    ];

    /// The name V4L2 tools print (the four-character code without trailing spaces).
    pub fn name(self) -> &'static str {
        match self {
            Encoding::Grey => "GREY",
            Encoding::Y16 => "Y16",
            Encoding::Y10 => "Y10",
            Encoding::Y12 => "Y12",
            Encoding::Yuyv => "YUYV",
            Encoding::Rgb3 => "RGB3",
            Encoding::Bgr3 => "BGR3",
            Encoding::Mjpg => "MJPG",
        }
    }

    pub fn from_name(name: &str) -> Option<Encoding> {
        Encoding::ALL
            .into_iter()
            .find(|e| e.name().eq_ignore_ascii_case(name.trim()))
    }

    /// Samples a pixel the sensor behind this format has: 1 (luma formats) or 3.
    pub fn channels(self) -> u8 {
        match self {
            Encoding::Grey | Encoding::Y16 | Encoding::Y10 | Encoding::Y12 => 1,
            _ => 3,
        }
    }
}

/// How a frame is encoded.
#[derive(Debug, Clone, Copy)]
pub struct EncodeOptions {
    /// Keep the DHT segments in MJPG frames.
    pub keep_huffman: bool,
    /// JPEG quality, 1..=100.
    pub jpeg_quality: u8,
}

impl Default for EncodeOptions {
    fn default() -> Self {
        EncodeOptions {
            keep_huffman: false,
            jpeg_quality: 90,
        }
    }
}

/// One sample as 16 bits.
fn wide(p: &SimPixels, i: usize) -> u16 {
    match p {
        SimPixels::U8(v) => v[i] as u16 * 257,
        SimPixels::U16(v) => v[i],
    }
}

fn narrow(v: u16) -> u8 {
    ((v as u32 + 128) / 257) as u8
}

/// The frame as 8-bit R'G'B' (borrowed when the sensor gives exactly that).
fn rgb8(p: &SimPixels, channels: usize, n: usize) -> std::borrow::Cow<'_, [u8]> {
    if let (SimPixels::U8(v), 3) = (p, channels) {
        if v.len() >= n * 3 {
            // narrow(wide(v)) == v for an 8-bit sample.
            return std::borrow::Cow::Borrowed(&v[..n * 3]);
        }
    }
    let mut out = Vec::with_capacity(n * 3);
    for i in 0..n {
        if channels == 3 {
            for c in 0..3 {
                out.push(narrow(wide(p, i * 3 + c)));
            }
        } else {
            let v = narrow(wide(p, i));
            out.extend([v, v, v]);
        }
    }
    std::borrow::Cow::Owned(out)
}

/// YUYV of 8-bit R'G'B' rows of `w` pixels: [`ycbcr601`] by tables of its products, so the
/// result is the formula's to the bit (the same products, added in the same order) at a
/// fraction of its cost.
fn yuyv(rgb: &[u8], w: usize, n: usize) -> Vec<u8> {
    if w == 0 || n == 0 {
        return Vec::new();
    }
    struct Tables {
        y: [[f64; 256]; 3],
        // Chroma of a pair's mean: indexed by the sum of the pair's two samples.
        cb: [[f64; 511]; 3],
        cr: [[f64; 511]; 3],
    }
    static TABLES: std::sync::OnceLock<Box<Tables>> = std::sync::OnceLock::new();
    let t = TABLES.get_or_init(|| {
        let mut t = Box::new(Tables {
            y: [[0.0; 256]; 3],
            cb: [[0.0; 511]; 3],
            cr: [[0.0; 511]; 3],
        });
        let ky = [65.481, 128.553, 24.966];
        let kb = [37.797, 74.203, 112.0];
        let kr = [112.0, 93.786, 18.214];
        for c in 0..3 {
            for v in 0..256 {
                t.y[c][v] = ky[c] * (v as f64 / 255.0);
            }
            for s in 0..511 {
                let m = (s as f64 / 2.0) / 255.0;
                t.cb[c][s] = kb[c] * m;
                t.cr[c][s] = kr[c] * m;
            }
        }
        t
    });
    let luma = |p: &[u8]| {
        clamp8(16.0 + t.y[0][p[0] as usize] + t.y[1][p[1] as usize] + t.y[2][p[2] as usize])
    };
    let mut out = vec![0u8; w.div_ceil(2) * 4 * (n / w.max(1))];
    for (row, dst) in rgb
        .chunks_exact(w * 3)
        .zip(out.chunks_exact_mut(w.div_ceil(2) * 4))
    {
        for (x, q) in (0..w).step_by(2).zip(dst.chunks_exact_mut(4)) {
            let a = &row[x * 3..x * 3 + 3];
            let b = if x + 1 < w {
                &row[x * 3 + 3..x * 3 + 6]
            } else {
                a
            };
            let s = [0, 1, 2].map(|c| a[c] as usize + b[c] as usize);
            let cb = 128.0 - t.cb[0][s[0]] - t.cb[1][s[1]] + t.cb[2][s[2]];
            let cr = 128.0 + t.cr[0][s[0]] - t.cr[1][s[1]] - t.cr[2][s[2]];
            q.copy_from_slice(&[luma(a), clamp8(cb), luma(b), clamp8(cr)]);
        }
    }
    // An odd width still sends whole pairs: trim to two bytes a pixel.
    out.truncate(n * 2);
    out
}

/// The frame as 16-bit luma.
fn luma16(p: &SimPixels, channels: usize, n: usize) -> Vec<u16> {
    (0..n)
        .map(|i| {
            if channels == 1 {
                wide(p, i)
            } else {
                let [r, g, b] = [0, 1, 2].map(|c| wide(p, i * 3 + c) as f64);
                (0.299 * r + 0.587 * g + 0.114 * b).round() as u16
            }
        })
        .collect()
}

/// BT.601 limited-range Y'CbCr of 8-bit R'G'B'.
pub fn ycbcr601(r: f64, g: f64, b: f64) -> [f64; 3] {
    let (r, g, b) = (r / 255.0, g / 255.0, b / 255.0);
    [
        16.0 + 65.481 * r + 128.553 * g + 24.966 * b,
        128.0 - 37.797 * r - 74.203 * g + 112.0 * b,
        128.0 + 112.0 * r - 93.786 * g - 18.214 * b,
    ]
}

/// `v.round().clamp(0.0, 255.0) as u8`, without the call to libm's `round` (the
/// fractional part `v - trunc(v)` is exact, so this rounds half away from zero as it does).
fn clamp8(v: f64) -> u8 {
    // Out of [-1, 256] the answer is 0 or 255 either way; NaN gives 0, as `as u8` does.
    let v = v.clamp(-1.0, 256.0);
    let i = v as i32;
    let frac = v - i as f64;
    let r = i + (frac >= 0.5) as i32 - (frac <= -0.5) as i32;
    r.clamp(0, 255) as u8
}

/// Remove every DHT segment (marker FF C4) before the scan of a baseline JPEG.
pub fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(jpeg.len());
    let mut i = 0;
    if jpeg.len() < 2 {
        return jpeg.to_vec();
    }
    out.extend_from_slice(&jpeg[..2]); // SOI
    i += 2;
    while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
        let marker = jpeg[i + 1];
        if marker == 0xDA {
            break; // start of scan: the rest is entropy-coded data and EOI
        }
        let len = u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]) as usize;
        let end = (i + 2 + len).min(jpeg.len());
        if marker != 0xC4 {
            out.extend_from_slice(&jpeg[i..end]);
        }
        i = end;
    }
    out.extend_from_slice(&jpeg[i..]);
    out
}

/// Encode a `width` x `height` frame of `channels` samples a pixel as `enc`.
pub fn encode(
    pixels: &SimPixels,
    width: u32,
    height: u32,
    channels: u8,
    enc: Encoding,
    opts: EncodeOptions,
) -> Vec<u8> {
    let (w, h, ch) = (width as usize, height as usize, channels as usize);
    let n = w * h;
    match enc {
        Encoding::Grey => luma16(pixels, ch, n).into_iter().map(narrow).collect(),
        Encoding::Y16 | Encoding::Y10 | Encoding::Y12 => {
            let shift = match enc {
                Encoding::Y10 => 6,
                Encoding::Y12 => 4,
                _ => 0,
            };
            luma16(pixels, ch, n)
                .into_iter()
                .flat_map(|v| (v >> shift).to_le_bytes())
                .collect()
        }
        Encoding::Rgb3 => rgb8(pixels, ch, n).into_owned(),
        Encoding::Bgr3 => {
            let mut v = rgb8(pixels, ch, n).into_owned();
            v.chunks_exact_mut(3).for_each(|p| p.swap(0, 2));
            v
        }
        Encoding::Yuyv => yuyv(&rgb8(pixels, ch, n), w, n),
        Encoding::Mjpg => {
            let rgb = rgb8(pixels, ch, n);
            let mut jpeg = Vec::new();
            let mut encoder = jpeg_encoder::Encoder::new(&mut jpeg, opts.jpeg_quality);
            encoder.set_sampling_factor(jpeg_encoder::SamplingFactor::F_2_1);
            let ok = encoder
                .encode(
                    &rgb,
                    width.min(u16::MAX as u32) as u16,
                    height.min(u16::MAX as u32) as u16,
                    jpeg_encoder::ColorType::Rgb,
                )
                .is_ok();
            if !ok {
                return Vec::new();
            }
            if opts.keep_huffman {
                jpeg
            } else {
                strip_dht(&jpeg)
            }
        }
    }
}

/// Bytes a frame of `enc` takes (MJPG: the most it may take, two bytes a pixel).
pub fn frame_bytes(enc: Encoding, width: u32, height: u32) -> usize {
    let n = width as usize * height as usize;
    match enc {
        Encoding::Grey => n,
        Encoding::Rgb3 | Encoding::Bgr3 => n * 3,
        _ => n * 2,
    }
}

/// Resample a frame to a smaller size by picking the nearest source pixel (the simulated
/// sensor's readout for its smaller modes).
pub fn resample(
    pixels: &SimPixels,
    width: u32,
    height: u32,
    channels: u8,
    to_w: u32,
    to_h: u32,
) -> SimPixels {
    if (to_w, to_h) == (width, height) {
        return pixels.clone();
    }
    let ch = channels as usize;
    let index = |x: u32, y: u32| {
        let sx = ((x as u64 * 2 + 1) * width as u64 / (to_w as u64 * 2)) as usize;
        let sy = ((y as u64 * 2 + 1) * height as u64 / (to_h as u64 * 2)) as usize;
        (sy * width as usize + sx) * ch
    };
    fn pick<T: Copy>(
        src: &[T],
        to_w: u32,
        to_h: u32,
        ch: usize,
        index: &dyn Fn(u32, u32) -> usize,
    ) -> Vec<T> {
        let mut out = Vec::with_capacity(to_w as usize * to_h as usize * ch);
        for y in 0..to_h {
            for x in 0..to_w {
                let i = index(x, y);
                out.extend_from_slice(&src[i..i + ch]);
            }
        }
        out
    }
    match pixels {
        SimPixels::U8(v) => SimPixels::U8(pick(v, to_w, to_h, ch, &index)),
        SimPixels::U16(v) => SimPixels::U16(pick(v, to_w, to_h, ch, &index)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(p: SimPixels, w: u32, h: u32, ch: u8, e: Encoding) -> Vec<u8> {
        encode(&p, w, h, ch, e, EncodeOptions::default())
    }

    #[test]
    fn luma_formats_of_a_16_bit_mono_sensor() {
        let p = SimPixels::U16(vec![0, 0x1234, 0xFFFF, 0x8000]);
        assert_eq!(enc(p.clone(), 2, 2, 1, Encoding::Grey), [0, 18, 255, 128]);
        assert_eq!(
            enc(p.clone(), 2, 2, 1, Encoding::Y16),
            [0, 0, 0x34, 0x12, 0xFF, 0xFF, 0x00, 0x80]
        );
        // Y10: 0x1234 >> 6 = 0x48, 0xFFFF >> 6 = 0x3FF, 0x8000 >> 6 = 0x200.
        assert_eq!(
            enc(p.clone(), 2, 2, 1, Encoding::Y10),
            [0, 0, 0x48, 0, 0xFF, 0x03, 0x00, 0x02]
        );
        // Y12: 0x1234 >> 4 = 0x123, 0xFFFF >> 4 = 0xFFF.
        assert_eq!(
            enc(p, 2, 2, 1, Encoding::Y12),
            [0, 0, 0x23, 0x01, 0xFF, 0x0F, 0x00, 0x08]
        );
    }

    #[test]
    fn an_8_bit_sample_widens_by_257() {
        let p = SimPixels::U8(vec![1, 255]);
        assert_eq!(enc(p.clone(), 2, 1, 1, Encoding::Y16), [1, 1, 0xFF, 0xFF]);
        assert_eq!(enc(p, 2, 1, 1, Encoding::Grey), [1, 255]);
    }

    #[test]
    fn rgb_and_bgr() {
        let p = SimPixels::U8(vec![10, 20, 30, 40, 50, 60]);
        assert_eq!(
            enc(p.clone(), 2, 1, 3, Encoding::Rgb3),
            [10, 20, 30, 40, 50, 60]
        );
        assert_eq!(enc(p, 2, 1, 3, Encoding::Bgr3), [30, 20, 10, 60, 50, 40]);
        let mono = SimPixels::U16(vec![0xFFFF]);
        assert_eq!(enc(mono, 1, 1, 1, Encoding::Rgb3), [255, 255, 255]);
    }

    #[test]
    fn yuyv_is_bt601_limited_range_with_averaged_chroma() {
        // White and black: Y' 235 and 16; the pair's chroma is that of mid grey (128).
        let p = SimPixels::U8(vec![255, 255, 255, 0, 0, 0]);
        assert_eq!(enc(p, 2, 1, 3, Encoding::Yuyv), [235, 128, 16, 128]);
        // Pure red twice: Y' 81, Cb 90, Cr 240 (BT.601 tables).
        let p = SimPixels::U8(vec![255, 0, 0, 255, 0, 0]);
        assert_eq!(enc(p, 2, 1, 3, Encoding::Yuyv), [81, 90, 81, 240]);
        // Red and blue: Cb, Cr of their mean (127.5, 0, 127.5).
        let p = SimPixels::U8(vec![255, 0, 0, 0, 0, 255]);
        let [_, cb, cr] = ycbcr601(127.5, 0.0, 127.5);
        assert_eq!(
            enc(p, 2, 1, 3, Encoding::Yuyv),
            [81, clamp8(cb), 41, clamp8(cr)]
        );
    }

    #[test]
    fn yuyv_tables_match_the_formula_to_the_bit() {
        let (w, h) = (7usize, 5usize);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 97 % 256) as u8).collect();
        let mut want = Vec::new();
        for row in rgb.chunks_exact(w * 3) {
            for x in (0..w).step_by(2) {
                let a = &row[x * 3..x * 3 + 3];
                let b = if x + 1 < w {
                    &row[x * 3 + 3..x * 3 + 6]
                } else {
                    a
                };
                let ya = ycbcr601(a[0] as f64, a[1] as f64, a[2] as f64)[0];
                let yb = ycbcr601(b[0] as f64, b[1] as f64, b[2] as f64)[0];
                let mean = |c: usize| (a[c] as f64 + b[c] as f64) / 2.0;
                let [_, cb, cr] = ycbcr601(mean(0), mean(1), mean(2));
                want.extend([clamp8(ya), clamp8(cb), clamp8(yb), clamp8(cr)]);
            }
        }
        want.truncate(w * h * 2);
        let got = enc(SimPixels::U8(rgb), w as u32, h as u32, 3, Encoding::Yuyv);
        assert_eq!(got, want);
    }

    #[test]
    fn clamp8_rounds_as_round_does() {
        for v in [
            -1.5,
            -0.5,
            -0.49,
            0.0,
            0.49999999999999994,
            0.5,
            1.5,
            2.5,
            127.5,
            254.5,
            255.4,
            255.5,
            300.0,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            assert_eq!(clamp8(v), v.round().clamp(0.0, 255.0) as u8, "{v}");
        }
        for k in 0..100_000 {
            let v = k as f64 * 0.0031 - 10.0;
            assert_eq!(clamp8(v), v.round().clamp(0.0, 255.0) as u8, "{v}");
        }
    }

    #[test]
    fn rgb_feeds_luma_with_bt601_weights() {
        let p = SimPixels::U8(vec![255, 0, 0]);
        assert_eq!(enc(p, 1, 1, 3, Encoding::Grey), [76]); // 0.299 * 255
    }

    #[test]
    fn mjpg_is_huffman_less_unless_asked() {
        let p = SimPixels::U8(vec![128; 16 * 8 * 3]);
        let has_dht = |j: &[u8]| j.windows(2).any(|w| w == [0xFF, 0xC4]);
        let stripped = enc(p.clone(), 16, 8, 3, Encoding::Mjpg);
        assert_eq!(&stripped[..2], [0xFF, 0xD8]);
        assert_eq!(&stripped[stripped.len() - 2..], [0xFF, 0xD9]);
        assert!(!has_dht(&stripped));
        let full = encode(
            &p,
            16,
            8,
            3,
            Encoding::Mjpg,
            EncodeOptions {
                keep_huffman: true,
                ..Default::default()
            },
        );
        assert!(has_dht(&full));
        assert!(stripped.len() < full.len());
        // Only the DHT segments differ.
        assert_eq!(strip_dht(&full), stripped);
    }

    #[test]
    fn resample_picks_nearest_pixels() {
        let p = SimPixels::U8((0..16).collect());
        assert_eq!(
            resample(&p, 4, 4, 1, 2, 2),
            SimPixels::U8(vec![5, 7, 13, 15])
        );
    }
}
