//! How large an image Glint decodes, and what an image's header says: shared by the
//! decoders of [`super`] and of [`super::dng`].

/// Largest width or height of a frame or photo Glint decodes.
pub const MAX_SIDE: u32 = 16384;
/// Largest frame or photo Glint decodes, in pixels: 160 megapixels, above the largest
/// camera sensors made (151 MP). A 16000x16000 photo (256 MP, a few hundred KB as a PNG of
/// zeros) is refused from its header, before any pixel is decoded.
pub const MAX_PIXELS: u64 = 160_000_000;

/// What an image's header says, before anything is decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageInfo {
    pub width: u32,
    pub height: u32,
    /// 8 or 16.
    pub bit_depth: u8,
}
