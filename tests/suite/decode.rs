//! The V4L2 pixel decoders (src/devices/decode.rs) on hand-computed pixel values: no device
//! needed, so they run in every build.

use glint::devices::decode::{
    decode, with_huffman_tables, ycbcr_to_rgb_formula, RawLayout, YcbcrMatrix, YcbcrParams,
    YcbcrRange,
};
use glint::devices::{DeviceError, Pixels};
use glint::rig::PixelFormat;

fn u8s(p: Pixels) -> Vec<u8> {
    match p {
        Pixels::U8(v) => v,
        Pixels::U16(_) => panic!("expected 8-bit pixels"),
    }
}

fn u16s(p: Pixels) -> Vec<u16> {
    match p {
        Pixels::U16(v) => v,
        Pixels::U8(_) => panic!("expected 16-bit pixels"),
    }
}

fn near(got: &[u8], want: &[u8], tol: u8) -> bool {
    got.len() == want.len() && got.iter().zip(want).all(|(g, w)| g.abs_diff(*w) <= tol)
}

#[test]
fn grey_respects_the_stride_and_refuses_a_short_buffer() {
    // 3x2, rows 4 bytes apart; the last row needs no padding.
    let mut l = RawLayout::packed(PixelFormat::GREY, 3, 2);
    l.bytes_per_line = 4;
    let data = [1, 2, 3, 99, 4, 5, 6];
    assert_eq!(u8s(decode(&l, &data, 0).unwrap()), [1, 2, 3, 4, 5, 6]);
    match decode(&l, &data[..6], 7) {
        Err(DeviceError::CorruptFrame {
            sequence: 7,
            reason,
        }) => {
            assert!(
                reason.contains("6 bytes") && reason.contains("needs 7"),
                "{reason}"
            )
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn y16_is_little_endian_and_y10_y12_scale_to_16_bits() {
    let l = RawLayout::packed(PixelFormat::Y16, 2, 1);
    assert_eq!(
        u16s(decode(&l, &[0x34, 0x12, 0xff, 0xff], 0).unwrap()),
        [0x1234, 0xffff]
    );
    // Y10: full scale 0x3ff -> 0xffc0; 0x201 -> 0x8040; the unused high bits are ignored.
    let l = RawLayout::packed(PixelFormat::Y10, 3, 1);
    let data = [0xff, 0x03, 0x01, 0x02, 0x01, 0xfc];
    assert_eq!(
        u16s(decode(&l, &data, 0).unwrap()),
        [0xffc0, 0x8040, 0x0040]
    );
    let l = RawLayout::packed(PixelFormat::Y12, 2, 1);
    assert_eq!(
        u16s(decode(&l, &[0xff, 0x0f, 0x00, 0x08], 0).unwrap()),
        [0xfff0, 0x8000]
    );
}

#[test]
fn rgb3_and_bgr3_give_rgb() {
    let l = RawLayout::packed(PixelFormat::RGB3, 2, 1);
    assert_eq!(
        u8s(decode(&l, &[1, 2, 3, 4, 5, 6], 0).unwrap()),
        [1, 2, 3, 4, 5, 6]
    );
    let l = RawLayout::packed(PixelFormat::BGR3, 2, 1);
    assert_eq!(
        u8s(decode(&l, &[1, 2, 3, 4, 5, 6], 0).unwrap()),
        [3, 2, 1, 6, 5, 4]
    );
}

fn yuyv(params: YcbcrParams, row: &[u8]) -> Vec<u8> {
    let mut l = RawLayout::packed(PixelFormat::YUYV, (row.len() / 2) as u32, 1);
    l.ycbcr = params;
    u8s(decode(&l, row, 0).unwrap())
}

const BT601_LIMITED: YcbcrParams = YcbcrParams {
    matrix: YcbcrMatrix::Bt601,
    range: YcbcrRange::Limited,
};

#[test]
fn yuyv_limited_range_white_black_and_grey() {
    // Y' 235 with neutral chroma is white, 16 is black; each chroma pair serves both pixels.
    assert_eq!(
        yuyv(BT601_LIMITED, &[235, 128, 16, 128]),
        [255, 255, 255, 0, 0, 0]
    );
    // Mid grey: (125.5 - 16) / 219 = 0.5 -> 127.5; 126 -> 128.
    assert!(near(
        &yuyv(BT601_LIMITED, &[126, 128, 126, 128]),
        &[128; 6],
        1
    ));
    // Below black and above white clip.
    assert_eq!(
        yuyv(BT601_LIMITED, &[0, 128, 255, 128]),
        [0, 0, 0, 255, 255, 255]
    );
}

#[test]
fn yuyv_pure_colours_in_each_matrix() {
    // R'G'B' (1, 0, 0) in BT.601 limited range: Y' = 16 + 219 * 0.299 = 81.5,
    // Cb = 128 - 112 * 0.299 / 0.886 = 90.2, Cr = 128 + 112 = 240.
    assert!(near(
        &yuyv(BT601_LIMITED, &[81, 90, 81, 240]),
        &[255, 0, 0, 255, 0, 0],
        1
    ));
    // Blue (0, 0, 1): Y' = 16 + 219 * 0.114 = 41, Cb = 240, Cr = 128 - 112 * 0.114 / 0.701 = 110.
    assert!(near(
        &yuyv(BT601_LIMITED, &[41, 240, 41, 110]),
        &[0, 0, 255, 0, 0, 255],
        1
    ));
    // Red in BT.709 limited: Y' = 16 + 219 * 0.2126 = 62.6, Cb = 128 - 112 * 0.2126 / 0.9278 = 102.3.
    let bt709 = YcbcrParams {
        matrix: YcbcrMatrix::Bt709,
        range: YcbcrRange::Limited,
    };
    assert!(near(
        &yuyv(bt709, &[63, 102, 63, 240]),
        &[255, 0, 0, 255, 0, 0],
        1
    ));
    // The same codes read as BT.601 are a different colour: the matrix matters.
    assert!(!near(
        &yuyv(BT601_LIMITED, &[63, 102, 63, 240]),
        &[255, 0, 0, 255, 0, 0],
        8
    ));
    // Green in BT.2020 full range: Y' = 255 * 0.678 = 172.9, Cb = 128 - 127.5 * 0.678 / 0.9407
    // = 36.1, Cr = 128 - 127.5 * 0.678 / 0.7373 = 10.8.
    let bt2020_full = YcbcrParams {
        matrix: YcbcrMatrix::Bt2020,
        range: YcbcrRange::Full,
    };
    assert!(near(
        &yuyv(bt2020_full, &[173, 36, 173, 11]),
        &[0, 255, 0, 0, 255, 0],
        1
    ));
    // Full range: 255 is white, 0 black.
    assert_eq!(
        yuyv(bt2020_full, &[255, 128, 0, 128]),
        [255, 255, 255, 0, 0, 0]
    );
}

#[test]
fn yuyv_chroma_is_shared_by_a_pair_of_pixels() {
    // Two pairs: a red pair, then a white/black pair; the red does not leak into pixel 2.
    let px = yuyv(BT601_LIMITED, &[81, 90, 81, 240, 235, 128, 16, 128]);
    assert!(near(&px[..6], &[255, 0, 0, 255, 0, 0], 1), "{px:?}");
    assert_eq!(&px[6..], &[255, 255, 255, 0, 0, 0]);
    // Two rows with a padded stride.
    let mut l = RawLayout::packed(PixelFormat::YUYV, 2, 2);
    l.bytes_per_line = 6;
    let data = [235, 128, 235, 128, 0, 0, 16, 128, 16, 128];
    assert_eq!(
        u8s(decode(&l, &data, 0).unwrap()),
        [255, 255, 255, 255, 255, 255, 0, 0, 0, 0, 0, 0]
    );
}

/// Every Y'/Cb/Cr combination in one frame: a row a (Cb, Cr) pair, 256 pixels wide, the
/// 256 luma codes in pairs (swapped on odd rows, so each code is both Y0 and Y1).
fn all_ycbcr_frame() -> (RawLayout, Vec<u8>) {
    let l = RawLayout::packed(PixelFormat::YUYV, 256, 65536);
    let mut data = Vec::with_capacity(256 * 65536 * 2);
    for row in 0..65536u32 {
        let (cb, cr) = ((row >> 8) as u8, row as u8);
        let swap = (row & 1) as u8;
        for y in (0..=255u8).step_by(2) {
            data.extend_from_slice(&[y ^ swap, cb, y ^ swap ^ 1, cr]);
        }
    }
    (l, data)
}

/// The formula's value rounded to nearest and clipped, and whether it lies so near a
/// half-step (a tie, up to the rounding of the coefficients) that either neighbour is right.
fn rounded(v: f64) -> (u8, bool) {
    let tie = (v - v.floor() - 0.5).abs() < 1e-4 && (0.0..=255.0).contains(&v);
    (v.round().clamp(0.0, 255.0) as u8, tie)
}

fn formula_rgb(p: YcbcrParams, y: u8, cb: u8, cr: u8) -> Vec<u8> {
    ycbcr_to_rgb_formula(p, y, cb, cr)
        .iter()
        .map(|v| rounded(*v).0)
        .collect()
}

#[test]
fn yuyv_fast_path_matches_the_formula_on_every_code() {
    // Every Y'/Cb/Cr combination, for every matrix and range: the decoder's fixed-point
    // tables give the floating-point formula rounded to nearest, except at exact ties
    // (e.g. BT.601 full range G' = Y' + 18.5 for Cb = 178, Cr = 78), which may go either way.
    let (mut l, data) = all_ycbcr_frame();
    for matrix in [
        YcbcrMatrix::Bt601,
        YcbcrMatrix::Bt709,
        YcbcrMatrix::Bt2020,
        YcbcrMatrix::Smpte240m,
    ] {
        for range in [YcbcrRange::Limited, YcbcrRange::Full] {
            let p = YcbcrParams { matrix, range };
            l.ycbcr = p;
            let got = u8s(decode(&l, &data, 0).unwrap());
            assert_eq!(got.len(), 256 * 65536 * 3);
            let mut ties = 0usize;
            for (q, px) in data.chunks_exact(4).zip(got.chunks_exact(6)) {
                let (cb, cr) = (q[1], q[3]);
                for (y, rgb) in [(q[0], &px[..3]), (q[2], &px[3..])] {
                    let exact = ycbcr_to_rgb_formula(p, y, cb, cr);
                    for (g, v) in rgb.iter().zip(exact) {
                        let (want, tie) = rounded(v);
                        assert!(
                            *g == want || (tie && g.abs_diff(want) == 1),
                            "{p}: Y'CbCr ({y}, {cb}, {cr}) -> {rgb:?}, the formula gives {exact:?}"
                        );
                        ties += (*g != want) as usize;
                    }
                }
            }
            assert!(ties < 256 * 65536 * 3 / 1000, "{p}: {ties} ties");
        }
    }
}

#[test]
fn yuyv_odd_width_and_padded_stride_take_the_fast_path_too() {
    // 3x2 frame, BT.709 full range, rows 10 bytes apart: a pair and a lone Y0 Cb a row.
    let p = YcbcrParams {
        matrix: YcbcrMatrix::Bt709,
        range: YcbcrRange::Full,
    };
    let mut l = RawLayout::packed(PixelFormat::YUYV, 3, 2);
    l.ycbcr = p;
    l.bytes_per_line = 10;
    let data = [
        200, 60, 90, 220, 30, 10, 7, 7, 7, 7, //
        16, 128, 235, 128, 128, 240,
    ];
    let got = u8s(decode(&l, &data, 0).unwrap());
    let r = |y, cb, cr| formula_rgb(p, y, cb, cr);
    let want: Vec<u8> = [
        r(200, 60, 220),
        r(90, 60, 220),
        r(30, 10, 128),
        r(16, 128, 128),
        r(235, 128, 128),
        r(128, 240, 128),
    ]
    .concat();
    assert!(near(&got, &want, 1), "{got:?} vs {want:?}");
}

#[test]
fn ycbcr_params_follow_the_kernels_defaults() {
    let p = |cs, enc, q| YcbcrParams::from_v4l2(cs, enc, q);
    // sRGB colour space (UVC cameras), nothing else set: BT.601, limited.
    assert_eq!(p(8, 0, 0), BT601_LIMITED);
    assert_eq!(p(0, 0, 0), BT601_LIMITED);
    // Rec. 709 colour space: BT.709.
    assert_eq!(p(3, 0, 0).matrix, YcbcrMatrix::Bt709);
    // JPEG colour space: BT.601 full range.
    assert_eq!(
        p(7, 0, 0),
        YcbcrParams {
            matrix: YcbcrMatrix::Bt601,
            range: YcbcrRange::Full
        }
    );
    // Explicit encoding and quantisation win: 709 (2), full range (1).
    assert_eq!(
        p(8, 2, 1),
        YcbcrParams {
            matrix: YcbcrMatrix::Bt709,
            range: YcbcrRange::Full
        }
    );
    assert_eq!(p(10, 0, 0).matrix, YcbcrMatrix::Bt2020);
    assert_eq!(p(7, 0, 2).range, YcbcrRange::Limited);
}

/// A 16x8 JPEG from the `image` crate's encoder (which writes the standard Annex K tables).
fn test_jpeg() -> (Vec<u8>, Vec<u8>) {
    let mut rgb = Vec::new();
    for y in 0..8u32 {
        for x in 0..16u32 {
            rgb.extend_from_slice(&[(x * 16) as u8, (y * 32) as u8, 200]);
        }
    }
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
        .encode(&rgb, 16, 8, image::ExtendedColorType::Rgb8)
        .unwrap();
    (jpeg, rgb)
}

/// The JPEG without its DHT segments, as many UVC cameras send it.
fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
    let mut out = jpeg[..2].to_vec();
    let mut i = 2;
    while jpeg[i + 1] != 0xda {
        let len = u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]) as usize;
        if jpeg[i + 1] != 0xc4 {
            out.extend_from_slice(&jpeg[i..i + 2 + len]);
        }
        i += 2 + len;
    }
    out.extend_from_slice(&jpeg[i..]);
    out
}

#[test]
fn mjpg_decodes_with_or_without_huffman_tables() {
    let (jpeg, rgb) = test_jpeg();
    let l = RawLayout::packed(PixelFormat::MJPG, 16, 8);
    let with = u8s(decode(&l, &jpeg, 0).unwrap());
    assert!(near(&with, &rgb, 12), "lossy, but close to the original");
    let bare = strip_dht(&jpeg);
    assert!(bare.len() < jpeg.len() && !bare.windows(2).any(|w| w == [0xff, 0xc4]));
    // The tables go in just before the scan, and the frame decodes to the same pixels.
    let fixed = with_huffman_tables(&bare).unwrap();
    assert!(fixed.windows(2).any(|w| w == [0xff, 0xc4]));
    assert_eq!(u8s(decode(&l, &bare, 0).unwrap()), with);
    // A frame that has its tables is left alone.
    assert!(matches!(
        with_huffman_tables(&jpeg).unwrap(),
        std::borrow::Cow::Borrowed(_)
    ));
}

#[test]
fn mjpg_damage_and_size_mismatch_are_corrupt_frames() {
    let (jpeg, _) = test_jpeg();
    let l = RawLayout::packed(PixelFormat::MJPG, 16, 8);
    for bad in [&jpeg[..jpeg.len() / 3], &jpeg[..1], &b"not a jpeg"[..]] {
        assert!(
            matches!(
                decode(&l, bad, 3),
                Err(DeviceError::CorruptFrame { sequence: 3, .. })
            ),
            "{} bytes",
            bad.len()
        );
    }
    let wrong = RawLayout::packed(PixelFormat::MJPG, 32, 8);
    match decode(&wrong, &jpeg, 4) {
        Err(DeviceError::CorruptFrame { reason, .. }) => {
            assert!(reason.contains("16x8"), "{reason}")
        }
        other => panic!("{other:?}"),
    }
}
