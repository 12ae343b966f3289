//! Raw V4L2 buffers to [`Pixels`]: one decoder a pixel format, no device needed.
//!
//! A buffer is what the driver filled: rows of `bytes_per_line` bytes (the stride, which may
//! be longer than a row's samples), of which the first `bytesused` bytes are valid. A buffer
//! too short for its frame is a [`DeviceError::CorruptFrame`], never a partly filled image.
//!
//! - `GREY`: 8-bit luma, one sample a pixel.
//! - `Y16`: 16-bit little-endian luma.
//! - `Y10`, `Y12`: 10- or 12-bit luma in the low bits of little-endian 16-bit words,
//!   scaled to 16 bits (`value << 6`, `value << 4`) so that every mono format fills the same
//!   range; the unused high bits are ignored.
//! - `YUYV`: packed Y'CbCr 4:2:2 (`Y0 Cb Y1 Cr` for each pair of pixels), converted to
//!   R'G'B' with the matrix (BT.601, BT.709, BT.2020) and range (limited 16..235/240 or full
//!   0..255) the device reports in its format ([`YcbcrParams::from_v4l2`]). The chroma has
//!   half the horizontal resolution: each Cb/Cr pair is applied to both pixels it was
//!   sampled with, so a colour edge is spread over 2 pixels (luma edges stay sharp).
//!   The output is gamma-encoded R'G'B', like every other 8-bit format Glint records;
//!   the camera's response curve (`glint response`) linearises it.
//! - `RGB3`, `BGR3`: 8-bit R'G'B' / B'G'R' triples.
//! - `MJPG`: a JPEG a frame. Many UVC cameras omit the Huffman tables (the "MJPEG" of
//!   AVI files, where the tables are fixed); when no DHT segment comes before the scan,
//!   the standard tables of JPEG Annex K.3 are inserted before decoding.

use crate::rig::PixelFormat;
use glint_format::image::Pixels;

use crate::error::DeviceError;

/// The Y'CbCr to R'G'B' matrix, named by its standard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum YcbcrMatrix {
    Bt601,
    Bt709,
    Bt2020,
    Smpte240m,
}

impl YcbcrMatrix {
    /// The luma weights (Kr, Kb) of the matrix.
    pub fn kr_kb(self) -> (f32, f32) {
        match self {
            YcbcrMatrix::Bt601 => (0.299, 0.114),
            YcbcrMatrix::Bt709 => (0.2126, 0.0722),
            YcbcrMatrix::Bt2020 => (0.2627, 0.0593),
            YcbcrMatrix::Smpte240m => (0.212, 0.087),
        }
    }
}

/// The quantisation range of Y'CbCr samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum YcbcrRange {
    /// Y' in 16..235, Cb and Cr in 16..240 (the default for Y'CbCr).
    Limited,
    /// All three in 0..255.
    Full,
}

/// How a device encodes Y'CbCr: matrix and range.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct YcbcrParams {
    pub matrix: YcbcrMatrix,
    pub range: YcbcrRange,
}

impl Default for YcbcrParams {
    fn default() -> Self {
        YcbcrParams {
            matrix: YcbcrMatrix::Bt601,
            range: YcbcrRange::Limited,
        }
    }
}

// V4L2's numbers (videodev2.h): enum v4l2_colorspace, v4l2_ycbcr_encoding, v4l2_quantization.
const V4L2_COLORSPACE_SMPTE240M: u32 = 2;
const V4L2_COLORSPACE_REC709: u32 = 3;
const V4L2_COLORSPACE_JPEG: u32 = 7;
const V4L2_COLORSPACE_BT2020: u32 = 10;
const V4L2_YCBCR_ENC_DEFAULT: u32 = 0;
const V4L2_YCBCR_ENC_709: u32 = 2;
const V4L2_YCBCR_ENC_XV709: u32 = 4;
const V4L2_YCBCR_ENC_BT2020: u32 = 6;
const V4L2_YCBCR_ENC_BT2020_CONST_LUM: u32 = 7;
const V4L2_YCBCR_ENC_SMPTE240M: u32 = 8;
const V4L2_QUANTIZATION_FULL_RANGE: u32 = 1;
const V4L2_QUANTIZATION_LIM_RANGE: u32 = 2;

impl YcbcrParams {
    /// The matrix and range of a V4L2 format's `colorspace`, `ycbcr_enc` and `quantization`
    /// fields, with the kernel's rules for the defaults (`V4L2_MAP_YCBCR_ENC_DEFAULT`,
    /// `V4L2_MAP_QUANTIZATION_DEFAULT`): an unset encoding follows the colour space (Rec. 709
    /// -> BT.709, BT.2020 -> BT.2020, SMPTE 240M -> 240M, everything else, sRGB included, ->
    /// BT.601); an unset quantisation is limited range for Y'CbCr, except in the JPEG colour
    /// space, which is full range. BT.2020's constant-luminance variant is decoded as the
    /// non-constant one (cameras do not send it).
    pub fn from_v4l2(colorspace: u32, ycbcr_enc: u32, quantization: u32) -> YcbcrParams {
        let enc = if ycbcr_enc == V4L2_YCBCR_ENC_DEFAULT {
            match colorspace {
                V4L2_COLORSPACE_REC709 => V4L2_YCBCR_ENC_709,
                V4L2_COLORSPACE_BT2020 => V4L2_YCBCR_ENC_BT2020,
                V4L2_COLORSPACE_SMPTE240M => V4L2_YCBCR_ENC_SMPTE240M,
                _ => 1,
            }
        } else {
            ycbcr_enc
        };
        let matrix = match enc {
            V4L2_YCBCR_ENC_709 | V4L2_YCBCR_ENC_XV709 => YcbcrMatrix::Bt709,
            V4L2_YCBCR_ENC_BT2020 | V4L2_YCBCR_ENC_BT2020_CONST_LUM => YcbcrMatrix::Bt2020,
            V4L2_YCBCR_ENC_SMPTE240M => YcbcrMatrix::Smpte240m,
            _ => YcbcrMatrix::Bt601,
        };
        let range = match quantization {
            V4L2_QUANTIZATION_FULL_RANGE => YcbcrRange::Full,
            V4L2_QUANTIZATION_LIM_RANGE => YcbcrRange::Limited,
            _ if colorspace == V4L2_COLORSPACE_JPEG => YcbcrRange::Full,
            _ => YcbcrRange::Limited,
        };
        YcbcrParams { matrix, range }
    }
}

impl std::fmt::Display for YcbcrParams {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let m = match self.matrix {
            YcbcrMatrix::Bt601 => "BT.601",
            YcbcrMatrix::Bt709 => "BT.709",
            YcbcrMatrix::Bt2020 => "BT.2020",
            YcbcrMatrix::Smpte240m => "SMPTE 240M",
        };
        let r = match self.range {
            YcbcrRange::Limited => "limited",
            YcbcrRange::Full => "full",
        };
        write!(f, "{m} {r} range")
    }
}

/// The layout of a frame in a driver's buffer, as the negotiated format describes it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawLayout {
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    /// Bytes from the start of one row to the next (V4L2 `bytesperline`); for MJPG unused.
    pub bytes_per_line: u32,
    /// For YUYV.
    pub ycbcr: YcbcrParams,
}

impl RawLayout {
    /// A layout with rows packed tightly (the smallest `bytes_per_line`), BT.601 limited.
    pub fn packed(format: PixelFormat, width: u32, height: u32) -> RawLayout {
        RawLayout {
            format,
            width,
            height,
            bytes_per_line: width * bytes_per_pixel(format),
            ycbcr: YcbcrParams::default(),
        }
    }

    /// The bytes a row's samples take (without the stride's padding).
    pub fn row_bytes(&self) -> usize {
        self.width as usize * bytes_per_pixel(self.format) as usize
    }

    /// The fewest bytes a complete frame takes: every row but the last at full stride.
    pub fn min_bytes(&self) -> usize {
        if self.format == PixelFormat::MJPG || self.height == 0 {
            return 0;
        }
        (self.height as usize - 1) * self.bytes_per_line as usize + self.row_bytes()
    }
}

/// Bytes a pixel in the raw buffer (0 for MJPG, which is compressed).
pub fn bytes_per_pixel(format: PixelFormat) -> u32 {
    match format {
        PixelFormat::GREY => 1,
        PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12 | PixelFormat::YUYV => 2,
        PixelFormat::RGB3 | PixelFormat::BGR3 => 3,
        PixelFormat::MJPG => 0,
    }
}

/// Decode the valid bytes of a buffer (`data` = the first `bytesused` bytes) into pixels:
/// one sample a pixel for the luma formats, RGB triples for the others, rows top to bottom.
/// `sequence` names the frame in errors.
pub fn decode(layout: &RawLayout, data: &[u8], sequence: u64) -> Result<Pixels, DeviceError> {
    let corrupt = |reason: String| DeviceError::CorruptFrame { sequence, reason };
    let (w, h) = (layout.width as usize, layout.height as usize);
    if layout.format == PixelFormat::MJPG {
        return decode_mjpg(data, layout.width, layout.height).map_err(|e| corrupt(e.to_string()));
    }
    if (layout.bytes_per_line as usize) < layout.row_bytes() {
        return Err(corrupt(format!(
            "the driver's stride ({} bytes a row) is shorter than a row of {w} {} pixels ({} bytes)",
            layout.bytes_per_line,
            layout.format,
            layout.row_bytes()
        )));
    }
    if data.len() < layout.min_bytes() {
        return Err(corrupt(format!(
            "{} bytes in the buffer, a {w}x{h} {} frame needs {}",
            data.len(),
            layout.format,
            layout.min_bytes()
        )));
    }
    let stride = layout.bytes_per_line as usize;
    let row_bytes = layout.row_bytes();
    let rows = (0..h).map(|y| &data[y * stride..y * stride + row_bytes]);
    Ok(match layout.format {
        PixelFormat::GREY | PixelFormat::RGB3 => {
            let mut out = Vec::with_capacity(h * row_bytes);
            if stride == row_bytes {
                out.extend_from_slice(&data[..h * row_bytes]);
            } else {
                rows.for_each(|r| out.extend_from_slice(r));
            }
            Pixels::U8(out)
        }
        PixelFormat::Y16 | PixelFormat::Y10 | PixelFormat::Y12 => {
            let (mask, shift) = match layout.format {
                PixelFormat::Y10 => (0x03ff, 6),
                PixelFormat::Y12 => (0x0fff, 4),
                _ => (0xffff, 0),
            };
            let mut out = vec![0u16; w * h];
            for (src, dst) in rows.zip(out.chunks_exact_mut(w.max(1))) {
                for (b, o) in src.chunks_exact(2).zip(dst.iter_mut()) {
                    *o = (u16::from_le_bytes([b[0], b[1]]) & mask) << shift;
                }
            }
            Pixels::U16(out)
        }
        PixelFormat::BGR3 => {
            let mut out = vec![0u8; w * h * 3];
            for (src, dst) in rows.zip(out.chunks_exact_mut((w * 3).max(1))) {
                for (p, o) in src.chunks_exact(3).zip(dst.chunks_exact_mut(3)) {
                    o.copy_from_slice(&[p[2], p[1], p[0]]);
                }
            }
            Pixels::U8(out)
        }
        PixelFormat::YUYV => {
            let conv = YcbcrTables::new(layout.ycbcr);
            let mut out = vec![0u8; w * h * 3];
            for (src, dst) in rows.zip(out.chunks_exact_mut((w * 3).max(1))) {
                conv.row(src, dst);
            }
            Pixels::U8(out)
        }
        PixelFormat::MJPG => unreachable!("decoded above"),
    })
}

/// Fractional bits of the fixed-point Y'CbCr tables (sums stay below 2^30).
const FIX_BITS: u32 = 20;

/// Y'CbCr (8-bit) to R'G'B' (8-bit) in fixed point: for one matrix and range, each term of
/// the conversion (`R' = Y' + a Cr`, `G' = Y' + b Cb + c Cr`, `B' = Y' + d Cb`, scaled to
/// 0..255) tabulated for all 256 codes, in units of 2^-20 of an output step, the luma table
/// carrying the +0.5 of rounding. A pixel is then a few additions, a shift and a lookup, and the
/// result is [`ycbcr_to_rgb_formula`]'s, rounded to nearest, to within 1 in the last
/// place (the tables' rounding can move a value that lies within ~2^-20 of a half-step).
pub struct YcbcrTables {
    y: [i32; 256],
    cr_r: [i32; 256],
    cb_g: [i32; 256],
    cr_g: [i32; 256],
    cb_b: [i32; 256],
}

impl YcbcrTables {
    pub fn new(p: YcbcrParams) -> Self {
        let c = YcbcrCoefficients::new(p);
        let fix = |v: f64| (v * 255.0 * (1u32 << FIX_BITS) as f64).round() as i32;
        let half = 1i32 << (FIX_BITS - 1);
        let mut t = YcbcrTables {
            y: [0; 256],
            cr_r: [0; 256],
            cb_g: [0; 256],
            cr_g: [0; 256],
            cb_b: [0; 256],
        };
        for v in 0..256usize {
            let (y, ch) = c.normalised(v as u8, v as u8);
            t.y[v] = fix(y) + half + (CLIP_ZERO << FIX_BITS);
            t.cr_r[v] = fix(c.cr_r * ch);
            t.cb_g[v] = fix(c.cb_g * ch);
            t.cr_g[v] = fix(c.cr_g * ch);
            t.cb_b[v] = fix(c.cb_b * ch);
        }
        t
    }

    /// One pixel.
    #[inline(always)]
    pub fn rgb(&self, y: u8, cb: u8, cr: u8) -> [u8; 3] {
        let r = self.cr_r[cr as usize];
        let g = self.cb_g[cb as usize] + self.cr_g[cr as usize];
        let b = self.cb_b[cb as usize];
        let y = self.y[y as usize];
        [clamp8(y + r), clamp8(y + g), clamp8(y + b)]
    }

    /// One row: `src` is `Y0 Cb Y1 Cr` quadruples for `dst.len() / 3` pixels; a row of odd
    /// width ends in a lone `Y0 Cb`, that pixel without its pair (its Cr taken as neutral).
    #[inline]
    pub fn row(&self, src: &[u8], dst: &mut [u8]) {
        let quads = src.chunks_exact(4);
        let tail = quads.remainder();
        let mut pairs = dst.chunks_exact_mut(6);
        for (q, o) in quads.zip(&mut pairs) {
            let (y0, cb, y1, cr) = (q[0], q[1], q[2], q[3]);
            let r = self.cr_r[cr as usize];
            let g = self.cb_g[cb as usize] + self.cr_g[cr as usize];
            let b = self.cb_b[cb as usize];
            let y0 = self.y[y0 as usize];
            let y1 = self.y[y1 as usize];
            o.copy_from_slice(&[
                clamp8(y0 + r),
                clamp8(y0 + g),
                clamp8(y0 + b),
                clamp8(y1 + r),
                clamp8(y1 + g),
                clamp8(y1 + b),
            ]);
        }
        let last = pairs.into_remainder();
        if let ([y0, cb, ..], [r, g, b, ..]) = (tail, last) {
            [*r, *g, *b] = self.rgb(*y0, *cb, 128);
        }
    }
}

/// Where 0 is in [`CLIP`]: a sum of the tables lies within about -300..560 output steps,
/// so with this added it is within 0..1023.
const CLIP_ZERO: i32 = 384;

/// 0..255 clipping as a table lookup, `CLIP[v + CLIP_ZERO]`: a comparison would branch,
/// and those branches mispredict wherever an image has clipped and unclipped pixels side
/// by side (a fourfold slowdown).
static CLIP: [u8; 1024] = {
    let mut t = [0u8; 1024];
    let mut i = 0;
    while i < 1024 {
        let v = i as i32 - CLIP_ZERO;
        t[i] = if v < 0 {
            0
        } else if v > 255 {
            255
        } else {
            v as u8
        };
        i += 1;
    }
    t
};

/// A fixed-point sum of the tables (with the rounding offset and `CLIP_ZERO` added by the
/// luma table) to 0..255.
#[inline(always)]
fn clamp8(v: i32) -> u8 {
    CLIP[(v >> FIX_BITS) as usize & 1023]
}

/// The conversion's coefficients for one matrix and range: Y' to 0..1 and Cb, Cr to
/// -0.5..0.5 from the 8-bit codes, then R'G'B' (0..1) = Y' + the chroma terms.
struct YcbcrCoefficients {
    y_off: f64,
    y_gain: f64,
    c_gain: f64,
    cr_r: f64,
    cb_g: f64,
    cr_g: f64,
    cb_b: f64,
}

impl YcbcrCoefficients {
    fn new(p: YcbcrParams) -> Self {
        let (kr, kb) = p.matrix.kr_kb();
        let (kr, kb) = (kr as f64, kb as f64);
        let kg = 1.0 - kr - kb;
        let (y_off, y_gain, c_gain) = match p.range {
            YcbcrRange::Limited => (16.0, 1.0 / 219.0, 1.0 / 224.0),
            YcbcrRange::Full => (0.0, 1.0 / 255.0, 1.0 / 255.0),
        };
        let cr_r = 2.0 * (1.0 - kr);
        let cb_b = 2.0 * (1.0 - kb);
        YcbcrCoefficients {
            y_off,
            y_gain,
            c_gain,
            cr_r,
            cb_g: -kb * cb_b / kg,
            cr_g: -kr * cr_r / kg,
            cb_b,
        }
    }

    /// (Y' in 0..1, a chroma code in -0.5..0.5).
    fn normalised(&self, y: u8, c: u8) -> (f64, f64) {
        (
            (y as f64 - self.y_off) * self.y_gain,
            (c as f64 - 128.0) * self.c_gain,
        )
    }
}

/// The conversion as a formula, one pixel at a time in floating point: R'G'B' scaled to
/// 0..255, before rounding and clipping. [`YcbcrTables`] gives these rounded to nearest and
/// clipped to 0..255, except that a value within ~2^-20 of a half-step may round either
/// way. For tests and comparisons; [`decode`] uses the tables.
pub fn ycbcr_to_rgb_formula(p: YcbcrParams, y: u8, cb: u8, cr: u8) -> [f64; 3] {
    let c = YcbcrCoefficients::new(p);
    let (y, cb) = c.normalised(y, cb);
    let (_, cr) = c.normalised(0, cr);
    [
        (y + c.cr_r * cr) * 255.0,
        (y + c.cb_g * cb + c.cr_g * cr) * 255.0,
        (y + c.cb_b * cb) * 255.0,
    ]
}

/// The DHT segment of JPEG Annex K.3 (tables K.3 to K.6: luminance and chrominance, DC
/// and AC), which Motion-JPEG frames use without sending it.
pub fn standard_dht_segment() -> Vec<u8> {
    const DC_LUMA_BITS: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
    const DC_CHROMA_BITS: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
    const DC_VALUES: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
    const AC_LUMA_BITS: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d];
    const AC_LUMA_VALUES: [u8; 162] = [
        0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61,
        0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52,
        0xd1, 0xf0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25,
        0x26, 0x27, 0x28, 0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45,
        0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64,
        0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83,
        0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99,
        0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6,
        0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3,
        0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8,
        0xe9, 0xea, 0xf1, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    const AC_CHROMA_BITS: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
    const AC_CHROMA_VALUES: [u8; 162] = [
        0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61,
        0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33,
        0x52, 0xf0, 0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18,
        0x19, 0x1a, 0x26, 0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44,
        0x45, 0x46, 0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63,
        0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a,
        0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97,
        0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4,
        0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca,
        0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7,
        0xe8, 0xe9, 0xea, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
    ];
    // Table class (0 DC, 1 AC) << 4 | table id (0 luminance, 1 chrominance).
    let tables: [(u8, &[u8; 16], &[u8]); 4] = [
        (0x00, &DC_LUMA_BITS, &DC_VALUES),
        (0x10, &AC_LUMA_BITS, &AC_LUMA_VALUES),
        (0x01, &DC_CHROMA_BITS, &DC_VALUES),
        (0x11, &AC_CHROMA_BITS, &AC_CHROMA_VALUES),
    ];
    let len: usize = 2 + tables.iter().map(|t| 17 + t.2.len()).sum::<usize>();
    let mut seg = vec![0xff, 0xc4, (len >> 8) as u8, len as u8];
    for (class_id, bits, values) in tables {
        seg.push(class_id);
        seg.extend_from_slice(bits);
        seg.extend_from_slice(values);
    }
    seg
}

/// Why a Motion-JPEG frame cannot be decoded (the reason of a
/// [`DeviceError::CorruptFrame`]).
#[derive(Debug, thiserror::Error)]
pub enum MjpegError {
    #[error("not a JPEG ({len} bytes, no start-of-image marker)")]
    NotJpeg { len: usize },
    #[error("JPEG truncated or garbled before its scan (at byte {at} of {len})")]
    BeforeScan { at: usize, len: usize },
    #[error("JPEG ends before its scan")]
    EndsBeforeScan,
    #[error("JPEG truncated in a segment header")]
    SegmentHeader,
    #[error("JPEG does not decode: {0}")]
    Decode(image::ImageError),
    #[error("JPEG is {}x{}, the format negotiated {}x{}", .got.0, .got.1, .negotiated.0, .negotiated.1)]
    Size {
        got: (u32, u32),
        negotiated: (u32, u32),
    },
}

/// The JPEG with the standard Huffman tables inserted before its scan when it has none
/// of its own before the scan (borrowed unchanged when it has).
pub fn with_huffman_tables(jpeg: &[u8]) -> Result<std::borrow::Cow<'_, [u8]>, MjpegError> {
    use std::borrow::Cow;
    if jpeg.len() < 4 || jpeg[0] != 0xff || jpeg[1] != 0xd8 {
        return Err(MjpegError::NotJpeg { len: jpeg.len() });
    }
    let mut i = 2;
    loop {
        // Markers may be padded with any number of 0xff bytes.
        while i < jpeg.len() && jpeg[i] == 0xff && jpeg.get(i + 1) == Some(&0xff) {
            i += 1;
        }
        if i + 1 >= jpeg.len() || jpeg[i] != 0xff {
            return Err(MjpegError::BeforeScan {
                at: i,
                len: jpeg.len(),
            });
        }
        match jpeg[i + 1] {
            0xc4 => return Ok(Cow::Borrowed(jpeg)),
            0xda => {
                let dht = standard_dht_segment();
                let mut out = Vec::with_capacity(jpeg.len() + dht.len());
                out.extend_from_slice(&jpeg[..i]);
                out.extend_from_slice(&dht);
                out.extend_from_slice(&jpeg[i..]);
                return Ok(Cow::Owned(out));
            }
            // Markers without a length.
            0x01 | 0xd0..=0xd7 => i += 2,
            0xd9 => return Err(MjpegError::EndsBeforeScan),
            _ => {
                let Some(len) = jpeg.get(i + 2..i + 4) else {
                    return Err(MjpegError::SegmentHeader);
                };
                i += 2 + u16::from_be_bytes([len[0], len[1]]) as usize;
            }
        }
    }
}

/// A Motion-JPEG frame to RGB (8-bit), checked against the negotiated size.
fn decode_mjpg(data: &[u8], width: u32, height: u32) -> Result<Pixels, MjpegError> {
    let jpeg = with_huffman_tables(data)?;
    let img = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)
        .map_err(MjpegError::Decode)?;
    if (img.width(), img.height()) != (width, height) {
        return Err(MjpegError::Size {
            got: (img.width(), img.height()),
            negotiated: (width, height),
        });
    }
    Ok(Pixels::U8(img.into_rgb8().into_raw()))
}
