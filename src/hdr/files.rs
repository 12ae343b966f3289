//! Files of the HDR stage: EXR images, the mask, the response as JSON, CSV and a plot.
//!
//! Every file is written to a temporary name and renamed into place
//! ([`crate::session::write_replace`]), so a reader never sees half a file.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use exr::prelude::{Image, SpecificChannels, Vec2, WritableImage};

use super::merge::{Merged, MASK_DARK, MASK_SATURATED};
use super::response::{channel_name, Response, FORMAT};
use super::HdrError;
use crate::session::write_replace;

/// What a plotters call into an SVG can fail with.
pub type PlotError = plotters::drawing::DrawingAreaErrorKind<std::io::Error>;

/// Why an image or a plot of the HDR stage cannot be encoded (the caller names the file).
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error(transparent)]
    Exr(#[from] exr::error::Error),
    #[error(transparent)]
    Image(#[from] image::ImageError),
    #[error("{samples} samples and {mask} mask values for a {width}x{height} image")]
    Sizes {
        samples: usize,
        mask: usize,
        width: usize,
        height: usize,
    },
    #[error("the response has no valid values")]
    NoValidValues,
    #[error("ln exposures {lo:.3e}..{hi:.3e} are beyond ±{PLOT_MAX_LN} (not a camera's response)")]
    BeyondPlot { lo: f64, hi: f64 },
    #[error(transparent)]
    Plot(#[from] PlotError),
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> HdrError {
    HdrError::File {
        path: path.into(),
        reason: reason.to_string(),
    }
}

/// Encode a float image as a 32-bit float OpenEXR file: RGB interleaved, or, with one
/// sample a pixel (`data` of width x height: a monochrome camera's), a single luminance
/// channel "Y". `attributes`: text attributes for the header (name, value), e.g. what the
/// numbers mean; the software's name is always set.
pub fn encode_exr(
    width: usize,
    height: usize,
    data: &[f32],
    attributes: &[(&str, String)],
) -> Result<Vec<u8>, EncodeError> {
    use exr::meta::attribute::{AttributeValue, Text};
    let software = Some(Text::from(
        format!("Glint {}", env!("CARGO_PKG_VERSION")).as_str(),
    ));
    let other = |m: &mut std::collections::HashMap<Text, AttributeValue>| {
        for (k, v) in attributes {
            m.insert(Text::from(*k), AttributeValue::Text(Text::from(v.as_str())));
        }
    };
    let mut buf = Vec::new();
    if data.len() == width * height {
        let channels = SpecificChannels::build()
            .with_channel("Y")
            .with_pixel_fn(|Vec2(x, y)| (data[y * width + x],));
        let mut img = Image::from_channels((width, height), channels);
        img.layer_data.attributes.software_name = software;
        other(&mut img.layer_data.attributes.other);
        img.write().to_buffered(Cursor::new(&mut buf))?;
        return Ok(buf);
    }
    let channels = SpecificChannels::rgb(|Vec2(x, y)| {
        let i = (y * width + x) * 3;
        (data[i], data[i + 1], data[i + 2])
    });
    let mut img = Image::from_channels((width, height), channels);
    img.layer_data.attributes.software_name = software;
    other(&mut img.layer_data.attributes.other);
    img.write().to_buffered(Cursor::new(&mut buf))?;
    Ok(buf)
}

/// The header attribute naming what an EXR of the HDR stage holds (one of the
/// `QUANTITY_*` values), which [`read_exr`] checks against the file's name.
pub const QUANTITY_KEY: &str = "glint_quantity";
/// `glint_quantity` of `radiance.exr`.
pub const QUANTITY_RADIANCE: &str = "radiance";
/// `glint_quantity` of `variance.exr`.
pub const QUANTITY_VARIANCE: &str = "variance of radiance (its units squared)";
/// `glint_quantity` of `radiance_filled.exr`.
pub const QUANTITY_FILLED: &str = "radiance, masked samples filled in";

/// What a session's EXR must hold, by its file name (`radiance.exr`, `variance.exr`,
/// `radiance_filled.exr`); None for any other name (nothing is required of it).
pub fn expected_quantity(path: &Path) -> Option<&'static str> {
    match path.file_name()?.to_str()? {
        "radiance.exr" => Some(QUANTITY_RADIANCE),
        "variance.exr" => Some(QUANTITY_VARIANCE),
        "radiance_filled.exr" => Some(QUANTITY_FILLED),
        _ => None,
    }
}

/// Whether an EXR header's `glint_quantity` (None: the file has none) may be read as the
/// file `path` names: a file without the attribute (written before it was checked, or by
/// another tool) is accepted; one that names another quantity is refused (radiance and
/// variance swapped or copied over each other), naming both and "re-run glint hdr".
pub fn quantity_problem(path: &Path, tagged: Option<&str>) -> Option<String> {
    let want = expected_quantity(path)?;
    let got = tagged?;
    (got != want).then(|| {
        format!(
            "its header's {QUANTITY_KEY} is {} but this file must hold {}: the HDR files were swapped or replaced; re-run glint hdr",
            crate::fsx::quote(got),
            crate::fsx::quote(want)
        )
    })
}

/// What the HDR files' numbers mean, for their headers (EXR text attributes).
fn exr_meaning(what: &str) -> Vec<(&'static str, String)> {
    vec![
        (QUANTITY_KEY, what.to_string()),
        (
            "glint_units",
            "relative radiance: exposure (the response curve's units) per second of exposure time, at the lamp's level; one scale for the session, not absolute".into(),
        ),
        (
            "glint_mask",
            "NaN where no radiance was measured: saturated in every frame (only a lower bound is known) or too dark in every frame; mask.png says which (255 saturated, 128 too dark, 0 measured); radiance.hdr holds no NaN".into(),
        ),
    ]
}

/// Radiance without NaN, for tone mappers: a saturated sample (`mask` [`MASK_SATURATED`])
/// becomes its channel's brightest measured radiance (a lower bound on it), a too-dark one
/// 0, as do non-finite ones; measured samples are kept as they are. `nc`: samples a pixel.
pub fn filled(data: &[f32], mask: &[u8], nc: usize) -> Vec<f32> {
    let mut brightest = [0.0f32; 3];
    for (i, (v, m)) in data.iter().zip(mask).enumerate() {
        if *m != MASK_SATURATED && *m != MASK_DARK && v.is_finite() {
            brightest[i % nc] = brightest[i % nc].max(*v);
        }
    }
    data.iter()
        .zip(mask)
        .enumerate()
        .map(|(i, (v, m))| match *m {
            MASK_SATURATED => brightest[i % nc],
            MASK_DARK => 0.0,
            _ if v.is_finite() => *v,
            _ => 0.0,
        })
        .collect()
}

/// `mask.png`'s value for a merge's mask value ([`MASK_SATURATED`] 255, [`MASK_DARK`]
/// 128, measured 0), and [`mask_from_png`] back.
pub fn mask_png_value(m: u8) -> u8 {
    match m {
        MASK_SATURATED => 255,
        MASK_DARK => 128,
        _ => 0,
    }
}

/// The merge's mask value for a `mask.png` value (see [`mask_png_value`]).
pub fn mask_from_png(v: u8) -> u8 {
    match v {
        255 => MASK_SATURATED,
        128 => MASK_DARK,
        _ => super::merge::MASK_OK,
    }
}

/// Read a session's `hdr/mask.png` for a `width` x `height` radiance of `channels` samples
/// a pixel (1: grey, 3: RGB) as the merge's mask values: size-capped, its size checked in
/// its header before anything is decoded (a PNG claiming another size is refused, naming
/// both, with "re-run glint hdr").
pub fn read_mask(
    file: impl Into<crate::fsx::Within>,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<Vec<u8>, HdrError> {
    let file = file.into();
    let path = &file.path();
    let bytes = file
        .read(crate::fsx::MAX_IMAGE_BYTES)
        .map_err(|e| file_err(path, format!("cannot read ({e}); re-run glint hdr")))?;
    match crate::session::png_header(&bytes) {
        Some((mw, mh, _, _)) if (mw as usize, mh as usize) == (width, height) => {}
        Some((mw, mh, _, _)) => {
            return Err(file_err(
                path,
                format!("is {mw}x{mh} but the radiance is {width}x{height}; re-run glint hdr"),
            ))
        }
        None => return Err(file_err(path, "is not a PNG; re-run glint hdr")),
    }
    let (_, _, _, px) = super::decode_as(&bytes, &path.display().to_string(), channels)
        .map_err(|e| file_err(path, format!("{e}; re-run glint hdr")))?;
    let crate::devices::Pixels::U8(v) = px else {
        return Err(file_err(path, "is not an 8-bit mask; re-run glint hdr"));
    };
    Ok(v.into_iter().map(mask_from_png).collect())
}

/// Write `radiance_filled.exr` beside a session's `hdr/radiance.exr`: the same radiance
/// with no NaN ([`filled`]; the mask read from `mask.png`), for tone mappers that NaN
/// poisons (OpenCV's Reinhard). Its header says what was filled in.
pub fn write_filled(hdr_dir: &Path) -> Result<PathBuf, HdrError> {
    let (w, h, data) = read_exr(crate::fsx::Within::new(hdr_dir, "radiance.exr"))?;
    let nc = data.len() / (w * h).max(1);
    let mask = read_mask(crate::fsx::Within::new(hdr_dir, "mask.png"), w, h, nc)?;
    let out = hdr_dir.join("radiance_filled.exr");
    let mut attrs = exr_meaning(QUANTITY_FILLED);
    attrs.retain(|(k, _)| *k != "glint_mask");
    attrs.push((
        "glint_mask",
        "no NaN: samples saturated in every frame hold their channel's brightest measured radiance (a lower bound on theirs), samples too dark in every frame hold 0; mask.png says which (255 saturated, 128 too dark, 0 measured); radiance.exr keeps NaN there".into(),
    ));
    let bytes =
        encode_exr(w, h, &filled(&data, &mask, nc), &attrs).map_err(|e| file_err(&out, e))?;
    write_replace(&out, &bytes)?;
    Ok(out)
}

/// Encode radiance as Radiance RGBE (`.hdr`): RGB interleaved, or one sample a pixel
/// (written as grey RGB). RGBE holds no NaN and nothing negative: a saturated sample
/// (`mask` [`MASK_SATURATED`]) is written as its channel's brightest measured radiance (a
/// lower bound on it), a too-dark one as 0, a negative one as 0. Precision: RGBE's shared
/// exponent with 8-bit mantissas, 1/256 of the pixel's brightest channel.
pub fn encode_rgbe(
    width: usize,
    height: usize,
    data: &[f32],
    mask: &[u8],
) -> Result<Vec<u8>, EncodeError> {
    let nc = if data.len() == width * height { 1 } else { 3 };
    if data.len() != width * height * nc || mask.len() != data.len() {
        return Err(EncodeError::Sizes {
            samples: data.len(),
            mask: mask.len(),
            width,
            height,
        });
    }
    let filled = filled(data, mask, nc);
    let value = |i: usize| filled[i].max(0.0);
    let px: Vec<image::Rgb<f32>> = (0..width * height)
        .map(|p| {
            if nc == 1 {
                image::Rgb([value(p); 3])
            } else {
                image::Rgb([value(3 * p), value(3 * p + 1), value(3 * p + 2)])
            }
        })
        .collect();
    let mut buf = Vec::new();
    image::codecs::hdr::HdrEncoder::new(&mut buf).encode(&px, width, height)?;
    Ok(buf)
}

/// Read an EXR into (width, height, samples): an RGB(A) file as interleaved RGB, a file
/// with a luminance channel "Y" and no "R" (a monochrome camera's) as one sample a pixel
/// (so the samples' count says which: width x height x 3, or width x height). A regular
/// file, size-capped, with every layer at most [`crate::session::MAX_SIDE`] pixels a side
/// (checked in the header, before any pixel is allocated). A session's `radiance.exr`,
/// `variance.exr` or `radiance_filled.exr` whose header names another quantity
/// (`glint_quantity`) is refused ([`quantity_problem`]).
pub fn read_exr(file: impl Into<crate::fsx::Within>) -> Result<(usize, usize, Vec<f32>), HdrError> {
    use exr::prelude::{read, ReadChannels, ReadLayers, ReadSpecificChannel};
    let file = file.into();
    let path = &file.path();
    let bytes = file
        .read(crate::fsx::MAX_IMAGE_BYTES)
        .map_err(|e| file_err(path, format!("cannot read ({e})")))?;
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(&bytes), false)
        .map_err(|e| file_err(path, format!("not an OpenEXR file ({e}); re-run glint hdr")))?;
    let max = crate::session::MAX_SIDE as usize;
    if let Some(h) = meta
        .headers
        .iter()
        .find(|h| h.layer_size.0 > max || h.layer_size.1 > max)
    {
        return Err(file_err(
            path,
            format!(
                "declares a {}x{} image, more than {max} pixels a side; re-run glint hdr",
                h.layer_size.0, h.layer_size.1
            ),
        ));
    }
    // What the file says it holds, against what its name says it must.
    let tagged = meta.headers.first().and_then(|h| {
        match h
            .own_attributes
            .other
            .get(&exr::meta::attribute::Text::from(QUANTITY_KEY))
        {
            Some(exr::meta::attribute::AttributeValue::Text(t)) => Some(t.to_string()),
            Some(_) => Some("(not text)".to_string()),
            None => None,
        }
    });
    if let Some(p) = quantity_problem(path, tagged.as_deref()) {
        return Err(file_err(path, p));
    }
    let named = |n: &str| {
        meta.headers.first().is_some_and(|h| {
            h.channels
                .list
                .iter()
                .any(|c| c.name.to_string().as_str() == n)
        })
    };
    if named("Y") && !named("R") {
        let img = read()
            .no_deep_data()
            .largest_resolution_level()
            .specific_channels()
            .required("Y")
            .collect_pixels(
                |res, _| (res.width(), vec![0.0f32; res.width() * res.height()]),
                |(w, px): &mut (usize, Vec<f32>), Vec2(x, y), (v,): (f32,)| {
                    if let Some(p) = px.get_mut(y * *w + x) {
                        *p = v;
                    }
                },
            )
            .first_valid_layer()
            .all_attributes()
            .from_buffered(Cursor::new(bytes))
            .map_err(|e| file_err(path, e))?;
        let size = img.layer_data.size;
        return Ok((size.0, size.1, img.layer_data.channel_data.pixels.1));
    }
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |res, _| (res.width(), vec![0.0f32; res.width() * res.height() * 3]),
            |(w, px): &mut (usize, Vec<f32>), Vec2(x, y), (r, g, b, _a): (f32, f32, f32, f32)| {
                let i = (y * *w + x) * 3;
                if let Some(p) = px.get_mut(i..i + 3) {
                    p.copy_from_slice(&[r, g, b]);
                }
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| file_err(path, e))?;
    let size = img.layer_data.size;
    Ok((size.0, size.1, img.layer_data.channel_data.pixels.1))
}

/// `radiance.exr` and `variance.exr` (see [`write_merged`]).
fn write_exrs(dir: &Path, m: &Merged) -> Result<(), HdrError> {
    for (name, data, what) in [
        ("radiance.exr", &m.radiance, QUANTITY_RADIANCE),
        ("variance.exr", &m.variance, QUANTITY_VARIANCE),
    ] {
        let path = dir.join(name);
        let bytes = encode_exr(m.width, m.height, data, &exr_meaning(what))
            .map_err(|e| file_err(&path, e))?;
        write_replace(&path, &bytes)?;
    }
    Ok(())
}

/// `radiance.hdr` and `preview.png`, for viewers and people (see [`write_merged`]).
fn write_views(dir: &Path, m: &Merged) -> Result<(), HdrError> {
    let path = dir.join("radiance.hdr");
    let bytes =
        encode_rgbe(m.width, m.height, &m.radiance, &m.mask).map_err(|e| file_err(&path, e))?;
    write_replace(&path, &bytes)?;
    let path = dir.join("preview.png");
    let png = crate::session::encode_png(
        m.width as u32,
        m.height as u32,
        &crate::devices::Pixels::U8(tone_mapped(m.width, m.height, &m.radiance, &m.mask)),
    )
    .map_err(|e| file_err(&path, e))?;
    write_replace(&path, &png)?;
    Ok(())
}

/// A picture of the radiance for people: Reinhard's global operator (the log-average
/// luminance of the measured samples mapped to 0.18, then L / (1 + L)), sRGB-encoded, 8
/// bits; saturated samples white, too-dark ones black. RGB interleaved or one sample a
/// pixel (then grey).
pub fn tone_mapped(width: usize, height: usize, data: &[f32], mask: &[u8]) -> Vec<u8> {
    let nc = if data.len() == width * height { 1 } else { 3 };
    let weights: &[f64] = if nc == 1 {
        &[1.0]
    } else {
        &[0.2126, 0.7152, 0.0722]
    };
    let value = |i: usize| data.get(i).copied().unwrap_or(0.0).max(0.0) as f64;
    let ok = |p: usize| (0..nc).all(|c| mask.get(nc * p + c) == Some(&super::merge::MASK_OK));
    let lum = |p: usize| -> f64 { (0..nc).map(|c| weights[c] * value(nc * p + c)).sum() };
    let (mut sum, mut count) = (0.0, 0usize);
    for p in (0..width * height).filter(|p| ok(*p)) {
        let l = lum(p);
        if l.is_finite() {
            sum += (l + 1e-12).ln();
            count += 1;
        }
    }
    let key = if count > 0 {
        0.18 / (sum / count as f64).exp()
    } else {
        1.0
    };
    // The sRGB encoding from a table (a power a sample took 0.2 s at 1280x960): 16384
    // steps, a fifth of an output level where the curve is steepest.
    const STEPS: usize = 16384;
    let table: Vec<u8> = (0..=STEPS)
        .map(|i| {
            let x = i as f64 / STEPS as f64;
            let v = if x <= 0.003_130_8 {
                12.92 * x
            } else {
                1.055 * x.powf(1.0 / 2.4) - 0.055
            };
            (v * 255.0).round() as u8
        })
        .collect();
    let srgb = |x: f64| {
        let x = if x.is_finite() {
            x.clamp(0.0, 1.0)
        } else {
            0.0
        };
        table[(x * STEPS as f64).round() as usize]
    };
    let mut out = Vec::with_capacity(width * height * nc);
    for p in 0..width * height {
        let l = lum(p) * key;
        // Each channel scaled as the luminance is (hue kept).
        let scale = if l > 0.0 && l.is_finite() {
            key / (1.0 + l)
        } else {
            0.0
        };
        for c in 0..nc {
            let i = nc * p + c;
            out.push(match mask.get(i) {
                Some(&MASK_SATURATED) => 255,
                Some(&MASK_DARK) => 0,
                _ => srgb(value(i) * scale),
            });
        }
    }
    out
}

/// Write `radiance.exr`, `variance.exr`, `radiance.hdr`, `preview.png` and `mask.png`
/// into `dir`.
///
/// The mask is an 8-bit RGB PNG (grey for a monochrome camera), per channel: 0 = radiance
/// measured, 255 = saturated in every frame (only a lower bound is known), 128 = too dark
/// in every frame. Masked samples are NaN in both EXR files, which have the channels R, G,
/// B, or Y alone for a monochrome camera, and say so in their headers (`glint_quantity`,
/// `glint_units`, `glint_mask`, `software`). `radiance.hdr` is the radiance as Radiance
/// RGBE for viewers and tone mappers, with no NaN ([`encode_rgbe`]); `preview.png` a
/// tone-mapped picture of it for people ([`tone_mapped`]).
pub fn write_merged(dir: &Path, m: &Merged) -> Result<(), HdrError> {
    crate::session::out_dir(dir)?;
    // The files for viewers are made on a second thread while the EXRs are (each takes
    // about as long at 1280x960: 0.05 s).
    std::thread::scope(|sc| {
        let views = sc.spawn(|| write_views(dir, m));
        let exrs = write_exrs(dir, m);
        let views = views
            .join()
            .unwrap_or_else(|p| std::panic::resume_unwind(p));
        exrs.and(views)
    })?;
    let mask: Vec<u8> = m.mask.iter().map(|v| mask_png_value(*v)).collect();
    let path = dir.join("mask.png");
    let png = crate::session::encode_png(
        m.width as u32,
        m.height as u32,
        &crate::devices::Pixels::U8(mask),
    )
    .map_err(|e| file_err(&path, e))?;
    write_replace(&path, &png)?;
    Ok(())
}

/// Write `response.json`, `response.csv` and `response.svg` into `dir`; `step` is the
/// bracket's exposure step in ln where known (the plot's band then includes the curve error
/// a bracket cannot see, as the fit's draws do).
pub fn write_response(dir: &Path, r: &Response, step: Option<f64>) -> Result<(), HdrError> {
    crate::session::out_dir(dir)?;
    save_response(&dir.join("response.json"), r)?;
    // The exposure of every value, then whether the value carries radiance (1: within the
    // channel's valid range; 0: too dark or saturated, where the table is only continued so
    // that it stays monotonic and says nothing measured).
    let mut csv = String::from("value");
    for c in 0..r.channels.len() {
        csv.push_str(&format!(",exposure_{}", r.channel_name(c).to_lowercase()));
    }
    for c in 0..r.channels.len() {
        csv.push_str(&format!(",valid_{}", r.channel_name(c).to_lowercase()));
    }
    csv.push('\n');
    for (z, e) in r.table() {
        csv.push_str(&z.to_string());
        for v in e {
            csv.push_str(&format!(",{v:.9e}"));
        }
        for ch in &r.channels {
            let valid = (ch.valid_min..=ch.valid_max).contains(&z);
            csv.push_str(if valid { ",1" } else { ",0" });
        }
        csv.push('\n');
    }
    write_replace(&dir.join("response.csv"), csv.as_bytes())?;
    let svg = plot_response(r, step).map_err(|e| file_err(&dir.join("response.svg"), e))?;
    write_replace(&dir.join("response.svg"), svg.as_bytes())?;
    Ok(())
}

/// Write a response's JSON to `path` (atomically).
pub fn save_response(path: &Path, r: &Response) -> Result<(), HdrError> {
    let json = serde_json::to_vec_pretty(r).expect("response serialises");
    write_replace(path, &json)?;
    Ok(())
}

/// Read a response JSON file: size-capped, a regular file, and every value usable
/// ([`response_problem`]).
pub fn load_response(file: impl Into<crate::fsx::Within>) -> Result<Response, HdrError> {
    let file = file.into();
    let path = &file.path();
    let text = file
        .read(crate::fsx::MAX_TEXT_BYTES)
        .map_err(|e| file_err(path, format!("cannot read ({e})")))?;
    let r: Response = serde_json::from_slice(&text).map_err(|e| {
        file_err(
            path,
            format!("not a Glint response file ({})", crate::fsx::json_error(&e)),
        )
    })?;
    if r.format != FORMAT || !(r.channels.len() == 3 || r.channels.len() == 1) {
        return Err(file_err(
            path,
            "not a Glint response file (its channels must be 3, R G B, or 1 for a monochrome camera)",
        ));
    }
    if let Some(p) = response_problem(&r) {
        return Err(file_err(
            path,
            format!("not a usable response: {p}; recover one with glint response"),
        ));
    }
    Ok(r)
}

/// What makes a response unusable (None when it is fine): bit depth 8 or 16; per channel
/// a table of one ln exposure per value (|ln E| <= 700), strictly increasing over the
/// channel's valid range, for the table models, or a positive gain and a black level in
/// range for the linear one; a valid range inside the values; noise terms and standard
/// deviations non-negative; at most 10 polynomial coefficients with a square covariance
/// (no negative variance); every number finite. The rules of every response Glint reads:
/// a session's `hdr/response.json`, a camera's profile beside the rig, `--response`.
pub fn response_problem(r: &Response) -> Option<String> {
    use super::response::Model;
    if r.bit_depth != 8 && r.bit_depth != 16 {
        return Some(format!("bit_depth must be 8 or 16 (got {})", r.bit_depth));
    }
    let max = r.max_value();
    let finite = |v: &[f64]| {
        v.iter()
            .all(|x| x.is_finite() && x.abs() <= super::response::LN_EXPOSURE_LIMIT)
    };
    for (c, ch) in r.channels.iter().enumerate() {
        let name = channel_name(r.channels.len(), c);
        match r.model {
            Model::Debevec | Model::Polynomial => {
                if ch.ln_exposure.len() != max as usize + 1 || !finite(&ch.ln_exposure) {
                    return Some(format!(
                        "channel {name}: ln_exposure must hold {} finite values (one per pixel value)",
                        max + 1
                    ));
                }
                if !(ch.ln_exposure_sd.is_empty()
                    || ch.ln_exposure_sd.len() == ch.ln_exposure.len()
                        && ch.ln_exposure_sd.iter().all(|x| x.is_finite() && *x >= 0.0))
                {
                    return Some(format!(
                        "channel {name}: ln_exposure_sd must be empty or one finite value, not negative, per pixel value"
                    ));
                }
                // A response rises with the pixel value over the values it is used for.
                let (lo, hi) = (ch.valid_min as usize, ch.valid_max as usize);
                if lo < hi && hi < ch.ln_exposure.len() {
                    if let Some(z) = (lo..hi).find(|&z| ch.ln_exposure[z + 1] <= ch.ln_exposure[z])
                    {
                        return Some(format!(
                            "channel {name}: ln_exposure must increase over the valid range {lo}..{hi}, but it does not from value {z} ({}) to {} ({}) (reversed or edited)",
                            ch.ln_exposure[z],
                            z + 1,
                            ch.ln_exposure[z + 1]
                        ));
                    }
                }
                let k = ch.coefficients.len();
                if k > super::response::MAX_DEGREE
                    || !ch.coefficients.iter().all(|x| x.is_finite())
                    || !(ch.coefficient_covariance.is_empty()
                        || ch.coefficient_covariance.len() == k
                            && ch
                                .coefficient_covariance
                                .iter()
                                .enumerate()
                                .all(|(i, row)| {
                                    row.len() == k
                                        && row.iter().all(|x| x.is_finite())
                                        && row[i] >= 0.0
                                }))
                {
                    return Some(format!(
                        "channel {name}: at most {} finite coefficients, with a square covariance of their number (no negative variance)",
                        super::response::MAX_DEGREE
                    ));
                }
            }
            Model::Linear => {
                if !(ch.gain.is_finite() && ch.gain > 0.0 && ch.gain < 1e12) {
                    return Some(format!(
                        "channel {name}: gain must be positive and finite (got {})",
                        ch.gain
                    ));
                }
                if !(ch.black.is_finite() && ch.black >= 0.0 && ch.black < max as f64) {
                    return Some(format!(
                        "channel {name}: black must be in 0..{max} (got {})",
                        ch.black
                    ));
                }
            }
        }
        if ch.valid_min >= ch.valid_max || ch.valid_max > max {
            return Some(format!(
                "channel {name}: the valid range {}..{} must lie in 0..{max} with min < max",
                ch.valid_min, ch.valid_max
            ));
        }
        let n = &ch.noise;
        if !(n.shot.is_finite() && n.shot >= 0.0 && n.read.is_finite() && n.read >= 0.0) {
            return Some(format!(
                "channel {name}: noise shot and read must be non-negative and finite"
            ));
        }
    }
    alternatives_problem(r)
}

/// Most alternative curves a response file may hold (a recovery keeps at most two: the
/// models not chosen).
const MAX_ALTERNATIVES: usize = 4;

/// What makes a response's alternative curves unusable (see [`response_problem`]): at
/// most [`MAX_ALTERNATIVES`], one list per channel, each of at most 4 096 (value, change)
/// pairs with values rising within the format's and changes finite (|change| <= 700).
fn alternatives_problem(r: &Response) -> Option<String> {
    if r.alternatives.len() > MAX_ALTERNATIVES {
        return Some(format!(
            "at most {MAX_ALTERNATIVES} alternatives (got {})",
            r.alternatives.len()
        ));
    }
    let max = r.max_value();
    for (i, a) in r.alternatives.iter().enumerate() {
        if a.channels.len() != r.channels.len() {
            return Some(format!(
                "alternative {i} must list {} channels (got {})",
                r.channels.len(),
                a.channels.len()
            ));
        }
        for (c, knots) in a.channels.iter().enumerate() {
            let ok = knots.len() <= 4096
                && knots
                    .iter()
                    .all(|(z, d)| *z <= max && d.is_finite() && d.abs() <= 700.0)
                && knots.windows(2).all(|w| w[0].0 < w[1].0);
            if !ok {
                return Some(format!(
                    "alternative {i}, channel {}: at most 4096 (value, change) pairs, values rising within 0..{max}, changes finite",
                    channel_name(r.channels.len(), c)
                ));
            }
        }
    }
    None
}

static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");

/// Register the embedded font with plotters (once).
pub fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, FONT)
            .map_err(|_| ())
            .expect("the embedded font is valid");
    });
}

/// Largest |ln relative exposure| [`plot_response`] draws (a response file holds at most
/// 700, [`response_problem`]).
const PLOT_MAX_LN: f64 = 1e4;

/// An SVG plot of ln(relative exposure) against pixel value for the three channels (one
/// grey curve for a monochrome camera) over each channel's valid range, with the curve's
/// 95% band; below it the band's half-width in percent of exposure, which on the curve's
/// own scale is too narrow to see. The band is [`Response::ln_sd_at`]: what the fit's
/// curve draws carry (`step`: the bracket's exposure step in ln, where known), a Debevec
/// curve's own sd and the top's shape allowance.
pub fn plot_response(r: &Response, step: Option<f64>) -> Result<String, EncodeError> {
    use plotters::prelude::*;
    register_font();
    let table = r.table();
    let max = r.max_value() as f64;
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for (z, e) in &table {
        for (c, v) in e.iter().enumerate() {
            let ch = &r.channels[c];
            if *z >= ch.valid_min && *z <= ch.valid_max && v.ln().is_finite() {
                lo = lo.min(v.ln());
                hi = hi.max(v.ln());
            }
        }
    }
    if !lo.is_finite() {
        return Err(EncodeError::NoValidValues);
    }
    if lo < -PLOT_MAX_LN || hi > PLOT_MAX_LN {
        return Err(EncodeError::BeyondPlot { lo, hi });
    }
    // Per channel: (z, ln E, sd of ln E) over the valid values.
    let values: Vec<Vec<u32>> = r
        .channels
        .iter()
        .map(|ch| {
            table
                .iter()
                .map(|(z, _)| *z)
                .filter(|z| (ch.valid_min..=ch.valid_max).contains(z))
                .collect()
        })
        .collect();
    let sd = r.ln_sd_at(&values, step);
    let curves: Vec<Vec<(f64, f64, f64)>> = (0..r.channels.len())
        .map(|c| {
            values[c]
                .iter()
                .zip(&sd[c])
                .map(|(&z, &s)| (z as f64, r.exposure(c, z as f64).ln(), s))
                .filter(|p| p.1.is_finite() && p.2.is_finite())
                .collect()
        })
        .collect();
    // The band's half-width in percent (exp(1.96 sd) - 1), at most 100% on the plot.
    let pct = |s: f64| (100.0 * ((1.96 * s).exp() - 1.0)).min(100.0);
    let band_max = curves
        .iter()
        .flatten()
        .map(|p| pct(p.2))
        .fold(0.0f64, f64::max);
    let band_top = if band_max > 0.0 {
        nice_up(1.1 * band_max)
    } else {
        1.0
    };
    // At least a thousandth of the values' size: a range too narrow for an f64 step
    // makes plotters loop for ever looking for tick marks.
    let pad = (0.05 * (hi - lo)).max(1e-3 * (1.0 + lo.abs().max(hi.abs())));
    let colours = if r.channels.len() == 1 {
        [RGBColor(96, 96, 96); 3]
    } else {
        [RED, GREEN, BLUE]
    };
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (720, 640)).into_drawing_area();
        root.fill(&WHITE)?;
        let (upper, lower) = root.split_vertically(440);
        let mut chart = ChartBuilder::on(&upper)
            .caption(
                format!("Camera response ({} model)", r.model.as_str()),
                ("sans-serif", 20),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..max, (lo - pad)..(hi + pad))?;
        chart
            .configure_mesh()
            .x_desc("pixel value z")
            .y_desc("ln relative exposure g(z)")
            .draw()?;
        for (c, pts) in curves.iter().enumerate() {
            let ch = &r.channels[c];
            let band: Vec<(f64, f64)> = pts
                .iter()
                .map(|p| (p.0, p.1 + 1.96 * p.2))
                .chain(pts.iter().rev().map(|p| (p.0, p.1 - 1.96 * p.2)))
                .collect();
            if band.len() > 2 {
                chart.draw_series(std::iter::once(Polygon::new(band, colours[c].mix(0.25))))?;
            }
            chart
                .draw_series(LineSeries::new(
                    pts.iter().map(|p| (p.0, p.1)),
                    colours[c].stroke_width(2),
                ))?
                .label(format!(
                    "{} (valid {}..{})",
                    r.channel_name(c),
                    ch.valid_min,
                    ch.valid_max
                ))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colours[c].stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::LowerRight)
            .draw()?;
        let mut chart = ChartBuilder::on(&lower)
            .caption(
                if band_max > 0.0 {
                    "the curve's 95% band, ± % of exposure"
                } else {
                    "the curve's 95% band: none (a linear curve that fits its data)"
                },
                ("sans-serif", 16),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..max, -band_top..band_top)?;
        chart
            .configure_mesh()
            .x_desc("pixel value z")
            .light_line_style(TRANSPARENT)
            .y_desc("± % of E")
            .draw()?;
        for (c, pts) in curves.iter().enumerate() {
            let band: Vec<(f64, f64)> = pts
                .iter()
                .map(|p| (p.0, pct(p.2)))
                .chain(pts.iter().rev().map(|p| (p.0, -pct(p.2))))
                .collect();
            if band.len() > 2 && band_max > 0.0 {
                chart.draw_series(std::iter::once(Polygon::new(band, colours[c].mix(0.15))))?;
                for sign in [1.0, -1.0] {
                    chart.draw_series(LineSeries::new(
                        pts.iter().map(|p| (p.0, sign * pct(p.2))),
                        colours[c].stroke_width(1),
                    ))?;
                }
            }
        }
        root.present()?;
    }
    Ok(svg)
}

/// The smallest of 1, 2, 5 times a power of ten at or above `x` (> 0).
fn nice_up(x: f64) -> f64 {
    let p = 10f64.powf(x.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * p)
        .find(|v| *v >= x * (1.0 - 1e-12))
        .unwrap_or(10.0 * p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    /// An 8-bit Debevec response whose every ln exposure in the valid range is `ln`.
    fn flat_response(ln: f64) -> Response {
        let ch = serde_json::json!({
            "ln_exposure": vec![ln; 256],
            "valid_min": 5, "valid_max": 250,
            "noise": {"shot": 0.0, "read": 0.0},
            "rms_residual": 0.0, "samples": 0,
        });
        serde_json::from_value(serde_json::json!({
            "format": FORMAT, "format_version": 1, "model": "debevec", "bit_depth": 8,
            "channels": [ch.clone(), ch.clone(), ch],
        }))
        .unwrap()
    }

    #[test]
    fn huge_ln_exposures_do_not_hang_the_response_plot() {
        // Was: a response with ln E = 1.15e12 (a profile) or 1e9 (`hdr --response`) had
        // plotters look for tick marks for ever.
        for ln in [1e9, 1.15e12, -1e12] {
            let t = Instant::now();
            let e = plot_response(&flat_response(ln), None)
                .unwrap_err()
                .to_string();
            assert!(e.contains("no valid values"), "{e}");
            assert!(t.elapsed() < Duration::from_secs(2));
        }
        // One entry beyond what exp() holds (a profile's channels[1].ln_exposure[216]).
        let mut r = flat_response(1.0);
        r.channels[1].ln_exposure[216] = 1.15e12;
        let t = Instant::now();
        assert!(plot_response(&r, None).unwrap().contains("<svg"));
        assert!(t.elapsed() < Duration::from_secs(5));
        // A flat curve at a large but possible value is drawn, promptly.
        for ln in [0.0, 700.0, -700.0] {
            let t = Instant::now();
            assert!(plot_response(&flat_response(ln), None)
                .unwrap()
                .contains("<svg"));
            assert!(t.elapsed() < Duration::from_secs(5), "ln E = {ln}");
        }
    }

    #[test]
    fn a_response_file_with_huge_or_long_values_is_refused_on_one_short_line() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("response.json");
        std::fs::write(&p, serde_json::to_vec(&flat_response(1e9)).unwrap()).unwrap();
        let e = load_response(&p).unwrap_err().to_string();
        assert!(e.contains("not a usable response"), "{e}");
        // A wrong value quoted by the parser is cut.
        let mut v = serde_json::to_value(flat_response(0.0)).unwrap();
        v["model"] = serde_json::Value::String(format!("{}\n", "x".repeat(10_000)));
        std::fs::write(&p, serde_json::to_vec(&v).unwrap()).unwrap();
        let e = load_response(&p).unwrap_err().to_string();
        assert!(e.contains("not a Glint response file"), "{e}");
        assert!(e.chars().count() < 500 && !e.contains('\n'), "{e}");
    }
}
