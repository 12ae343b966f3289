//! DNG (camera raw) photos through `glint import` with a processing rig, then every stage.
//! The photos are the simulated lab's, written out as a camera's uncompressed DNG would
//! hold them: a small 8-bit RGB thumbnail in IFD0 (which a plain TIFF reader would take
//! for the photo) and the raw RGGB mosaic, 14-bit values in 16-bit samples, in a SubIFD.
//! Glint reads the mosaic at half size (one RGB pixel a 2x2 block, no interpolation).

use std::path::Path;

use glint::capture::FrameKind;

use super::import_rig::{chain, chosen_n, import_with_rig, processing_rig, s, table};
use super::util::{err, glint, ok, record, tempdir};

/// A little-endian TIFF: blobs and IFDs appended, (tag, type, values) entries.
struct Tiff {
    buf: Vec<u8>,
}

impl Tiff {
    fn new() -> Self {
        Tiff {
            buf: b"II*\0\0\0\0\0".to_vec(),
        }
    }
    fn blob(&mut self, data: &[u8]) -> u32 {
        if self.buf.len() % 2 == 1 {
            self.buf.push(0);
        }
        let at = self.buf.len() as u32;
        self.buf.extend_from_slice(data);
        at
    }
    fn ifd(&mut self, mut tags: Vec<(u16, u16, Vec<u32>)>) -> u32 {
        tags.sort_by_key(|t| t.0);
        let mut fields = Vec::new();
        for (tag, typ, vals) in &tags {
            let mut d = Vec::new();
            for v in vals {
                match typ {
                    1 => d.push(*v as u8),
                    3 => d.extend_from_slice(&(*v as u16).to_le_bytes()),
                    _ => d.extend_from_slice(&v.to_le_bytes()),
                }
            }
            let field = if d.len() <= 4 {
                d.resize(4, 0);
                d
            } else {
                self.blob(&d).to_le_bytes().to_vec()
            };
            fields.push((*tag, *typ, vals.len() as u32, field));
        }
        let at = self.blob(&(fields.len() as u16).to_le_bytes());
        for (tag, typ, n, field) in fields {
            self.buf.extend_from_slice(&tag.to_le_bytes());
            self.buf.extend_from_slice(&typ.to_le_bytes());
            self.buf.extend_from_slice(&n.to_le_bytes());
            self.buf.extend_from_slice(&field);
        }
        self.buf.extend_from_slice(&0u32.to_le_bytes());
        at
    }
}

/// A DNG of a 16-bit RGB frame: an RGGB mosaic (R from pixel (2i, 2j), G from (2i, 2j+1)
/// and (2i+1, 2j), B from (2i+1, 2j+1), as (row, column)) at 14 bits (v * 16383 / 65535,
/// rounded) in 16-bit samples, strips of 16 rows, BlackLevel and WhiteLevel `levels` (a
/// camera's: 256 and 16383), in a SubIFD; IFD0 a 64x48 8-bit RGB thumbnail.
/// `compression` is written as is (the data stay uncompressed: a reader that believes the
/// tag refuses before reading a pixel).
fn write_dng(
    path: &Path,
    img: &image::ImageBuffer<image::Rgb<u16>, Vec<u16>>,
    compression: u32,
    levels: (u32, u32),
) {
    let (w, h) = img.dimensions();
    let to14 = |v: u16| (v as f64 * 16383.0 / 65535.0).round() as u16;
    let mut raw = Vec::with_capacity((w * h * 2) as usize);
    for y in 0..h {
        for x in 0..w {
            let c = match (y % 2, x % 2) {
                (0, 0) => 0,
                (1, 1) => 2,
                _ => 1,
            };
            raw.extend_from_slice(&to14(img.get_pixel(x, y).0[c]).to_le_bytes());
        }
    }
    let mut t = Tiff::new();
    let thumb = image::imageops::thumbnail(img, 64, 48);
    let thumb: Vec<u8> = thumb.as_raw().iter().map(|v| (v >> 8) as u8).collect();
    let thumb_at = t.blob(&thumb);
    let rows = 16u32;
    let strip = (rows * w * 2) as usize;
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    for chunk in raw.chunks(strip) {
        offsets.push(t.blob(chunk));
        counts.push(chunk.len() as u32);
    }
    let sub = t.ifd(vec![
        (254, 4, vec![0]),
        (256, 4, vec![w]),
        (257, 4, vec![h]),
        (258, 3, vec![16]),
        (259, 3, vec![compression]),
        (262, 3, vec![32803]),
        (273, 4, offsets),
        (277, 3, vec![1]),
        (278, 4, vec![rows]),
        (279, 4, counts),
        (33421, 3, vec![2, 2]),
        (33422, 1, vec![0, 1, 1, 2]),
        (50714, 3, vec![levels.0]), // BlackLevel: Glint measures it from dark photos instead
        (50717, 3, vec![levels.1]),
    ]);
    let ifd0 = t.ifd(vec![
        (254, 4, vec![1]),
        (256, 4, vec![64]),
        (257, 4, vec![48]),
        (258, 3, vec![8, 8, 8]),
        (259, 3, vec![1]),
        (262, 3, vec![2]),
        (273, 4, vec![thumb_at]),
        (277, 3, vec![3]),
        (278, 4, vec![48]),
        (279, 4, vec![thumb.len() as u32]),
        (330, 4, vec![sub]),
        (50706, 1, vec![1, 4, 0, 0]),
    ]);
    t.buf[4..8].copy_from_slice(&ifd0.to_le_bytes());
    std::fs::write(path, t.buf).unwrap();
}

/// A session's frames written as DNGs (`compression` in each) into `photos`, with a times
/// file naming kinds; the times file's path.
fn dng_set(
    dir: &Path,
    rec: &glint::capture::Recorded,
    photos: &Path,
    compression: u32,
) -> std::path::PathBuf {
    dng_set_levels(dir, rec, photos, compression, (256, 16383))
}

/// [`dng_set`] with the BlackLevel and WhiteLevel tags given.
fn dng_set_levels(
    dir: &Path,
    rec: &glint::capture::Recorded,
    photos: &Path,
    compression: u32,
    levels: (u32, u32),
) -> std::path::PathBuf {
    let captured = dir.join("s");
    std::fs::create_dir_all(photos).unwrap();
    let mut times = String::from("# name  seconds  kind\n");
    for f in &rec.manifest.frames {
        let img = image::open(captured.join(&f.file)).unwrap().to_rgb16();
        let name = format!("IMG_{:04}.DNG", 100 + f.index);
        write_dng(&photos.join(&name), &img, compression, levels);
        times.push_str(&format!(
            "{name} {} {}\n",
            f.exposure_us() * 1e-6,
            f.kind.as_str()
        ));
    }
    let tf = photos.with_extension("times.txt");
    std::fs::write(&tf, times).unwrap();
    tf
}

/// A 640x480 16-bit capture written as uncompressed DNGs (bracket, dark and grid photos,
/// a thumbnail first in each): imported at half size, 320x240 16-bit, and every stage runs
/// to the tile's model.
#[test]
fn an_uncompressed_dng_session_is_read_at_half_size_and_runs_every_stage() {
    let dir = tempdir();
    let t = table([640, 480], 16, 7);
    let rec = record(dir.path(), &t).unwrap();
    let photos = dir.path().join("dng");
    let tf = dng_set(dir.path(), &rec, &photos, 1);
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let out = dir.path().join("imported");
    let said = ok(&import_with_rig(&photos, &tf, &rig, &out));
    assert!(said.contains("glint calibrate"), "{said}");
    let m = glint::session::load(&out).unwrap();
    let kinds = |k: FrameKind| m.frames.iter().filter(|f| f.kind == k).count();
    let own = |k: FrameKind| rec.manifest.frames.iter().filter(|f| f.kind == k).count();
    for k in [FrameKind::Tile, FrameKind::Dark, FrameKind::Grid] {
        assert_eq!(kinds(k), own(k), "{k:?}");
    }
    assert!(m
        .frames
        .iter()
        .all(|f| (f.width, f.height, f.bit_depth) == (320, 240, 16)));
    let r = m.rig.as_ref().unwrap();
    assert_eq!(
        (r.camera.width, r.camera.height, r.camera.bit_depth),
        (320, 240, 16)
    );
    // The frames are the mosaic's blocks: a tile frame's pixel is the capture's red at
    // (2i, 2j), the mean of its greens and its blue, through 14 bits and back.
    let tile = m.frames.iter().find(|f| f.kind == FrameKind::Tile).unwrap();
    let own_tile = &rec.manifest.frames[tile.index as usize];
    assert_eq!(own_tile.kind, FrameKind::Tile);
    assert_eq!(own_tile.exposure_us(), tile.exposure_us());
    let half = image::open(out.join(&tile.file)).unwrap().to_rgb16();
    let full = image::open(dir.path().join("s").join(&own_tile.file))
        .unwrap()
        .to_rgb16();
    let to14 = |v: u16| (v as f64 * 16383.0 / 65535.0).round();
    let back = |v: f64| (v * 65535.0 / 16383.0).round().min(65535.0) as u16;
    for (x, y) in [(0u32, 0u32), (160, 120), (319, 239), (77, 201)] {
        let p = |dx: u32, dy: u32, c: usize| full.get_pixel(2 * x + dx, 2 * y + dy).0[c];
        let want = [
            back(to14(p(0, 0, 0))),
            back((to14(p(1, 0, 1)) + to14(p(0, 1, 1))) / 2.0),
            back(to14(p(1, 1, 2))),
        ];
        assert_eq!(half.get_pixel(x, y).0, want, "pixel ({x}, {y})");
    }
    ok(&glint(&["session", "verify", s(&out)]));

    let fit = chain(&out);
    let (model, n, ci) = chosen_n(&fit);
    println!(
        "DNG import: {}x{} 16-bit frames from 640x480 mosaics; {model} n {n:.3} {ci:?} (truth blinn-phong 120)",
        r.camera.width, r.camera.height
    );
    assert_eq!(model, "blinn-phong");
    assert!((n / 120.0 - 1.0).abs() < 0.10, "{n}");
}

/// The same set with its raw data marked lossless-JPEG compressed: refused in one line
/// naming the conversion, with nothing written.
#[test]
fn a_compressed_dng_set_is_refused_in_one_line() {
    let dir = tempdir();
    let t = table([160, 120], 16, 3);
    let rec = record(dir.path(), &t).unwrap();
    let photos = dir.path().join("dng");
    let tf = dng_set(dir.path(), &rec, &photos, 7);
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let out = dir.path().join("imported");
    let e = err(&import_with_rig(&photos, &tf, &rig, &out));
    println!("{e}");
    assert!(
        e.contains("IMG_0100.DNG")
            && e.contains("compressed with lossless JPEG")
            && e.contains("dnglab convert --compression none")
            && e.contains("dcraw -4 -T"),
        "{e}"
    );
    assert!(!out.exists(), "nothing is written");
}

/// A DNG set whose BlackLevel (60000) is above its WhiteLevel (100): refused naming both
/// tags and their values, not the exposure times (before, every photo read as saturated
/// and the times were blamed). A set with a DNG cut to half its length is refused naming
/// it. Nothing is written.
#[test]
fn a_dng_black_level_above_its_white_level_is_blamed_on_those_tags() {
    let dir = tempdir();
    let t = table([160, 120], 16, 3);
    let rec = record(dir.path(), &t).unwrap();
    let rig = dir.path().join("processing.toml");
    processing_rig(&rig, &t);
    let photos = dir.path().join("dng");
    let tf = dng_set_levels(dir.path(), &rec, &photos, 1, (60000, 100));
    let out = dir.path().join("imported");
    let e = err(&import_with_rig(&photos, &tf, &rig, &out));
    println!("{e}");
    assert!(
        e.contains("IMG_0100.DNG")
            && e.contains("BlackLevel (tag 50714) is 60000")
            && e.contains("WhiteLevel (tag 50717) 100"),
        "{e}"
    );
    assert!(!e.contains("exposure"), "{e}");
    assert!(!out.exists(), "nothing is written");
    // A black level equal to the white level leaves no value to measure light either.
    let photos = dir.path().join("dng-ok");
    let tf = dng_set_levels(dir.path(), &rec, &photos, 1, (16383, 16383));
    assert!(err(&import_with_rig(&photos, &tf, &rig, &out)).contains("BlackLevel"));
    // Cut short.
    let photos = dir.path().join("dng-cut");
    let tf = dng_set(dir.path(), &rec, &photos, 1);
    let cut = photos.join("IMG_0101.DNG");
    let bytes = std::fs::read(&cut).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = err(&import_with_rig(&photos, &tf, &rig, &out));
    println!("{e}");
    assert!(e.contains("IMG_0101.DNG") && e.contains("corrupt"), "{e}");
    assert!(!out.exists(), "nothing is written");
}
