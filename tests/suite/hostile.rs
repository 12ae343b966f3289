//! Hostile and absurd input to `glint import`, `glint hdr`, `glint calibrate --images`:
//! decompression bombs refused from their headers under a memory budget, absurd or
//! inverted exposure times, radiance that would not be finite, overlong values in
//! messages, files that are not regular files. Each test is named after the defect it
//! pins.

use std::path::{Path, PathBuf};

use super::util::{err, glint, ok, tempdir};

/// CRC-32 (ISO-HDLC, as PNG uses).
fn crc32(parts: &[&[u8]]) -> u32 {
    let mut table = [0u32; 256];
    for (i, t) in table.iter_mut().enumerate() {
        let mut c = i as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
        *t = c;
    }
    let mut c = !0u32;
    for p in parts {
        for b in *p {
            c = table[((c ^ *b as u32) & 0xff) as usize] ^ (c >> 8);
        }
    }
    !c
}

/// Deflate's bit order: values least significant bit first, Huffman codes most
/// significant bit first.
struct Bits {
    out: Vec<u8>,
    acc: u64,
    n: u32,
}

impl Bits {
    fn put(&mut self, v: u32, n: u32) {
        self.acc |= (v as u64) << self.n;
        self.n += n;
        while self.n >= 8 {
            self.out.push(self.acc as u8);
            self.acc >>= 8;
            self.n -= 8;
        }
    }
    fn code(&mut self, code: u32, len: u32) {
        self.put(code.reverse_bits() >> (32 - len), len);
    }
    fn finish(mut self) -> Vec<u8> {
        if self.n > 0 {
            self.out.push(self.acc as u8);
        }
        self.out
    }
}

/// A `w` x `h` 8-bit grey PNG of zeros, written without ever holding its pixels: one
/// deflate block with the fixed codes, a literal 0 and then copies of 258 bytes at
/// distance 1 (13 bits each). A 16000x16000 one is 1.6 MB and claims 256 MB of pixels.
fn zero_png(w: u32, h: u32) -> Vec<u8> {
    let raw = (w as u64 + 1) * h as u64; // a filter byte (0) and the row, per row
    let mut bits = Bits {
        out: vec![0x78, 0x01],
        acc: 0,
        n: 0,
    };
    bits.put(1, 1); // the last block
    bits.put(1, 2); // fixed codes
    let literal0 = |b: &mut Bits| b.code(0x30, 8);
    literal0(&mut bits);
    let rest = raw - 1;
    for _ in 0..rest / 258 {
        bits.code(0xC5, 8); // length 258 (code 285)
        bits.code(0, 5); // distance 1
    }
    for _ in 0..rest % 258 {
        literal0(&mut bits);
    }
    bits.code(0, 7); // end of block
    let mut z = bits.finish();
    let adler = (((raw % 65521) as u32) << 16) | 1;
    z.extend_from_slice(&adler.to_be_bytes());
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8; 4], data: &[u8]| {
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        png.extend_from_slice(kind);
        png.extend_from_slice(data);
        png.extend_from_slice(&crc32(&[kind, data]).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &z);
    chunk(b"IEND", &[]);
    png
}

#[test]
fn the_hand_written_zero_png_is_a_valid_png() {
    let png = zero_png(300, 7);
    let img = image::load_from_memory(&png).unwrap().into_luma8();
    assert_eq!(img.dimensions(), (300, 7));
    assert!(img.iter().all(|v| *v == 0));
}

/// Memory given to the child in the bomb tests: 200 MB of address space.
const BUDGET_MB: u64 = 200;

/// Run glint with at most [`BUDGET_MB`] of address space ([`super::util::glint_limited`]).
fn glint_limited(args: &[&str]) -> (bool, String, f64) {
    super::util::glint_limited(args, BUDGET_MB)
}

fn one_error_line(stderr: &str) -> String {
    let lines: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    lines[0].to_string()
}

/// Four 16000x16000 grey PNGs (today's defect: `glint import` decoded them all at once and
/// aborted at 3.2 GB) are refused from their headers by a glint limited to 200 MB of
/// memory, with its one-line error; `glint calibrate --images` refuses such a photo the
/// same way.
#[test]
fn sixteen_thousand_squared_png_bomb_is_refused_under_200_mb() {
    let dir = tempdir();
    let d = dir.path().join("bomb");
    std::fs::create_dir(&d).unwrap();
    let png = zero_png(16000, 16000);
    println!("a 16000x16000 zero PNG: {} KB", png.len() / 1024);
    let mut times = String::new();
    for i in 0..4 {
        std::fs::write(d.join(format!("b{i}.png")), &png).unwrap();
        times.push_str(&format!("b{i}.png 1/{}\n", 1000 >> i));
    }
    drop(png);
    let tf = dir.path().join("times.txt");
    std::fs::write(&tf, times).unwrap();
    let out = dir.path().join("s");
    let (success, stderr, peak) = glint_limited(&[
        "import",
        d.to_str().unwrap(),
        "--times",
        tf.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    println!("glint import of four 16000² PNGs within {BUDGET_MB} MB: peak RSS <= {peak:.1} MB");
    assert!(!success);
    // Refused with its one-line error, not killed by the limit.
    let e = one_error_line(&stderr);
    assert!(
        e.contains("16000x16000") && e.contains("megapixels") && e.contains("b0.png"),
        "{e}"
    );
    assert!(!out.exists());
    let (success, stderr, peak) = glint_limited(&[
        "calibrate",
        "--images",
        d.join("b0.png").to_str().unwrap(),
        "--grid",
        "9x6",
        "--out",
        dir.path().join("c").to_str().unwrap(),
    ]);
    println!(
        "glint calibrate --images of a 16000² PNG within {BUDGET_MB} MB: peak RSS <= {peak:.1} MB"
    );
    assert!(!success);
    let e = one_error_line(&stderr);
    assert!(e.contains("16000x16000") && e.contains("b0.png"), "{e}");
    // The library's decoder refuses it too (frames of a session go through it).
    let e = glint::hdr::decode(&zero_png(16000, 16000), "frames/x.png").unwrap_err();
    assert!(e
        .to_string()
        .starts_with("frames/x.png: the image is 16000x16000"));
}

/// Photos that are large but allowed are decoded one at a time: four 4000x4000 photos
/// (48 MB of RGB pixels each; all at once, as before, 192 MB plus their PNG buffers)
/// import within 200 MB of memory.
#[test]
fn import_decodes_one_photo_at_a_time() {
    let dir = tempdir();
    let d = dir.path().join("big");
    std::fs::create_dir(&d).unwrap();
    let png = zero_png(4000, 4000);
    let mut times = String::new();
    for i in 0..4 {
        std::fs::write(d.join(format!("b{i}.png")), &png).unwrap();
        times.push_str(&format!("b{i}.png 1/{}\n", 1000 >> i));
    }
    let tf = dir.path().join("times.txt");
    std::fs::write(&tf, times).unwrap();
    let out = dir.path().join("s");
    let (success, stderr, peak) = glint_limited(&[
        "import",
        d.to_str().unwrap(),
        "--times",
        tf.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    println!("glint import of four 4000² PNGs within {BUDGET_MB} MB: peak RSS <= {peak:.1} MB");
    assert!(success, "{stderr}");
    assert_eq!(glint::session::load(&out).unwrap().frames.len(), 4);
}

/// A folder of three small 8-bit photos, brighter with `i`, with a times file.
fn photos(dir: &Path, times: &str) -> (PathBuf, PathBuf) {
    let d = dir.join("photos");
    std::fs::create_dir_all(&d).unwrap();
    for i in 0..3u32 {
        image::RgbImage::from_fn(32, 24, |x, y| image::Rgb([(20 + 60 * i + x + y) as u8; 3]))
            .save(d.join(format!("p{i}.png")))
            .unwrap();
    }
    let tf = dir.join("times.txt");
    std::fs::write(&tf, times).unwrap();
    (d, tf)
}

fn import(d: &Path, tf: &Path, out: &Path) -> std::process::Output {
    glint(&[
        "import",
        d.to_str().unwrap(),
        "--times",
        tf.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
}

/// Nothing but the photos and the times file is left in `dir` (no session, no staging
/// folder).
fn nothing_written(dir: &Path) {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["photos", "times.txt"]);
}

/// A times file in inverse seconds (`250` for 1/250 s: today accepted, and `hdr` then gives
/// a misleading error) reverses the bracket: refused, naming the two photos and the 1/s
/// mistake; nothing is written.
#[test]
fn times_in_inverse_seconds_are_refused_naming_both_photos() {
    let dir = tempdir();
    let (d, tf) = photos(dir.path(), "p0.png 250\np1.png 125\np2.png 60\n");
    let e = err(&import(&d, &tf, &dir.path().join("s")));
    assert!(
        e.contains("p1.png (125 s) is darker than p2.png (60 s)") && e.contains("1/s"),
        "{e}"
    );
    assert!(e.contains("times.txt"), "{e}");
    nothing_written(dir.path());
    // The same photos with the times in seconds import.
    std::fs::write(&tf, "p0.png 1/250\np1.png 1/125\np2.png 1/60\n").unwrap();
    ok(&import(&d, &tf, &dir.path().join("s")));
}

/// Absurd exposure times (1e-300 s, 1e300 s: today they import, and the merge divides by
/// them) are refused up front with the range.
#[test]
fn absurd_exposure_times_are_refused_by_import_with_the_range() {
    for (t, want) in [
        ("1e-300", "outside the 1 µs .. 1 hour"),
        ("1e300", "outside the 1 µs .. 1 hour"),
        ("7200", "outside the 1 µs .. 1 hour"),
        ("0.0000001", "outside the 1 µs .. 1 hour"),
        ("1/0", "not a number of seconds"),
    ] {
        let dir = tempdir();
        let (d, tf) = photos(
            dir.path(),
            &format!("p0.png 1/250\np1.png {t}\np2.png 1/60\n"),
        );
        let e = err(&import(&d, &tf, &dir.path().join("s")));
        assert!(e.contains(want) && e.contains("p1.png"), "{t}: {e}");
        assert!(e.contains("times.txt:2"), "{e}");
        nothing_written(dir.path());
    }
}

/// The NaN import fails `hdr`: a session whose exposure times make the merge non-finite
/// (an import made before the times were checked, or by another tool: here the manifest's
/// exact time of one frame is 1e300 µs) fails `glint hdr` with one line naming that frame
/// and its exposure, and writes no radiance.
#[test]
fn the_nan_import_fails_hdr() {
    for (bad, shown) in [(1e300, "1e300 µs"), (1e-300, "1e-300 µs")] {
        let dir = tempdir();
        let (d, tf) = photos(dir.path(), "p0.png 1/250\np1.png 1/125\np2.png 1/60\n");
        let s = dir.path().join("s");
        ok(&import(&d, &tf, &s));
        let path = s.join("manifest.json");
        let mut m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        m["frames"][2]["exposure_exact_us"] = serde_json::json!(bad);
        let frame = m["frames"][2]["file"].as_str().unwrap().to_string();
        std::fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
        let e = err(&glint(&["hdr", s.to_str().unwrap()]));
        assert!(e.contains(&frame) && e.contains(shown), "{e}");
        assert!(e.len() < 600, "{e}");
        assert!(!s.join("hdr/radiance.exr").exists());
    }
}

/// A times file line of a megabyte (today quoted whole in the error) is quoted in at most
/// ~100 characters, on one line.
#[test]
fn a_megabyte_times_file_line_is_quoted_short() {
    let long = "x".repeat(1 << 20);
    for times in [
        format!("{long}\n"),
        format!("p0.png {long}\n"),
        format!("p0.png 1/250\n{long} 1/100\n"),
        // A name short enough to be a path, too long for a file name.
        format!("p0.png 1/250\n{} 1/100\n", "y".repeat(3000)),
    ] {
        let dir = tempdir();
        let (d, tf) = photos(dir.path(), &times);
        let e = err(&import(&d, &tf, &dir.path().join("s")));
        assert!(e.len() < 500, "{} bytes: {}", e.len(), &e[..200]);
        nothing_written(dir.path());
    }
}

/// Photos named by the times file are read only inside the folder and only if they are
/// regular files: `../x`, `/dev/zero` and a FIFO (today `/dev/zero` reads until memory
/// runs out and a FIFO blocks) are refused with one line.
#[test]
fn import_reads_only_regular_files_inside_the_folder() {
    let dir = tempdir();
    let (d, tf) = photos(dir.path(), "p0.png 1/250\n");
    let fifo = d.join("fifo.png");
    let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid C string.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    for (name, want) in [
        ("../times.txt", "relative path inside"),
        ("/dev/zero", "relative path inside"),
        ("fifo.png", "not a regular file"),
    ] {
        std::fs::write(&tf, format!("p0.png 1/250\n{name} 1/100\n")).unwrap();
        let e = err(&import(&d, &tf, &dir.path().join("s")));
        assert!(e.contains(want), "{name}: {e}");
        assert!(!dir.path().join("s").exists());
    }
}

/// A photo in a format Glint does not read (GIF bytes, whatever its name) is refused as
/// such, naming the formats it reads, not as a corrupt file; a TIFF whose header is all
/// there is is refused as corrupt (TIFF is read since 2026-12-04). Each in one line, with
/// nothing written.
#[test]
fn a_gif_photo_is_refused_as_unsupported_and_a_broken_tiff_as_corrupt() {
    // A bracket of a good PNG and `name` holding `head` and 64 zero bytes: the error.
    let refused = |name: &str, head: &[u8]| {
        let dir = tempdir();
        let (d, tf) = photos(dir.path(), &format!("p0.png 1/250\n{name} 1/100\n"));
        let mut bytes = head.to_vec();
        bytes.extend_from_slice(&[0; 64]);
        std::fs::write(d.join(name), bytes).unwrap();
        let e = err(&import(&d, &tf, &dir.path().join("s")));
        assert!(e.contains(name), "{e}");
        assert_eq!(e.trim().lines().count(), 1, "{e}");
        nothing_written(dir.path());
        e
    };
    let e = refused("t.png", b"GIF89a");
    assert!(
        e.contains("Glint reads PNG, JPEG, TIFF and uncompressed DNG"),
        "{e}"
    );
    let e = refused("t.tif", b"II*\0\x08\0\0\0");
    assert!(e.contains("corrupt"), "{e}");
}
