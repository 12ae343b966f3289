//! HDR: from an exposure bracket to radiance with a variance and a mask.
//!
//! - [`response`]: camera response recovery (Debevec & Malik with deliberate sampling and
//!   checks, or linear), the noise model, the inverse response;
//! - [`merge`]: the variance-optimal merge, streaming ([`merge::Merger`]) or all at once;
//! - [`files`]: `hdr/radiance.exr`, `variance.exr`, `mask.png`, the response as JSON, CSV
//!   and an SVG plot;
//! - [`run`]: the `glint hdr` stage on a session;
//! - [`dng`]: DNG camera raw photos (`glint import`), read as half-size linear RGB.
//!
//! Numerical code here is pure (no I/O); [`run`] and [`files`] do the reading and writing.

pub mod dng;
pub mod files;
pub mod limits;
pub mod run;

pub use limits::{ImageInfo, MAX_PIXELS, MAX_SIDE};

// The numerical half (response recovery, the merge, brackets) lives in `glint-numerics`.
pub use glint_numerics::hdr::{
    merge, response, Bracket, BracketFrame, DarkMedian, MergeError, MAX_EXPOSURE_US,
    MIN_EXPOSURE_US,
};

use std::path::{Path, PathBuf};

use crate::devices::Pixels;
use crate::plan::FrameKind;
use crate::session::{self, FrameRecord, Manifest, SessionError};

/// What can go wrong in the HDR stage.
#[derive(Debug, thiserror::Error)]
pub enum HdrError {
    /// The frames or times given cannot be merged (sizes, depths, times).
    #[error("{0}")]
    Input(String),
    /// The response cannot be recovered from these frames.
    #[error("response recovery failed: {0}")]
    Recovery(String),
    #[error(transparent)]
    Session(#[from] SessionError),
    /// What the numerical half refused (the same words as [`HdrError::Input`] and
    /// [`HdrError::Recovery`]).
    #[error(transparent)]
    Merge(#[from] MergeError),
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error("{path}: {source}")]
    Decode { path: PathBuf, source: DecodeError },
}

/// Why an image cannot be read: the reason, for the caller to put after the file's name.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("cannot read the image ({0})")]
    Read(std::io::Error),
    /// A format recognised but not built in (TIFF, WebP, ...).
    #[error("cannot decode the image ({}); Glint reads PNG, JPEG, TIFF and uncompressed DNG files", one_line(.0))]
    Unsupported(image::ImageError),
    /// Content recognised as no format at all.
    #[error("cannot decode the image ({}); the file is corrupt or not an image", one_line(.0))]
    Corrupt(image::ImageError),
    #[error("the image is {width}x{height} ({:.1} megapixels); Glint decodes at most {MAX_SIDE} pixels a side and {} megapixels", (*.width as u64 * *.height as u64) as f64 * 1e-6, MAX_PIXELS / 1_000_000)]
    TooLarge { width: u32, height: u32 },
    #[error("the image is {width}x{height}: it has no pixels")]
    NoPixels { width: u32, height: u32 },
    #[error("{0:?} images are not supported; use 8- or 16-bit frames")]
    Colour(image::ColorType),
    /// What the DNG reader refused ([`dng`]).
    #[error("{0}")]
    Dng(dng::DngError),
    #[error("the DNG decodes to 8-bit pixels; Glint reads DNGs as 16-bit")]
    Dng8Bit,
    #[error("the DNG decodes to fewer pixels than its size")]
    DngShort,
    #[error("the image decodes to {got_width}x{got_height} but its header says {width}x{height}; the file is corrupt")]
    Size {
        got_width: u32,
        got_height: u32,
        width: u32,
        height: u32,
    },
    #[error("cannot decode the JPEG ({}); the file is cut short (truncated) or corrupt", one_line(.0))]
    Jpeg(zune_jpeg::errors::DecodeErrors),
    #[error("the JPEG decodes to {values} values, not its header's {width}x{height} pixels; the file is corrupt")]
    JpegValues {
        values: usize,
        width: u32,
        height: u32,
    },
    #[error("the JPEG does not decode to its header's {width}x{height}; the file is corrupt")]
    JpegSize { width: u32, height: u32 },
}

/// The decoder's limits: [`MAX_SIDE`] a side, and allocations bounded by [`MAX_PIXELS`]
/// at 8 bytes a pixel (RGBA, 16 bits) plus room for the decoder's own buffers.
fn limits(sides: bool) -> image::Limits {
    let mut l = image::Limits::default();
    if sides {
        l.max_image_width = Some(MAX_SIDE);
        l.max_image_height = Some(MAX_SIDE);
    }
    l.max_alloc = Some(MAX_PIXELS * 8 + (64 << 20));
    l
}

fn one_line(e: impl std::fmt::Display) -> String {
    let s = e.to_string().replace(['\n', '\r'], " ");
    let q = crate::fsx::quote(&s);
    q[1..q.len() - 1].to_string()
}

fn cannot_decode(e: image::ImageError) -> DecodeError {
    // A format recognised but not built in (TIFF, WebP, ...); content recognised as no
    // format at all is "corrupt or not an image".
    if let image::ImageError::Unsupported(u) = &e {
        if u.format_hint() != image::error::ImageFormatHint::Unknown {
            return DecodeError::Unsupported(e);
        }
    }
    DecodeError::Corrupt(e)
}

/// Read an image's header only (nothing is decoded) and check it against the limits:
/// at most [`MAX_SIDE`] pixels a side and [`MAX_PIXELS`] in all, 8 or 16 bits a channel.
/// The error is the reason, for the caller to put after the file's name.
///
/// A DNG ([`dng::is_dng`]) is probed by [`dng::probe`]: its raw mosaic, not the thumbnail
/// a TIFF reader would find first, at half size and 16 bits.
pub fn probe_image(bytes: &[u8]) -> Result<ImageInfo, DecodeError> {
    use image::ImageDecoder;
    if dng::is_dng(bytes) {
        return dng::probe(bytes).map_err(DecodeError::Dng);
    }
    let mut r = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(DecodeError::Read)?;
    // The sides are checked here rather than by the decoder, to name them.
    r.limits(limits(false));
    let d = r.into_decoder().map_err(cannot_decode)?;
    let (w, h) = d.dimensions();
    let pixels = w as u64 * h as u64;
    if w > MAX_SIDE || h > MAX_SIDE || pixels > MAX_PIXELS {
        return Err(DecodeError::TooLarge {
            width: w,
            height: h,
        });
    }
    if w == 0 || h == 0 {
        return Err(DecodeError::NoPixels {
            width: w,
            height: h,
        });
    }
    use image::ColorType::*;
    let bit_depth = match d.color_type() {
        L8 | La8 | Rgb8 | Rgba8 => 8,
        L16 | La16 | Rgb16 | Rgba16 => 16,
        other => return Err(DecodeError::Colour(other)),
    };
    Ok(ImageInfo {
        width: w,
        height: h,
        bit_depth,
    })
}

/// Decode an image after checking its header ([`probe_image`]): nothing larger than the
/// limits is ever allocated. The error is the reason, for the caller to put after the
/// file's name.
///
/// A DNG ([`dng::is_dng`]) is decoded by [`dng::decode`] to half-size 16-bit RGB (see
/// [`dng`]); as an RGB image it then goes wherever a 16-bit RGB TIFF would: in
/// particular [`decode_as`] with one channel makes it grey with the same weights as any
/// colour photo (a weighted sum: still linear in the light).
pub fn decode_image(bytes: &[u8]) -> Result<(ImageInfo, image::DynamicImage), DecodeError> {
    if dng::is_dng(bytes) {
        let (info, pixels) = dng::decode(bytes).map_err(DecodeError::Dng)?;
        let Pixels::U16(v) = pixels else {
            return Err(DecodeError::Dng8Bit);
        };
        let img = image::ImageBuffer::from_raw(info.width, info.height, v)
            .ok_or(DecodeError::DngShort)?;
        return Ok((info, image::DynamicImage::ImageRgb16(img)));
    }
    let info = probe_image(bytes)?;
    let img = if image::guess_format(bytes).ok() == Some(image::ImageFormat::Jpeg) {
        decode_jpeg(bytes, info)?
    } else {
        let mut r = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(DecodeError::Read)?;
        r.limits(limits(true));
        r.decode().map_err(cannot_decode)?
    };
    if (img.width(), img.height()) != (info.width, info.height) {
        return Err(DecodeError::Size {
            got_width: img.width(),
            got_height: img.height(),
            width: info.width,
            height: info.height,
        });
    }
    Ok((info, img))
}

/// Decode a JPEG whose header [`probe_image`] has checked (`info`), refusing one that is
/// cut short or damaged.
///
/// The decoder is zune-jpeg, the one the image crate uses, but called directly in its
/// strict mode: the image crate runs it leniently, and a JPEG truncated to half its length
/// then decodes without an error, its missing rows grey (128), which would merge into
/// radiance as if measured. Strict, the decoder refuses an entropy-coded stream that ends
/// before its last block ("Premature end of buffer"), a marker where none belongs and
/// bytes between markers. PNG (the png crate checks each chunk's CRC and the zlib
/// stream's end), TIFF (each strip must be read whole) and DNG ([`dng`]: every strip
/// inside the file) refuse a file cut short already. The output is what the image crate
/// would make of it: RGB, RGBA, grey or grey with alpha, 8 bits.
fn decode_jpeg(bytes: &[u8], info: ImageInfo) -> Result<image::DynamicImage, DecodeError> {
    use image::{DynamicImage, ImageBuffer};
    use zune_core::colorspace::ColorSpace;
    let failed = DecodeError::Jpeg;
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(MAX_SIDE as usize)
        .set_max_height(MAX_SIDE as usize);
    let mut d = zune_jpeg::JpegDecoder::new_with_options(
        zune_core::bytestream::ZCursor::new(bytes),
        options,
    );
    d.decode_headers().map_err(failed)?;
    let out = match d.input_colorspace() {
        Some(c @ (ColorSpace::RGB | ColorSpace::RGBA | ColorSpace::Luma | ColorSpace::LumaA)) => c,
        _ => ColorSpace::RGB,
    };
    let options = d.options().jpeg_set_out_colorspace(out);
    d.set_options(options);
    let px = d.decode().map_err(failed)?;
    let (w, h) = (info.width, info.height);
    if px.len() as u64 != w as u64 * h as u64 * out.num_components() as u64 {
        return Err(DecodeError::JpegValues {
            values: px.len(),
            width: w,
            height: h,
        });
    }
    let img = match out {
        ColorSpace::RGBA => ImageBuffer::from_raw(w, h, px).map(DynamicImage::ImageRgba8),
        ColorSpace::Luma => ImageBuffer::from_raw(w, h, px).map(DynamicImage::ImageLuma8),
        ColorSpace::LumaA => ImageBuffer::from_raw(w, h, px).map(DynamicImage::ImageLumaA8),
        _ => ImageBuffer::from_raw(w, h, px).map(DynamicImage::ImageRgb8),
    };
    img.ok_or(DecodeError::JpegSize {
        width: w,
        height: h,
    })
}

/// Decode a PNG (or, for imports, any format the image crate reads) into RGB pixels,
/// bounded: the header is read and checked first ([`probe_image`]), so a small file that
/// claims a huge image is refused before anything is allocated.
pub fn decode(bytes: &[u8], name: &str) -> Result<(usize, usize, u8, Pixels), HdrError> {
    decode_as(bytes, name, 3)
}

/// [`decode`] into `channels` samples a pixel: 3 (RGB) or 1 (grey, a monochrome
/// camera's frames).
pub fn decode_as(
    bytes: &[u8],
    name: &str,
    channels: usize,
) -> Result<(usize, usize, u8, Pixels), HdrError> {
    let file = |source: DecodeError| HdrError::Decode {
        path: name.into(),
        source,
    };
    let (info, img) = decode_image(bytes).map_err(file)?;
    let (w, h) = (info.width as usize, info.height as usize);
    Ok(match (info.bit_depth, channels) {
        (8, 1) => (w, h, 8, Pixels::U8(img.into_luma8().into_raw())),
        (8, _) => (w, h, 8, Pixels::U8(img.into_rgb8().into_raw())),
        (_, 1) => (w, h, 16, Pixels::U16(img.into_luma16().into_raw())),
        _ => (w, h, 16, Pixels::U16(img.into_rgb16().into_raw())),
    })
}

/// Load a session's lit tile frames and its dark frames as brackets (shortest exposure
/// first), checking each file against the manifest ([`session::read_verified`]: inside
/// the session, size-capped, its checksum and header) and its decoded size and depth.
/// `m` is a manifest [`session::open`] has checked. Every frame is held in memory: the
/// HDR stage reads them one at a time instead ([`SessionFrames`]).
pub fn load_session(dir: &Path, m: &Manifest) -> Result<(Bracket, Bracket), HdrError> {
    let s = SessionFrames::new(dir, m)?;
    let tiles = s.tiles()?;
    let darks = s
        .darks
        .iter()
        .map(|f| s.read(f))
        .collect::<Result<Vec<_>, _>>()?;
    let d = Bracket::new_with(
        tiles.width,
        tiles.height,
        tiles.bit_depth,
        tiles.channels,
        darks,
    )?;
    Ok((tiles, d))
}

/// A session's tile and dark frames as its manifest lists them, each kind sorted by
/// exposure (shortest first, in listed order within one exposure), read and checked one at
/// a time ([`SessionFrames::read`]), so that a stage holds one decoded frame at a time
/// whatever the number of frames listed. The shapes and exposures are checked from the
/// manifest before any frame is read.
pub struct SessionFrames<'a> {
    dir: &'a Path,
    channels: u8,
    pub width: usize,
    pub height: usize,
    pub bit_depth: u8,
    /// Tile frames, shortest exposure first.
    pub tiles: Vec<&'a FrameRecord>,
    /// Dark frames, shortest exposure first.
    pub darks: Vec<&'a FrameRecord>,
}

impl<'a> SessionFrames<'a> {
    /// The session's frames (`m` a manifest [`session::open`] has checked): all of one
    /// size and depth, at least one tile frame, and the tile frames' exposures a bracket's
    /// ([`Bracket::check_exposures`]).
    pub fn new(dir: &'a Path, m: &'a Manifest) -> Result<Self, HdrError> {
        let mut first: Option<&FrameRecord> = None;
        let mut tiles = Vec::new();
        let mut darks = Vec::new();
        for f in &m.frames {
            match f.kind {
                FrameKind::Tile => tiles.push(f),
                FrameKind::Dark => darks.push(f),
                FrameKind::Grid => continue,
            }
            match first {
                None => first = Some(f),
                Some(a) => {
                    if (f.width, f.height) != (a.width, a.height) {
                        return Err(HdrError::Input(format!(
                            "{} is {}x{} but {} is {}x{}; all frames must have one size",
                            f.file, f.width, f.height, a.file, a.width, a.height
                        )));
                    }
                    if f.bit_depth != a.bit_depth {
                        return Err(HdrError::Input(format!(
                            "{} is {}-bit but {} is {}-bit; all frames must have one bit depth",
                            f.file, f.bit_depth, a.file, a.bit_depth
                        )));
                    }
                }
            }
        }
        let Some(a) = first.filter(|_| !tiles.is_empty()) else {
            return Err(HdrError::Input(
                "the session has no tile frames to merge".into(),
            ));
        };
        // Stable: frames of one exposure stay in the order listed.
        tiles.sort_by(|a, b| a.exposure_us().total_cmp(&b.exposure_us()));
        darks.sort_by(|a, b| a.exposure_us().total_cmp(&b.exposure_us()));
        let s = SessionFrames {
            dir,
            channels: m.channels(),
            width: a.width as usize,
            height: a.height as usize,
            bit_depth: a.bit_depth,
            tiles,
            darks,
        };
        s.times().check_exposures()?;
        Ok(s)
    }

    /// Samples a pixel: 3 (RGB) or 1 (monochrome).
    pub fn channels(&self) -> usize {
        self.channels as usize
    }

    /// The tile frames' times and names as a bracket whose frames hold no pixels (for
    /// [`Bracket::step`], [`Bracket::check_exposures`] and a summary's exposures).
    pub fn times(&self) -> Bracket {
        let none = || match self.bit_depth {
            8 => Pixels::U8(Vec::new()),
            _ => Pixels::U16(Vec::new()),
        };
        Bracket {
            width: self.width,
            height: self.height,
            bit_depth: self.bit_depth,
            channels: self.channels(),
            frames: self
                .tiles
                .iter()
                .map(|f| BracketFrame {
                    name: f.file.clone(),
                    exposure_us: f.exposure_us(),
                    pixels: none(),
                })
                .collect(),
        }
    }

    /// Read and decode one frame, checked against its record ([`session::read_verified`]:
    /// inside the session, size-capped, its checksum and header; then its decoded size
    /// and depth).
    pub fn read(&self, f: &FrameRecord) -> Result<BracketFrame, HdrError> {
        let bytes = session::read_verified(self.dir, f, self.channels)
            .map_err(|(path, reason)| HdrError::File { path, reason })?;
        let (w, h, bits, pixels) = decode_as(&bytes, &f.file, self.channels())?;
        drop(bytes);
        if (w as u64, h as u64, bits) != (f.width as u64, f.height as u64, f.bit_depth) {
            return Err(HdrError::File {
                path: self.dir.join(&f.file),
                reason: format!(
                    "decodes as {w}x{h} {bits}-bit but the manifest lists {}x{} {}-bit; the frame or the manifest was altered",
                    f.width, f.height, f.bit_depth
                ),
            });
        }
        Ok(BracketFrame {
            name: f.file.clone(),
            exposure_us: f.exposure_us(),
            pixels,
        })
    }

    /// Every tile frame, decoded (response recovery needs them all at once; their number
    /// is bounded by the capture plan, [`session::problems`]).
    pub fn tiles(&self) -> Result<Bracket, HdrError> {
        let frames = self
            .tiles
            .iter()
            .map(|f| self.read(f))
            .collect::<Result<Vec<_>, _>>()?;
        let b = Bracket::new_with(
            self.width,
            self.height,
            self.bit_depth,
            self.channels(),
            frames,
        )?;
        Ok(b)
    }

    /// What response recovery needs of the dark frames, read one at a time: each one's
    /// exposure and channel medians.
    pub fn dark_medians(&self) -> Result<Vec<DarkMedian>, HdrError> {
        self.darks
            .iter()
            .map(|f| {
                let d = self.read(f)?;
                Ok(DarkMedian::of(&d, self.bit_depth, self.channels()))
            })
            .collect()
    }
}
