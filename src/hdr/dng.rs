//! DNG (camera raw) photos for `glint import`: the sensor's colour filter array (CFA)
//! mosaic, read as half-size linear RGB.
//!
//! A DNG is a TIFF whose IFD0 carries the DNGVersion tag (50706). IFD0 is usually a small
//! 8-bit RGB thumbnail and the raw mosaic sits in a SubIFD (tag 330): a plain TIFF reader
//! (the `image` crate) would read the thumbnail, a silent wrong result, so every photo
//! that [`is_dng`] goes through this module instead ([`crate::hdr::probe_image`],
//! [`crate::hdr::decode_image`]).
//!
//! # What is read
//! The raw image is the first IFD (IFD0, then its SubIFDs and the IFDs after it) with
//! NewSubfileType (254) 0 and PhotometricInterpretation (262) 32803 (CFA), with:
//! - Compression (259) 1, uncompressed;
//! - BitsPerSample 8 to 16, SampleFormat unsigned integer, SamplesPerPixel 1; 8 and 16
//!   bits in the file's byte order, 9 to 15 (packed 10, 12, 14-bit) packed most
//!   significant bit first, each row starting on a byte, as the DNG specification requires
//!   whatever the file's byte order;
//! - strips (273, 278, 279) or tiles (322 to 325);
//! - a 2x2 rectangular CFA (CFARepeatPatternDim 33421 = [2, 2], CFALayout 50711 = 1)
//!   holding one red, two green and one blue (CFAPattern 33422, through CFAPlaneColor
//!   50710 when given): RGGB, BGGR, GRBG, GBRG;
//! - WhiteLevel (50717), by default 2^bits - 1;
//! - ActiveArea (50829): the pixels outside it (masked border pixels) are left out, and
//!   the CFA pattern starts at its top-left corner, as the specification says.
//!
//! DefaultCropOrigin and DefaultCropSize are ignored: they trim a few edge pixels a raw
//! converter keeps for demosaicing, and every photo of a session is read alike, so the
//! calibration simply sees a few more pixels. Orientation is ignored too: the sensor's
//! own rows are what the rig's camera sees, as for a captured session.
//!
//! # What comes out
//! Half-size RGB, 16 bits, with no interpolation: each 2x2 CFA block becomes one pixel
//! (its red, the mean of its two greens, its blue). HDR merging and BRDF fitting need
//! linear radiance, and demosaicing invents two thirds of the values by interpolating
//! across edges (the tile's outline, the grid's corners); at half size every output value
//! is a measurement (or the mean of two), still linear in the light. The camera is then
//! calibrated in half-size pixels, consistently for the whole session (grid, tile and
//! dark photos are all read alike). Values are scaled so that WhiteLevel maps to 65535
//! (rounded, clamped): a clipped sensor value reads as saturated at the top of Glint's
//! 16-bit range. The black level is *not* subtracted: Glint's dark photos and linear
//! response model measure it, as for any other camera.
//!
//! # What is refused (one line, naming what to do)
//! - compressed raw data: lossless JPEG (7), lossy JPEG (34892), JPEG XL (52546), deflate
//!   (8, 32946) or any other scheme. No maintained pure-Rust lossless-JPEG decoder with an
//!   MIT/Apache-compatible licence reads DNG's tiles: `rawler`, `rawloader`, `quickraw`
//!   and `ljpeg` are LGPL-2.1; `jpeg-decoder` (MIT/Apache, in maintenance mode) decodes
//!   lossless JPEG but refuses the 2-component frames Adobe's converter writes for CFA
//!   tiles; `flashraw-codecs` (MIT/Apache) is a new internal crate of another project.
//!   Convert such a DNG to an uncompressed one (`dnglab convert --compression none`) or to
//!   a linear 16-bit TIFF (`dcraw -4 -T`);
//! - LinearRaw (34892) images (already demosaiced, or monochrome sensors), CFA patterns
//!   other than 2x2 (Fujifilm X-Trans is 6x6), non-rectangular CFA layouts, floating-point
//!   samples, a LinearizationTable (the values would not be linear), more than one sample
//!   a pixel, fewer than 8 or more than 16 bits.
//!
//! # Hostile files
//! Whatever the bytes, nothing panics and the work is bounded: all reads go through
//! `get` and checked arithmetic, at most [`MAX_IFDS`] IFDs are visited (each once: no
//! cycles) with at most [`MAX_ENTRIES`] entries each, a tag's values are read only once
//! they are known to lie inside the file, the raw image's sides and pixels are checked
//! against [`MAX_SIDE`] and [`MAX_PIXELS`], and every strip or tile against the file's
//! length, before any pixel buffer is allocated. Memory is the output plus two rows.
//!
//! The parser is hand-written (a few hundred lines) rather than built on the `tiff` crate:
//! that crate is only an indirect dependency (through `image`), so using it would add a
//! direct one, and it would give little: tag reading is the easy part, while its image
//! decoding is for the usual photometric types, not a CFA mosaic (32803) whose 10/12/14-bit
//! samples are packed by the DNG rule. A small parser also keeps every bound in view.

use std::collections::{HashSet, VecDeque};

use crate::devices::Pixels;
use crate::hdr::limits::{ImageInfo, MAX_PIXELS, MAX_SIDE};

/// At most this many IFDs are visited in one file.
pub const MAX_IFDS: usize = 64;
/// At most this many entries in one IFD.
pub const MAX_ENTRIES: usize = 4096;

const NEW_SUBFILE_TYPE: u16 = 254;
const IMAGE_WIDTH: u16 = 256;
const IMAGE_LENGTH: u16 = 257;
const BITS_PER_SAMPLE: u16 = 258;
const COMPRESSION: u16 = 259;
const PHOTOMETRIC: u16 = 262;
const STRIP_OFFSETS: u16 = 273;
const SAMPLES_PER_PIXEL: u16 = 277;
const ROWS_PER_STRIP: u16 = 278;
const STRIP_BYTE_COUNTS: u16 = 279;
const TILE_WIDTH: u16 = 322;
const TILE_LENGTH: u16 = 323;
const TILE_OFFSETS: u16 = 324;
const TILE_BYTE_COUNTS: u16 = 325;
const SUB_IFDS: u16 = 330;
const SAMPLE_FORMAT: u16 = 339;
const CFA_REPEAT_PATTERN_DIM: u16 = 33421;
const CFA_PATTERN: u16 = 33422;
const DNG_VERSION: u16 = 50706;
const CFA_PLANE_COLOR: u16 = 50710;
const CFA_LAYOUT: u16 = 50711;
const LINEARIZATION_TABLE: u16 = 50712;
const BLACK_LEVEL: u16 = 50714;
const WHITE_LEVEL: u16 = 50717;
const ACTIVE_AREA: u16 = 50829;

const PHOTOMETRIC_CFA: u64 = 32803;
const PHOTOMETRIC_LINEAR_RAW: u64 = 34892;

/// What to do with a DNG Glint does not read.
const CONVERT: &str = "convert it to an uncompressed DNG (dnglab convert --compression none IN OUT) or to a linear 16-bit TIFF (dcraw -4 -T)";
const TO_TIFF: &str = "convert it to a linear 16-bit TIFF (dcraw -4 -T)";

/// Is this a DNG: a classic TIFF (`II*\0` or `MM\0*`) whose IFD0 has the DNGVersion tag?
pub fn is_dng(bytes: &[u8]) -> bool {
    let Some((t, ifd0)) = Tiff::open(bytes) else {
        return false;
    };
    t.ifd(ifd0)
        .map(|ifd| ifd.get(DNG_VERSION).is_some())
        .unwrap_or(false)
}

/// The decoded image's size and depth (half the raw image's active area, 16 bits), from
/// the headers only, after every check [`decode`] makes short of reading the pixels.
pub fn probe(bytes: &[u8]) -> Result<ImageInfo, DngError> {
    let raw = Raw::parse(bytes)?;
    Ok(raw.info())
}

/// Decode the raw mosaic to half-size RGB, interleaved, 16 bits (see the module's doc).
pub fn decode(bytes: &[u8]) -> Result<(ImageInfo, Pixels), DngError> {
    let raw = Raw::parse(bytes)?;
    let px = raw.pixels(bytes)?;
    Ok((raw.info(), Pixels::U16(px)))
}

/// A classic TIFF's bytes and byte order.
struct Tiff<'a> {
    b: &'a [u8],
    le: bool,
}

/// One IFD entry: its tag, type, count and where its 12 bytes start.
#[derive(Debug, Clone, Copy)]
struct Entry {
    tag: u16,
    typ: u16,
    count: u32,
    at: usize,
}

struct Ifd {
    entries: Vec<Entry>,
    next: u32,
}

impl Ifd {
    fn get(&self, tag: u16) -> Option<&Entry> {
        self.entries.iter().find(|e| e.tag == tag)
    }
}

fn type_size(typ: u16) -> Option<usize> {
    match typ {
        1 | 2 | 6 | 7 => Some(1),
        3 | 8 => Some(2),
        4 | 9 | 11 | 13 => Some(4),
        5 | 10 | 12 => Some(8),
        _ => None,
    }
}

/// Why a DNG cannot be read: the reason, for the caller to put after the file's name.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DngError {
    /// The file contradicts itself or the TIFF format.
    #[error("the DNG is corrupt ({what})")]
    Corrupt { what: String },
    /// A kind of raw image Glint does not read, which a linear TIFF would carry.
    #[error("{what}, which Glint does not read; {}", TO_TIFF)]
    NotRead { what: String },
    #[error("the DNG holds no raw colour filter (CFA) image in IFD0 or its SubIFDs; the file is corrupt or not a camera raw")]
    NoMosaic,
    #[error(
        "the DNG is compressed with {scheme}, which Glint does not read; {}",
        CONVERT
    )]
    Compressed { scheme: String },
    #[error(
        "the DNG's raw image has {samples} samples a pixel where a colour filter mosaic has 1; {}",
        TO_TIFF
    )]
    Samples { samples: u64 },
    #[error(
        "the DNG's raw samples are {bits}-bit; Glint reads 8- to 16-bit raw samples: {}",
        TO_TIFF
    )]
    Bits { bits: u64 },
    #[error("the raw image is {width}x{height} ({:.1} megapixels); Glint decodes at most {} pixels a side and {} megapixels", .width.saturating_mul(*.height) as f64 * 1e-6, MAX_SIDE, MAX_PIXELS / 1_000_000)]
    TooLarge { width: u64, height: u64 },
    #[error("the DNG's colour filter pattern repeats every {repeat} pixels, not 2x2 (Bayer), which Glint does not read (Fujifilm X-Trans is 6x6); {}", TO_TIFF)]
    NotBayer { repeat: String },
    #[error("the DNG's BlackLevel (tag 50714) is {black}, not below its WhiteLevel (tag 50717) {white}: no raw value between them is left to measure light, so the file's levels are wrong; re-export the photo from the camera's raw file, or {}", TO_TIFF)]
    BlackLevel { black: f64, white: u64 },
    #[error("the raw image's active area is {width}x{height}: it has no 2x2 pixel block")]
    NoBlock { width: usize, height: usize },
}

fn corrupt(what: impl std::fmt::Display) -> DngError {
    DngError::Corrupt {
        what: what.to_string(),
    }
}

impl<'a> Tiff<'a> {
    fn open(b: &'a [u8]) -> Option<(Tiff<'a>, u32)> {
        let le = match b.get(0..4)? {
            [b'I', b'I', 42, 0] => true,
            [b'M', b'M', 0, 42] => false,
            _ => return None,
        };
        let t = Tiff { b, le };
        let ifd0 = t.u32(4)?;
        Some((t, ifd0))
    }

    fn u16(&self, at: usize) -> Option<u16> {
        let s = self.b.get(at..at.checked_add(2)?)?;
        let a = [*s.first()?, *s.get(1)?];
        Some(if self.le {
            u16::from_le_bytes(a)
        } else {
            u16::from_be_bytes(a)
        })
    }

    fn u32(&self, at: usize) -> Option<u32> {
        let s = self.b.get(at..at.checked_add(4)?)?;
        let a = [*s.first()?, *s.get(1)?, *s.get(2)?, *s.get(3)?];
        Some(if self.le {
            u32::from_le_bytes(a)
        } else {
            u32::from_be_bytes(a)
        })
    }

    /// The IFD at `off`: its entries must lie inside the file, at most [`MAX_ENTRIES`].
    fn ifd(&self, off: u32) -> Result<Ifd, DngError> {
        let off = off as usize;
        let n = self
            .u16(off)
            .ok_or_else(|| corrupt(format!("an IFD at byte {off} lies outside the file")))?
            as usize;
        if n > MAX_ENTRIES {
            return Err(corrupt(format!(
                "an IFD has {n} entries, more than {MAX_ENTRIES}"
            )));
        }
        let mut entries = Vec::with_capacity(n);
        for i in 0..n {
            let at = i
                .checked_mul(12)
                .and_then(|x| x.checked_add(off))
                .and_then(|x| x.checked_add(2))
                .ok_or_else(|| corrupt("an IFD lies outside the file"))?;
            let (Some(tag), Some(typ), Some(count)) = (
                self.u16(at),
                self.u16(at.saturating_add(2)),
                self.u32(at.saturating_add(4)),
            ) else {
                return Err(corrupt(format!(
                    "an IFD at byte {off} runs past the end of the file"
                )));
            };
            entries.push(Entry {
                tag,
                typ,
                count,
                at,
            });
        }
        let next = off
            .checked_add(2)
            .and_then(|x| x.checked_add(n.checked_mul(12)?))
            .and_then(|x| self.u32(x))
            .ok_or_else(|| {
                corrupt(format!(
                    "an IFD at byte {off} runs past the end of the file"
                ))
            })?;
        Ok(Ifd { entries, next })
    }

    /// The bytes of an entry's values, known to lie inside the file.
    fn data(&self, e: &Entry) -> Result<&'a [u8], DngError> {
        let size = type_size(e.typ)
            .ok_or_else(|| corrupt(format!("tag {} has an unknown type {}", e.tag, e.typ)))?;
        let outside = || corrupt(format!("the values of tag {} lie outside the file", e.tag));
        let total = (e.count as usize).checked_mul(size).ok_or_else(outside)?;
        let start = if total <= 4 {
            e.at.checked_add(8).ok_or_else(outside)?
        } else {
            self.u32(e.at.saturating_add(8)).ok_or_else(outside)? as usize
        };
        let end = start.checked_add(total).ok_or_else(outside)?;
        self.b.get(start..end).ok_or_else(outside)
    }

    /// An entry's first `max` values (at most) as whole numbers (BYTE, UNDEFINED, SHORT,
    /// LONG, IFD): a tag claiming millions of values costs no more than the caller needs
    /// (each value would take 8 bytes here for 1 in the file).
    fn uints(&self, e: &Entry, max: usize) -> Result<Vec<u64>, DngError> {
        let d = self.data(e)?;
        let t = Tiff { b: d, le: self.le };
        let v: Vec<u64> = match e.typ {
            1 | 7 => d.iter().take(max).map(|&x| x as u64).collect(),
            3 => (0..(d.len() / 2).min(max))
                .filter_map(|i| t.u16(i * 2).map(u64::from))
                .collect(),
            4 | 13 => (0..(d.len() / 4).min(max))
                .filter_map(|i| t.u32(i * 4).map(u64::from))
                .collect(),
            other => {
                return Err(corrupt(format!(
                    "tag {} has type {other} where whole numbers are expected",
                    e.tag
                )))
            }
        };
        Ok(v)
    }

    /// An entry's first `max` values (at most) as numbers: the whole-number types of
    /// [`Tiff::uints`], RATIONAL and SRATIONAL (a zero denominator is refused).
    fn numbers(&self, e: &Entry, max: usize) -> Result<Vec<f64>, DngError> {
        if !matches!(e.typ, 5 | 10) {
            return Ok(self.uints(e, max)?.into_iter().map(|v| v as f64).collect());
        }
        let d = self.data(e)?;
        let t = Tiff { b: d, le: self.le };
        let mut out = Vec::new();
        for i in 0..(d.len() / 8).min(max) {
            let (Some(n), Some(den)) = (t.u32(i * 8), t.u32(i * 8 + 4)) else {
                break;
            };
            let (n, den) = if e.typ == 10 {
                (n as i32 as f64, den as i32 as f64)
            } else {
                (n as f64, den as f64)
            };
            if den == 0.0 {
                return Err(corrupt(format!("tag {} has a zero denominator", e.tag)));
            }
            out.push(n / den);
        }
        Ok(out)
    }

    /// A tag's first value, if the tag is there.
    fn first(&self, ifd: &Ifd, tag: u16) -> Result<Option<u64>, DngError> {
        match ifd.get(tag) {
            None => Ok(None),
            Some(e) => {
                let v = self.uints(e, 1)?;
                v.first()
                    .copied()
                    .map(Some)
                    .ok_or_else(|| corrupt(format!("tag {tag} has no value")))
            }
        }
    }

    fn required(&self, ifd: &Ifd, tag: u16, name: &str) -> Result<u64, DngError> {
        self.first(ifd, tag)?
            .ok_or_else(|| corrupt(format!("the raw image has no {name} (tag {tag})")))
    }

    /// IFD0, its SubIFDs (and theirs) and the IFDs chained after it, breadth first: at
    /// most [`MAX_IFDS`], each visited once.
    fn ifds(&self, ifd0: u32) -> Result<Vec<Ifd>, DngError> {
        let mut out = Vec::new();
        let mut seen = HashSet::new();
        let mut queue = VecDeque::from([ifd0 as u64]);
        while let Some(off) = queue.pop_front() {
            if out.len() >= MAX_IFDS {
                break;
            }
            if off == 0 || !seen.insert(off) {
                continue;
            }
            // A broken IFD other than IFD0 (a preview, say) is skipped: the raw image may
            // be elsewhere, and if not, that is said.
            let ifd = match u32::try_from(off)
                .map_err(corrupt)
                .and_then(|o| self.ifd(o))
            {
                Ok(ifd) => ifd,
                Err(e) if out.is_empty() => return Err(e),
                Err(_) => continue,
            };
            if let Some(e) = ifd.get(SUB_IFDS) {
                queue.extend(self.uints(e, MAX_IFDS)?);
            }
            if ifd.next != 0 {
                queue.push_back(ifd.next as u64);
            }
            out.push(ifd);
        }
        Ok(out)
    }
}

/// Where the raw samples are.
#[derive(Debug)]
enum Layout {
    /// Each strip `rows` rows of `row_bytes` bytes.
    Strips {
        rows: usize,
        row_bytes: usize,
        offsets: Vec<usize>,
    },
    /// Tiles of `width` x `length` samples, `across` a row of tiles, each row of a tile
    /// `row_bytes` bytes.
    Tiles {
        width: usize,
        length: usize,
        across: usize,
        row_bytes: usize,
        offsets: Vec<usize>,
    },
}

/// A raw CFA image, checked against the file: every strip or tile lies inside it.
#[derive(Debug)]
struct Raw {
    le: bool,
    bits: u32,
    /// Top, left, bottom, right of the active area.
    active: [usize; 4],
    /// Colour (0 R, 1 G, 2 B) at (row, column) parity (0, 0), (0, 1), (1, 0), (1, 1) from
    /// the active area's top-left corner.
    cfa: [u8; 4],
    white: u64,
    layout: Layout,
}

fn compression_name(c: u64) -> String {
    match c {
        7 => "lossless JPEG".into(),
        34892 => "lossy JPEG".into(),
        52546 => "JPEG XL".into(),
        8 | 32946 => "deflate".into(),
        other => format!("compression scheme {other}"),
    }
}

fn ceil_div(a: usize, b: usize) -> Option<usize> {
    (b != 0).then(|| a.div_ceil(b))
}

/// The main (not a preview) IFD that holds the colour filter mosaic.
fn raw_ifd<'i>(t: &Tiff, ifds: &'i [Ifd]) -> Result<&'i Ifd, DngError> {
    let main = |ifd: &&Ifd| t.first(ifd, NEW_SUBFILE_TYPE).ok().flatten().unwrap_or(0) == 0;
    let photometric = |ifd: &Ifd| t.first(ifd, PHOTOMETRIC).ok().flatten();
    if let Some(ifd) = ifds
        .iter()
        .filter(main)
        .find(|i| photometric(i) == Some(PHOTOMETRIC_CFA))
    {
        return Ok(ifd);
    }
    if ifds
        .iter()
        .filter(main)
        .any(|i| photometric(i) == Some(PHOTOMETRIC_LINEAR_RAW))
    {
        return Err(DngError::NotRead {
            what: "the DNG holds a LinearRaw image (already demosaiced, or a monochrome sensor), not a colour filter mosaic".into(),
        });
    }
    Err(DngError::NoMosaic)
}

/// The raw samples' bits, after checking they are uncompressed, unsigned integers, one a
/// pixel, on a rectangular filter and linear.
fn sample_bits(t: &Tiff, ifd: &Ifd) -> Result<u32, DngError> {
    let compression = t.first(ifd, COMPRESSION)?.unwrap_or(1);
    if compression != 1 {
        return Err(DngError::Compressed {
            scheme: compression_name(compression),
        });
    }
    match t.first(ifd, SAMPLE_FORMAT)?.unwrap_or(1) {
        1 => {}
        3 => {
            return Err(DngError::NotRead {
                what: "the DNG's raw samples are floating point".into(),
            })
        }
        other => {
            return Err(DngError::NotRead {
                what: format!("the DNG's raw samples have SampleFormat {other}"),
            })
        }
    }
    let samples = t.first(ifd, SAMPLES_PER_PIXEL)?.unwrap_or(1);
    if samples != 1 {
        return Err(DngError::Samples { samples });
    }
    let bits = t.first(ifd, BITS_PER_SAMPLE)?.unwrap_or(1);
    if !(8..=16).contains(&bits) {
        return Err(DngError::Bits { bits });
    }
    if t.first(ifd, CFA_LAYOUT)?.unwrap_or(1) != 1 {
        return Err(DngError::NotRead {
            what: "the DNG's colour filter layout is not rectangular".into(),
        });
    }
    if ifd.get(LINEARIZATION_TABLE).is_some() {
        return Err(DngError::NotRead {
            what: "the DNG has a LinearizationTable (its raw values are not linear)".into(),
        });
    }
    Ok(bits as u32)
}

/// The raw image's width and height, within the decoder's limits.
fn raw_size(t: &Tiff, ifd: &Ifd) -> Result<(usize, usize), DngError> {
    let width = t.required(ifd, IMAGE_WIDTH, "ImageWidth")?;
    let height = t.required(ifd, IMAGE_LENGTH, "ImageLength")?;
    if width > MAX_SIDE as u64
        || height > MAX_SIDE as u64
        || width.saturating_mul(height) > MAX_PIXELS
    {
        return Err(DngError::TooLarge { width, height });
    }
    Ok((width as usize, height as usize))
}

/// The CFA: 2x2, one red, two green, one blue; the colour at each (row, column) parity.
fn cfa_of(t: &Tiff, ifd: &Ifd) -> Result<[u8; 4], DngError> {
    let dim = match ifd.get(CFA_REPEAT_PATTERN_DIM) {
        Some(e) => t.uints(e, 16)?,
        None => {
            return Err(corrupt(
                "the raw image has no CFARepeatPatternDim (tag 33421)",
            ))
        }
    };
    if dim.as_slice() != [2, 2] {
        let shown: Vec<String> = dim.iter().take(4).map(u64::to_string).collect();
        return Err(DngError::NotBayer {
            repeat: shown.join("x"),
        });
    }
    let pattern = match ifd.get(CFA_PATTERN) {
        Some(e) => t.uints(e, 16)?,
        None => return Err(corrupt("the raw image has no CFAPattern (tag 33422)")),
    };
    let planes = match ifd.get(CFA_PLANE_COLOR) {
        Some(e) => t.uints(e, 16)?,
        None => vec![0, 1, 2],
    };
    let mut cfa = [0u8; 4];
    if pattern.len() != 4 {
        return Err(corrupt(format!(
            "CFAPattern has {} values for a 2x2 pattern",
            pattern.len()
        )));
    }
    for (c, p) in cfa.iter_mut().zip(&pattern) {
        let colour = usize::try_from(*p)
            .ok()
            .and_then(|i| planes.get(i))
            .copied()
            .unwrap_or(u64::MAX);
        *c = u8::try_from(colour).unwrap_or(u8::MAX);
    }
    let count = |k: u8| cfa.iter().filter(|&&c| c == k).count();
    if (count(0), count(1), count(2)) != (1, 2, 1) {
        return Err(DngError::NotRead {
            what: format!(
                "the DNG's 2x2 colour filter pattern {:?} is not one red, two green and one blue (RGGB, BGGR, GRBG or GBRG)",
                pattern
            ),
        });
    }
    Ok(cfa)
}

/// The white level, with the black level below it.
fn white_level(t: &Tiff, ifd: &Ifd, bits: u32) -> Result<u64, DngError> {
    let white = t.first(ifd, WHITE_LEVEL)?.unwrap_or((1u64 << bits) - 1);
    if white == 0 {
        return Err(corrupt("WhiteLevel is 0"));
    }
    // The black level is not subtracted (dark photos measure it), but one at or above
    // the white level leaves no raw value that measures light: the tags are wrong, and
    // every photo would read as saturated (or black), which later stages would blame on
    // the exposure times.
    if let Some(e) = ifd.get(BLACK_LEVEL) {
        let levels = t.numbers(e, 64)?;
        if let Some(black) = levels
            .iter()
            .copied()
            .find(|b| b.is_nan() || *b >= white as f64)
        {
            return Err(DngError::BlackLevel { black, white });
        }
    }
    Ok(white)
}

/// Top, left, bottom, right of the active area, which holds at least one 2x2 block.
fn active_area(t: &Tiff, ifd: &Ifd, width: usize, height: usize) -> Result<[usize; 4], DngError> {
    let active = match ifd.get(ACTIVE_AREA) {
        None => [0, 0, height, width],
        Some(e) => {
            let v = t.uints(e, 16)?;
            let [top, left, bottom, right] = v.as_slice() else {
                return Err(corrupt("ActiveArea does not have 4 values"));
            };
            if !(top < bottom && left < right && *bottom <= height as u64 && *right <= width as u64)
            {
                return Err(corrupt(format!(
                    "ActiveArea {top},{left},{bottom},{right} is not inside the {width}x{height} raw image"
                )));
            }
            // Below MAX_SIDE: they fit.
            [
                *top as usize,
                *left as usize,
                *bottom as usize,
                *right as usize,
            ]
        }
    };
    let (w2, h2) = ((active[3] - active[1]) / 2, (active[2] - active[0]) / 2);
    if w2 == 0 || h2 == 0 {
        return Err(DngError::NoBlock {
            width: active[3] - active[1],
            height: active[2] - active[0],
        });
    }
    Ok(active)
}

/// What the strips or tiles are checked against: the raw image's size and bits, and the
/// file's length.
struct Geometry {
    width: usize,
    height: usize,
    bits: u32,
    len: usize,
}

impl Geometry {
    /// The bytes of a row of `samples` samples.
    fn row_bytes(&self, samples: usize) -> Result<usize, DngError> {
        samples
            .checked_mul(self.bits as usize)
            .and_then(|b| ceil_div(b, 8))
            .ok_or_else(|| corrupt("the raw image's rows are too long"))
    }
}

fn too_short(what: &str, i: usize) -> DngError {
    corrupt(format!(
        "{what} {i} lies outside the file or holds fewer bytes than its pixels need"
    ))
}

/// A tiled raw image's tiles, each inside the file.
fn tiles(t: &Tiff, ifd: &Ifd, g: &Geometry) -> Result<Layout, DngError> {
    let tw = t.required(ifd, TILE_WIDTH, "TileWidth")? as usize;
    let tl = t.required(ifd, TILE_LENGTH, "TileLength")? as usize;
    // TIFF tiles are multiples of 16 a side; smaller ones would only serve to make
    // the list of tiles (and its memory) huge.
    if tw < 16 || tl < 16 {
        return Err(corrupt(format!(
            "the tiles are {tw}x{tl}; TIFF tiles are at least 16x16"
        )));
    }
    let across = ceil_div(g.width, tw).unwrap_or(0);
    let down = ceil_div(g.height, tl).unwrap_or(0);
    let n = across
        .checked_mul(down)
        .ok_or_else(|| corrupt("too many tiles"))?;
    let offsets = match ifd.get(TILE_OFFSETS) {
        Some(e) => t.uints(e, n)?,
        None => return Err(corrupt("the raw image has no TileOffsets (tag 324)")),
    };
    let counts = match ifd.get(TILE_BYTE_COUNTS) {
        Some(e) => Some(t.uints(e, n)?),
        None => None,
    };
    if offsets.len() < n || counts.as_ref().is_some_and(|c| c.len() < n) {
        return Err(corrupt(format!(
            "{across}x{down} tiles but {} tile offsets",
            offsets.len()
        )));
    }
    let row_bytes = g.row_bytes(tw)?;
    let need = row_bytes
        .checked_mul(tl)
        .ok_or_else(|| corrupt("the tiles are too large"))?;
    let mut offs = Vec::with_capacity(n);
    for (i, &o) in offsets.iter().take(n).enumerate() {
        let o = usize::try_from(o).map_err(|_| too_short("tile", i))?;
        let count_ok = counts
            .as_ref()
            .and_then(|c| c.get(i))
            .is_none_or(|&c| c >= need as u64);
        if !count_ok || o.checked_add(need).is_none_or(|end| end > g.len) {
            return Err(too_short("tile", i));
        }
        offs.push(o);
    }
    Ok(Layout::Tiles {
        width: tw,
        length: tl,
        across,
        row_bytes,
        offsets: offs,
    })
}

/// A raw image's strips, each inside the file.
fn strips(t: &Tiff, ifd: &Ifd, g: &Geometry) -> Result<Layout, DngError> {
    let height = g.height;
    let rows = t
        .first(ifd, ROWS_PER_STRIP)?
        .unwrap_or(u32::MAX as u64)
        .min(height as u64) as usize;
    if rows == 0 {
        return Err(corrupt("RowsPerStrip is 0"));
    }
    let n = ceil_div(height, rows).unwrap_or(0);
    let offsets = match ifd.get(STRIP_OFFSETS) {
        Some(e) => t.uints(e, n)?,
        None => return Err(corrupt("the raw image has no StripOffsets (tag 273)")),
    };
    let counts = match ifd.get(STRIP_BYTE_COUNTS) {
        Some(e) => Some(t.uints(e, n)?),
        None => None,
    };
    if offsets.len() < n || counts.as_ref().is_some_and(|c| c.len() < n) {
        return Err(corrupt(format!(
            "{n} strips but {} strip offsets",
            offsets.len()
        )));
    }
    let row_bytes = g.row_bytes(g.width)?;
    let mut offs = Vec::with_capacity(n);
    for (i, &o) in offsets.iter().take(n).enumerate() {
        let o = usize::try_from(o).map_err(|_| too_short("strip", i))?;
        // The last strip may hold fewer rows.
        let in_strip = rows.min(height - (i * rows).min(height));
        let need = row_bytes
            .checked_mul(in_strip)
            .ok_or_else(|| too_short("strip", i))?;
        let count_ok = counts
            .as_ref()
            .and_then(|c| c.get(i))
            .is_none_or(|&c| c >= need as u64);
        if !count_ok || o.checked_add(need).is_none_or(|end| end > g.len) {
            return Err(too_short("strip", i));
        }
        offs.push(o);
    }
    Ok(Layout::Strips {
        rows,
        row_bytes,
        offsets: offs,
    })
}

impl Raw {
    /// The raw image of a DNG, checked: the CFA image found, its samples, size, colour
    /// filter, levels and active area read, and every strip or tile inside the file.
    fn parse(bytes: &[u8]) -> Result<Raw, DngError> {
        let (t, ifd0) = Tiff::open(bytes).ok_or_else(|| corrupt("no TIFF header"))?;
        let ifds = t.ifds(ifd0)?;
        let ifd = raw_ifd(&t, &ifds)?;
        let bits = sample_bits(&t, ifd)?;
        let (width, height) = raw_size(&t, ifd)?;
        let cfa = cfa_of(&t, ifd)?;
        let white = white_level(&t, ifd, bits)?;
        let active = active_area(&t, ifd, width, height)?;
        let geometry = Geometry {
            width,
            height,
            bits,
            len: bytes.len(),
        };
        let layout = if ifd.get(TILE_OFFSETS).is_some() || ifd.get(TILE_WIDTH).is_some() {
            tiles(&t, ifd, &geometry)?
        } else {
            strips(&t, ifd, &geometry)?
        };
        Ok(Raw {
            le: t.le,
            bits,
            active,
            cfa,
            white,
            layout,
        })
    }

    fn half(&self) -> (usize, usize) {
        (
            (self.active[3] - self.active[1]) / 2,
            (self.active[2] - self.active[0]) / 2,
        )
    }

    fn info(&self) -> ImageInfo {
        let (w, h) = self.half();
        ImageInfo {
            width: w as u32,
            height: h as u32,
            bit_depth: 16,
        }
    }

    /// Sample `col` of a row of samples starting at byte `base`.
    fn sample(&self, b: &[u8], base: usize, col: usize) -> Option<u16> {
        match self.bits {
            8 => b.get(base.checked_add(col)?).map(|&v| v as u16),
            16 => {
                let at = base.checked_add(col.checked_mul(2)?)?;
                let s = b.get(at..at.checked_add(2)?)?;
                let a = [*s.first()?, *s.get(1)?];
                Some(if self.le {
                    u16::from_le_bytes(a)
                } else {
                    u16::from_be_bytes(a)
                })
            }
            bits => {
                // Packed, most significant bit first (DNG, whatever the byte order).
                let bits = bits as usize;
                let bit = col.checked_mul(bits)?;
                let first = base.checked_add(bit / 8)?;
                let shift = bit % 8;
                let nbytes = (shift + bits).div_ceil(8);
                let mut acc: u32 = 0;
                for k in 0..nbytes {
                    acc = (acc << 8) | *b.get(first.checked_add(k)?)? as u32;
                }
                let v = (acc >> (nbytes * 8 - shift - bits)) & ((1u32 << bits) - 1);
                Some(v as u16)
            }
        }
    }

    /// Samples `x0 .. x0 + out.len()` of raw row `y`.
    fn row(&self, b: &[u8], y: usize, x0: usize, out: &mut [u16]) -> Result<(), DngError> {
        let bad = || corrupt(format!("row {y} of the raw image cannot be read"));
        match &self.layout {
            Layout::Strips {
                rows,
                row_bytes,
                offsets,
            } => {
                let base = offsets
                    .get(y / rows)
                    .and_then(|o| o.checked_add((y % rows).checked_mul(*row_bytes)?))
                    .ok_or_else(bad)?;
                for (k, v) in out.iter_mut().enumerate() {
                    *v = self.sample(b, base, x0 + k).ok_or_else(bad)?;
                }
            }
            Layout::Tiles {
                width,
                length,
                across,
                row_bytes,
                offsets,
            } => {
                let ty = y / length;
                let in_tile = (y % length).checked_mul(*row_bytes).ok_or_else(bad)?;
                let mut k = 0;
                while k < out.len() {
                    let x = x0 + k;
                    let (tx, col) = (x / width, x % width);
                    let run = (width - col).min(out.len() - k);
                    let base = ty
                        .checked_mul(*across)
                        .and_then(|i| i.checked_add(tx))
                        .and_then(|i| offsets.get(i))
                        .and_then(|o| o.checked_add(in_tile))
                        .ok_or_else(bad)?;
                    for (j, v) in out.iter_mut().skip(k).take(run).enumerate() {
                        *v = self.sample(b, base, col + j).ok_or_else(bad)?;
                    }
                    k += run;
                }
            }
        }
        Ok(())
    }

    /// `sum` of `n` raw values scaled so that WhiteLevel is 65535, rounded, clamped.
    fn scale(&self, sum: u64, n: u64) -> u16 {
        let den = 2 * n * self.white;
        ((2 * sum * 65535 + n * self.white) / den).min(65535) as u16
    }

    /// Half-size RGB: each 2x2 block its red, the mean of its greens, its blue.
    fn pixels(&self, b: &[u8]) -> Result<Vec<u16>, DngError> {
        let (w2, h2) = self.half();
        let [top, left, _, _] = self.active;
        // Within MAX_PIXELS (checked in parse): no overflow.
        let mut out = Vec::with_capacity(w2 * h2 * 3);
        let mut r0 = vec![0u16; 2 * w2];
        let mut r1 = vec![0u16; 2 * w2];
        for j in 0..h2 {
            self.row(b, top + 2 * j, left, &mut r0)?;
            self.row(b, top + 2 * j + 1, left, &mut r1)?;
            for (a, c) in r0.chunks_exact(2).zip(r1.chunks_exact(2)) {
                let mut sums = [0u64; 3];
                for (v, colour) in a.iter().chain(c).zip(self.cfa) {
                    if let Some(s) = sums.get_mut(colour as usize) {
                        *s += *v as u64;
                    }
                }
                out.push(self.scale(sums[0], 1));
                out.push(self.scale(sums[1], 2));
                out.push(self.scale(sums[2], 1));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A little-endian TIFF writer: IFD entries and their out-of-line data.
    struct Writer {
        buf: Vec<u8>,
        be: bool,
    }

    /// (tag, type, values): values as u32, written as the type's size.
    type Tag = (u16, u16, Vec<u32>);

    impl Writer {
        fn new() -> Self {
            Writer::with_order(false)
        }
        /// Big-endian (`MM`) when `be`.
        fn with_order(be: bool) -> Self {
            let mut w = Writer {
                buf: if be { b"MM\0*" } else { b"II*\0" }.to_vec(),
                be,
            };
            w.buf.extend_from_slice(&[0; 4]);
            w
        }
        fn b16(&self, v: u16) -> [u8; 2] {
            if self.be {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        }
        fn b32(&self, v: u32) -> [u8; 4] {
            if self.be {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        }
        fn pad(&mut self) {
            if self.buf.len() % 2 == 1 {
                self.buf.push(0);
            }
        }
        fn blob(&mut self, data: &[u8]) -> u32 {
            self.pad();
            let at = self.buf.len() as u32;
            self.buf.extend_from_slice(data);
            at
        }
        /// Write an IFD; returns its offset and where its next-IFD pointer is.
        fn ifd(&mut self, tags: &[Tag]) -> (u32, usize) {
            let mut tags = tags.to_vec();
            tags.sort_by_key(|t| t.0);
            let mut encoded = Vec::new();
            for (tag, typ, vals) in &tags {
                let mut d = Vec::new();
                for v in vals {
                    match typ {
                        1 | 7 => d.push(*v as u8),
                        3 => d.extend_from_slice(&self.b16(*v as u16)),
                        _ => d.extend_from_slice(&self.b32(*v)),
                    }
                }
                let field = if d.len() <= 4 {
                    d.resize(4, 0);
                    d
                } else {
                    let at = self.blob(&d);
                    self.b32(at).to_vec()
                };
                // A RATIONAL's values are given as numerator, denominator pairs.
                let count = if matches!(typ, 5 | 10) {
                    vals.len() / 2
                } else {
                    vals.len()
                };
                encoded.push((*tag, *typ, count as u32, field));
            }
            self.pad();
            let at = self.buf.len() as u32;
            let n = self.b16(encoded.len() as u16);
            self.buf.extend_from_slice(&n);
            for (tag, typ, n, field) in encoded {
                let head = [self.b16(tag), self.b16(typ)].concat();
                self.buf.extend_from_slice(&head);
                let n = self.b32(n);
                self.buf.extend_from_slice(&n);
                self.buf.extend_from_slice(&field);
            }
            let next = self.buf.len();
            self.buf.extend_from_slice(&[0; 4]);
            (at, next)
        }
        fn set_u32(&mut self, at: usize, v: u32) {
            let b = self.b32(v);
            self.buf[at..at + 4].copy_from_slice(&b);
        }
    }

    /// A DNG: IFD0 a 4x4 8-bit RGB thumbnail (with DNGVersion), its SubIFD the raw
    /// `w` x `h` 16-bit mosaic in two strips, with `pattern` and WhiteLevel `white`.
    fn dng(raw: &[u16], w: u32, h: u32, pattern: [u32; 4], white: u32, extra: &[Tag]) -> Vec<u8> {
        let mut wr = Writer::new();
        let thumb = wr.blob(&[200u8; 4 * 4 * 3]);
        let bytes: Vec<u8> = raw.iter().flat_map(|v| v.to_le_bytes()).collect();
        let rows = h.div_ceil(2);
        let strip = (rows * w * 2) as usize;
        let s0 = wr.blob(&bytes[..strip.min(bytes.len())]);
        let s1 = wr.blob(&bytes[strip.min(bytes.len())..]);
        let mut raw_tags: Vec<Tag> = vec![
            (NEW_SUBFILE_TYPE, 4, vec![0]),
            (IMAGE_WIDTH, 4, vec![w]),
            (IMAGE_LENGTH, 4, vec![h]),
            (BITS_PER_SAMPLE, 3, vec![16]),
            (COMPRESSION, 3, vec![1]),
            (PHOTOMETRIC, 3, vec![32803]),
            (STRIP_OFFSETS, 4, vec![s0, s1]),
            (SAMPLES_PER_PIXEL, 3, vec![1]),
            (ROWS_PER_STRIP, 4, vec![rows]),
            (
                STRIP_BYTE_COUNTS,
                4,
                vec![strip as u32, (bytes.len() - strip) as u32],
            ),
            (CFA_REPEAT_PATTERN_DIM, 3, vec![2, 2]),
            (CFA_PATTERN, 1, pattern.to_vec()),
            (WHITE_LEVEL, 3, vec![white]),
        ];
        for e in extra {
            raw_tags.retain(|t| t.0 != e.0);
            raw_tags.push(e.clone());
        }
        let (sub, _) = wr.ifd(&raw_tags);
        let (ifd0, _) = wr.ifd(&[
            (NEW_SUBFILE_TYPE, 4, vec![1]),
            (IMAGE_WIDTH, 4, vec![4]),
            (IMAGE_LENGTH, 4, vec![4]),
            (BITS_PER_SAMPLE, 3, vec![8, 8, 8]),
            (COMPRESSION, 3, vec![1]),
            (PHOTOMETRIC, 3, vec![2]),
            (STRIP_OFFSETS, 4, vec![thumb]),
            (SAMPLES_PER_PIXEL, 3, vec![3]),
            (ROWS_PER_STRIP, 4, vec![4]),
            (STRIP_BYTE_COUNTS, 4, vec![48]),
            (SUB_IFDS, 4, vec![sub]),
            (DNG_VERSION, 1, vec![1, 4, 0, 0]),
        ]);
        wr.set_u32(4, ifd0);
        wr.buf
    }

    /// A 6x4 mosaic of 12-bit values, distinct everywhere.
    fn mosaic() -> (Vec<u16>, u32, u32) {
        let (w, h) = (6u32, 4u32);
        let v = (0..w * h).map(|i| ((i * 173 + 11) % 4096) as u16).collect();
        (v, w, h)
    }

    fn expected(raw: &[u16], w: u32, h: u32, pattern: [u32; 4], white: u32) -> Vec<u16> {
        let s = |v: f64| (v * 65535.0 / white as f64).round().min(65535.0) as u16;
        let mut out = Vec::new();
        for j in 0..(h / 2) as usize {
            for i in 0..(w / 2) as usize {
                let at = |dy: usize, dx: usize| raw[(2 * j + dy) * w as usize + 2 * i + dx] as f64;
                let block = [at(0, 0), at(0, 1), at(1, 0), at(1, 1)];
                let mut rgb = [0.0; 3];
                for (v, c) in block.iter().zip(pattern) {
                    rgb[c as usize] += v;
                }
                out.extend([s(rgb[0]), s(rgb[1] / 2.0), s(rgb[2])]);
            }
        }
        out
    }

    #[test]
    fn rggb_and_bggr_decode_to_exact_half_size_values_not_the_thumbnail() {
        let (raw, w, h) = mosaic();
        for pattern in [[0, 1, 1, 2], [2, 1, 1, 0], [1, 0, 2, 1], [1, 2, 0, 1]] {
            let bytes = dng(&raw, w, h, pattern, 4095, &[]);
            assert!(is_dng(&bytes));
            let info = probe(&bytes).unwrap();
            assert_eq!(
                info,
                ImageInfo {
                    width: 3,
                    height: 2,
                    bit_depth: 16
                }
            );
            let (info2, px) = decode(&bytes).unwrap();
            assert_eq!(info2, info);
            let Pixels::U16(px) = px else {
                panic!("16-bit expected")
            };
            assert_eq!(px, expected(&raw, w, h, pattern, 4095), "{pattern:?}");
        }
        // A hand-checked pixel: RGGB, block (0, 0) = raw 11, 184, 1049, 1222.
        let bytes = dng(&raw, w, h, [0, 1, 1, 2], 4095, &[]);
        let (_, Pixels::U16(px)) = decode(&bytes).unwrap() else {
            panic!()
        };
        assert_eq!(&raw[..2], &[11, 184]);
        assert_eq!(&raw[6..8], &[1049, 1222]);
        let r = (11.0f64 * 65535.0 / 4095.0).round() as u16;
        let g = ((184.0 + 1049.0) / 2.0f64 * 65535.0 / 4095.0).round() as u16;
        let b = (1222.0f64 * 65535.0 / 4095.0).round() as u16;
        assert_eq!(&px[..3], &[r, g, b]);
    }

    #[test]
    fn a_black_level_not_below_the_white_level_is_refused_naming_both_tags() {
        let (raw, w, h) = mosaic();
        for (black, refused) in [
            ((3, vec![64, 64, 64, 64]), None),
            ((3, vec![64, 64, 64, 4095]), Some("is 4095")),
            ((4, vec![60000]), Some("is 60000")),
            ((5, vec![129, 2]), None),
            ((5, vec![8191, 2]), Some("is 4095.5")),
        ] {
            let bytes = dng(
                &raw,
                w,
                h,
                [0, 1, 1, 2],
                4095,
                &[(BLACK_LEVEL, black.0, black.1)],
            );
            match refused {
                None => {
                    probe(&bytes).unwrap();
                    // Not subtracted: dark photos measure it.
                    let (_, Pixels::U16(px)) = decode(&bytes).unwrap() else {
                        panic!()
                    };
                    assert_eq!(px, expected(&raw, w, h, [0, 1, 1, 2], 4095));
                }
                Some(value) => {
                    let e = probe(&bytes).unwrap_err().to_string();
                    assert!(
                        e.contains(&format!("BlackLevel (tag 50714) {value}"))
                            && e.contains("WhiteLevel (tag 50717) 4095"),
                        "{e}"
                    );
                }
            }
        }
        let bytes = dng(
            &raw,
            w,
            h,
            [0, 1, 1, 2],
            4095,
            &[(BLACK_LEVEL, 5, vec![1, 0])],
        );
        assert!(probe(&bytes)
            .unwrap_err()
            .to_string()
            .contains("zero denominator"));
    }

    #[test]
    fn values_above_the_white_level_read_as_saturated() {
        let raw = vec![4095u16, 5000, 60000, 65535];
        let bytes = dng(&raw, 2, 2, [0, 1, 1, 2], 4095, &[]);
        let (_, Pixels::U16(px)) = decode(&bytes).unwrap() else {
            panic!()
        };
        assert_eq!(px, vec![65535, 65535, 65535]);
    }

    #[test]
    fn the_active_area_crops_and_sets_the_pattern_origin() {
        let (raw, w, h) = mosaic();
        // Columns 1..5, rows 0..4: with GRBG at the raw origin, RGGB from column 1.
        let bytes = dng(
            &raw,
            w,
            h,
            [1, 0, 2, 1],
            4095,
            &[(ACTIVE_AREA, 3, vec![0, 1, 4, 5])],
        );
        let (info, Pixels::U16(px)) = decode(&bytes).unwrap() else {
            panic!()
        };
        assert_eq!((info.width, info.height), (2, 2));
        let cropped: Vec<u16> = (0..4)
            .flat_map(|y| raw[y * 6 + 1..y * 6 + 5].to_vec())
            .collect();
        assert_eq!(px, expected(&cropped, 4, 4, [1, 0, 2, 1], 4095));
    }

    /// 12-bit samples packed MSB first, two to three bytes, in one strip.
    #[test]
    fn packed_12_bit_samples_are_read() {
        let (raw, w, h) = mosaic();
        let mut packed = Vec::new();
        for row in raw.chunks(w as usize) {
            for p in row.chunks(2) {
                let (a, b) = (p[0] as u32, p[1] as u32);
                let v = (a << 12) | b;
                packed.extend_from_slice(&[(v >> 16) as u8, (v >> 8) as u8, v as u8]);
            }
        }
        let mut wr = Writer::new();
        let s = wr.blob(&packed);
        let (ifd0, _) = wr.ifd(&[
            (IMAGE_WIDTH, 4, vec![w]),
            (IMAGE_LENGTH, 4, vec![h]),
            (BITS_PER_SAMPLE, 3, vec![12]),
            (PHOTOMETRIC, 3, vec![32803]),
            (STRIP_OFFSETS, 4, vec![s]),
            (STRIP_BYTE_COUNTS, 4, vec![packed.len() as u32]),
            (CFA_REPEAT_PATTERN_DIM, 3, vec![2, 2]),
            (CFA_PATTERN, 1, vec![0, 1, 1, 2]),
            (DNG_VERSION, 1, vec![1, 4, 0, 0]),
        ]);
        wr.set_u32(4, ifd0);
        let (_, Pixels::U16(px)) = decode(&wr.buf).unwrap() else {
            panic!()
        };
        assert_eq!(px, expected(&raw, w, h, [0, 1, 1, 2], 4095));
    }

    /// A 40x36 mosaic in 16x16 tiles (the last column and row of tiles partly outside
    /// the image); tiles smaller than TIFF's 16x16 are refused.
    #[test]
    fn tiles_are_read() {
        let (w, h) = (40u32, 36u32);
        let raw: Vec<u16> = (0..w * h).map(|i| ((i * 173 + 11) % 4096) as u16).collect();
        let (tw, tl) = (16usize, 16usize);
        let mut wr = Writer::new();
        let mut offs = Vec::new();
        for ty in 0..3 {
            for tx in 0..3 {
                let mut t = Vec::new();
                for y in 0..tl {
                    for x in 0..tw {
                        let (gx, gy) = (tx * tw + x, ty * tl + y);
                        let v = if gx < w as usize && gy < h as usize {
                            raw[gy * w as usize + gx]
                        } else {
                            0
                        };
                        t.extend_from_slice(&v.to_le_bytes());
                    }
                }
                offs.push(wr.blob(&t));
            }
        }
        let (ifd0, _) = wr.ifd(&[
            (IMAGE_WIDTH, 4, vec![w]),
            (IMAGE_LENGTH, 4, vec![h]),
            (BITS_PER_SAMPLE, 3, vec![16]),
            (PHOTOMETRIC, 3, vec![32803]),
            (TILE_WIDTH, 4, vec![tw as u32]),
            (TILE_LENGTH, 4, vec![tl as u32]),
            (TILE_OFFSETS, 4, offs),
            (TILE_BYTE_COUNTS, 4, vec![(tw * tl * 2) as u32; 9]),
            (CFA_REPEAT_PATTERN_DIM, 3, vec![2, 2]),
            (CFA_PATTERN, 1, vec![2, 1, 1, 0]),
            (WHITE_LEVEL, 3, vec![4095]),
            (DNG_VERSION, 1, vec![1, 4, 0, 0]),
        ]);
        wr.set_u32(4, ifd0);
        let (_, Pixels::U16(px)) = decode(&wr.buf).unwrap() else {
            panic!()
        };
        assert_eq!(px, expected(&raw, w, h, [2, 1, 1, 0], 4095));
        // The same file claiming 8x8 tiles.
        let mut small = wr.buf.clone();
        let at = small
            .windows(2)
            .enumerate()
            .find(|(i, _)| {
                small[*i..*i + 2] == TILE_WIDTH.to_le_bytes() && small[*i + 2..*i + 4] == [4, 0]
            })
            .map(|(i, _)| i)
            .unwrap();
        small[at + 8..at + 12].copy_from_slice(&8u32.to_le_bytes());
        let e = decode(&small).unwrap_err().to_string();
        assert!(e.contains("at least 16x16"), "{e}");
    }

    /// A big-endian file: 16-bit samples in its byte order; 8-bit samples as bytes.
    #[test]
    fn big_endian_16_bit_and_8_bit_samples_are_read() {
        let (raw, w, h) = mosaic();
        for bits in [16u32, 8] {
            let raw: Vec<u16> = raw
                .iter()
                .map(|v| if bits == 8 { v >> 4 } else { *v })
                .collect();
            let data: Vec<u8> = if bits == 8 {
                raw.iter().map(|&v| v as u8).collect()
            } else {
                raw.iter().flat_map(|v| v.to_be_bytes()).collect()
            };
            let mut wr = Writer::with_order(true);
            let s = wr.blob(&data);
            let (ifd0, _) = wr.ifd(&[
                (IMAGE_WIDTH, 3, vec![w]),
                (IMAGE_LENGTH, 3, vec![h]),
                (BITS_PER_SAMPLE, 3, vec![bits]),
                (PHOTOMETRIC, 3, vec![32803]),
                (STRIP_OFFSETS, 4, vec![s]),
                (STRIP_BYTE_COUNTS, 4, vec![data.len() as u32]),
                (CFA_REPEAT_PATTERN_DIM, 3, vec![2, 2]),
                (CFA_PATTERN, 1, vec![1, 2, 0, 1]),
                (DNG_VERSION, 1, vec![1, 4, 0, 0]),
            ]);
            wr.set_u32(4, ifd0);
            assert!(is_dng(&wr.buf));
            let (_, Pixels::U16(px)) = decode(&wr.buf).unwrap() else {
                panic!()
            };
            // WhiteLevel by default 2^bits - 1.
            let white = (1u32 << bits) - 1;
            assert_eq!(px, expected(&raw, w, h, [1, 2, 0, 1], white), "{bits}-bit");
        }
    }

    #[test]
    fn a_plain_tiff_is_not_a_dng() {
        let mut tiff = Vec::new();
        image::RgbImage::new(4, 4)
            .write_to(
                &mut std::io::Cursor::new(&mut tiff),
                image::ImageFormat::Tiff,
            )
            .unwrap();
        assert!(!is_dng(&tiff));
        assert!(!is_dng(b"II*\0"));
        assert!(!is_dng(b""));
        assert!(!is_dng(b"\x89PNG\r\n\x1a\n"));
    }

    #[test]
    fn what_is_not_read_is_refused_in_one_line_naming_the_way_out() {
        let (raw, w, h) = mosaic();
        let cases: Vec<(Vec<Tag>, &str)> = vec![
            (
                vec![(COMPRESSION, 3, vec![7])],
                "the DNG is compressed with lossless JPEG, which Glint does not read; convert it to an uncompressed DNG (dnglab convert --compression none IN OUT) or to a linear 16-bit TIFF (dcraw -4 -T)",
            ),
            (vec![(COMPRESSION, 3, vec![34892])], "lossy JPEG"),
            (vec![(COMPRESSION, 3, vec![52546])], "JPEG XL"),
            (vec![(PHOTOMETRIC, 3, vec![34892])], "LinearRaw"),
            (vec![(CFA_REPEAT_PATTERN_DIM, 3, vec![6, 6])], "X-Trans"),
            (vec![(CFA_PATTERN, 1, vec![0, 1, 2, 2])], "not one red, two green"),
            (vec![(SAMPLE_FORMAT, 3, vec![3])], "floating point"),
            (vec![(LINEARIZATION_TABLE, 3, vec![0, 1, 2])], "LinearizationTable"),
            (vec![(BITS_PER_SAMPLE, 3, vec![32])], "32-bit"),
            (vec![(IMAGE_WIDTH, 4, vec![20000])], "at most 16384 pixels a side"),
        ];
        for (extra, want) in cases {
            let bytes = dng(&raw, w, h, [0, 1, 1, 2], 4095, &extra);
            assert!(is_dng(&bytes));
            for e in
                [probe(&bytes).unwrap_err(), decode(&bytes).unwrap_err()].map(|e| e.to_string())
            {
                assert!(e.contains(want), "{e}\nshould contain: {want}");
                assert!(!e.contains('\n'), "{e}");
                assert!(
                    e.contains("dcraw -4 -T") || e.contains("megapixels"),
                    "names the way out: {e}"
                );
            }
        }
    }

    #[test]
    fn a_truncated_or_cyclic_dng_is_refused_not_a_panic() {
        let (raw, w, h) = mosaic();
        let bytes = dng(&raw, w, h, [0, 1, 1, 2], 4095, &[]);
        for cut in 0..bytes.len() {
            let r = decode(&bytes[..cut]);
            assert!(r.is_err() || cut == bytes.len());
        }
        // IFD0's next pointer back to IFD0: visited once.
        let mut c = bytes.clone();
        let ifd0 = u32::from_le_bytes(c[4..8].try_into().unwrap()) as usize;
        let n = u16::from_le_bytes([c[ifd0], c[ifd0 + 1]]) as usize;
        let next = ifd0 + 2 + 12 * n;
        c[next..next + 4].copy_from_slice(&(ifd0 as u32).to_le_bytes());
        assert!(decode(&c).is_ok());
    }

    /// Seeded random mutations of a valid DNG: never a panic, each result Ok or one line.
    #[test]
    fn random_mutations_never_panic() {
        let (raw, w, h) = mosaic();
        let base = dng(&raw, w, h, [0, 1, 1, 2], 4095, &[]);
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(0x0d1c_e5ee_d000_0001);
        let (mut ok, mut refused) = (0, 0);
        for _ in 0..3000 {
            let mut b = base.clone();
            let edits = rng.random_range(1..8);
            for _ in 0..edits {
                let i = rng.random_range(0..b.len());
                match rng.random_range(0..4) {
                    0 => b[i] = rng.random(),
                    1 => b[i] ^= 1 << rng.random_range(0..8),
                    2 => b[i] = [0, 0xff, 0x7f, 0x80, 2][rng.random_range(0..5)],
                    _ => b.truncate(i.max(8)),
                }
            }
            let _ = is_dng(&b);
            let p = probe(&b);
            match decode(&b) {
                Ok((info, px)) => {
                    ok += 1;
                    assert_eq!(p, Ok(info));
                    assert_eq!(px.len(), info.width as usize * info.height as usize * 3);
                }
                Err(e) => {
                    let e = e.to_string();
                    refused += 1;
                    assert!(!e.is_empty() && !e.contains('\n'), "{e:?}");
                }
            }
        }
        println!("3000 mutated DNGs: {ok} decoded, {refused} refused");
        assert!(ok > 0 && refused > 0);
    }
}
