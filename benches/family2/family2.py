#!/usr/bin/env python3
"""The second scene family: draw scenes from seeds, write each as a session in Glint's public
format (as a lab's own capture tool would), run Glint's stages on it and score the results
against the scene's truth.

    python3 benches/family2/family2.py make SEED OUT            one scene's session (+ truth)
    python3 benches/family2/family2.py run --seeds 1000-1099    the family through Glint
        [--glint target/release/glint] [--work DIR] [--size 640x480] [--lens] [--ward]
        [--out results.jsonl]
    python3 benches/family2/family2.py table results.jsonl      the accuracy table

Seeds: each set is fresh until a change is judged on it, then it is a tuning set. Tuning
sets so far: 1000-1099, 2000-2099, 4000-4052 (changes were found and fixed on them);
5000-5099, 6000-6099, 7000-7099, 8000-8099, 9000-9099, 10000-10099, 11000-11099,
12000-12099, 13000-13099, 14000-14099 and 15000-15099 were each held out for one round
(or one change) and are now looked at (docs/results/accuracy.md says which); 16000 and up
are fresh. Ward
materials (--ward): seeds 3000-3008 give the nine published materials in turn. Scenes are
drawn, never committed.

Needs numpy, scipy, opencv-python-headless and OpenEXR (pip). The EMoR response model comes from the
project's shared test data where present (../shared/data); without it a filmic curve family
of this file's own stands in, and the run says so.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scene import (  # noqa: E402
    GRID, MODELS, SQUARE, WARD_MATERIALS, Lens, Scene, draw_curve, load_emor,
    radiance_image, rot_look,
)

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
import cv2  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
I_LAMP = 1.0e6


# ----------------------------------------------------------------------------------------
# Drawing a scene.


def board_visible(lens, R, t, W, H, margin=0.03):
    """Whether the whole board (its outer squares) projects inside the image with a margin,
    in front of the camera, and the distortion stays monotone out to it."""
    nx, ny = GRID
    xs = np.linspace(-SQUARE, nx * SQUARE, 21)
    ys = np.linspace(-SQUARE, ny * SQUARE, 15)
    X, Y = np.meshgrid(xs, ys)
    P = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], -1)
    Xc = P @ R.T + t
    if np.any(Xc[:, 2] < 50):
        return False
    u, v = lens.project(Xc)
    mu, mv = margin * W, margin * H
    if not (np.all(u > mu) and np.all(u < W - 1 - mu) and np.all(v > mv) and np.all(v < H - 1 - mv)):
        return False
    # Monotone radial distortion out to the image's corners.
    r = np.linspace(0, 1.05 * math.hypot(W / lens.fx, H / lens.fy) / 2 + 0.3, 200)
    rd = r * (1 + lens.k[0] * r**2 + lens.k[1] * r**4 + lens.k[2] * r**6)
    return bool(np.all(np.diff(rd) > 0))


def draw(seed: int, width=640, height=480, ward=False, emor=None) -> Scene:
    rng = np.random.default_rng([0xFA2, seed])
    bits = int(rng.choice([8, 16]))
    adc_bits = int(rng.choice([10, 12])) if bits == 8 else int(rng.choice([12, 14]))
    bayer = bool(rng.random() < 0.5)
    if bits == 8:
        curves, kind, params = draw_curve(rng, emor)
    elif rng.random() < 0.6:
        curves, kind, params = None, "linear", []
    else:
        curves, kind, params = draw_curve(rng, emor)
    black_dn = int(rng.choice([0, 16, 64])) * (1 << (adc_bits - 10)) if kind == "linear" else 0
    k1 = float(rng.uniform(-0.35, 0.15))
    k2 = float(rng.uniform(-0.05, 0.12))
    k3 = float(rng.uniform(-0.05, 0.05)) if rng.random() < 0.3 else 0.0
    p = [float(rng.normal(0, 4e-4)), float(rng.normal(0, 4e-4))] if rng.random() < 0.3 else [0.0, 0.0]
    pp = np.clip(rng.normal(0, 0.02, 2), -0.06, 0.06) * max(width, height)
    # The tile: 60-110 mm, somewhere on the board's middle, 3-12 mm thick.
    sx, sy = rng.uniform(60, 110, 2)
    cx0, cy0 = 100 + rng.uniform(-20, 20), 62.5 + rng.uniform(-12, 12)
    outline = [[cx0 - sx / 2, cy0 - sy / 2], [cx0 + sx / 2, cy0 - sy / 2],
               [cx0 + sx / 2, cy0 + sy / 2], [cx0 - sx / 2, cy0 + sy / 2]]
    outline = [[round(a, 1), round(b, 1)] for a, b in outline]
    thick = round(float(rng.uniform(3, 12)), 2)
    # The camera and the lamp, redrawn until the board is in view.
    for _ in range(500):
        dist = rng.uniform(250, 900)
        polar = math.radians(rng.uniform(15, 60))
        az = math.radians(rng.uniform(-180, 180))
        centre = np.array([cx0, cy0, thick])
        cam = centre + dist * np.array([math.sin(polar) * math.cos(az), math.sin(polar) * math.sin(az), math.cos(polar)])
        target = np.array([100.0, 62.5, 0.0]) + np.append(rng.normal(0, 10, 2), 0.0)
        roll = rng.uniform(-15, 15)
        R = rot_look(cam, target, roll)
        t = -R @ cam
        # Focal length: the board fills 55-85% of the frame's width.
        fill = rng.uniform(0.55, 0.85)
        corners = np.array([[x, y, 0.0] for x in (-SQUARE, GRID[0] * SQUARE) for y in (-SQUARE, GRID[1] * SQUARE)])
        Xc = corners @ R.T + t
        span = float(np.max(Xc[:, 0] / Xc[:, 2]) - np.min(Xc[:, 0] / Xc[:, 2]))
        fx = fill * width / span
        lens = Lens(fx=fx, fy=fx, cx=(width - 1) / 2 + pp[0], cy=(height - 1) / 2 + pp[1], k=[k1, k2, k3], p=p)
        if not board_visible(lens, R, t, width, height):
            continue
        # The lamp in the mirror direction of the camera about a point on the tile's middle.
        P = np.array([cx0 + rng.uniform(-0.25, 0.25) * sx, cy0 + rng.uniform(-0.25, 0.25) * sy, thick])
        vdir = (cam - P) / np.linalg.norm(cam - P)
        ldir = np.array([-vdir[0], -vdir[1], vdir[2]])
        lamp = P + rng.uniform(200, 1200) * ldir
        if lamp[2] < 60:
            continue
        break
    else:
        raise RuntimeError(f"seed {seed}: no camera placement shows the board")
    # The tile.
    ward_p = None
    if ward:
        names = list(WARD_MATERIALS)
        name = names[seed % len(names)]
        rd, rs, alpha = WARD_MATERIALS[name]
        tint = rng.uniform(0.6, 1.0, 3)
        tint /= tint.max()
        kd = (rd / math.pi * tint).tolist()
        ks = [rs] * 3
        model, n = "ward", 0.0
        ward_p = {"material": name, "rho_d": rd, "rho_s": rs, "alpha": alpha}
    else:
        u = rng.random()
        model = "lambert" if u < 0.1 else MODELS[1 + int((u - 0.1) / 0.3)]
        n = float(math.exp(rng.uniform(math.log(5), math.log(1000))))
        base = rng.uniform(0.05, 0.7) / math.pi
        kd = (base * rng.uniform(0.4, 1.0, 3)).tolist()
        if rng.random() < 0.1:
            kd[int(rng.integers(3))] *= 0.02
        ratio = math.exp(rng.uniform(math.log(1.1), math.log(300)))
        cl = float(np.clip(ldir[2], 0, 1))
        lobe_max = 1.0 if model in ("phong", "blinn-phong") else (n + 2) / (2 * math.pi) * cl
        ks_g = (ratio - 1) * kd[1] * cl / lobe_max if model != "lambert" else 0.0
        if rng.random() < 0.15:
            ks = (ks_g * rng.uniform(0.5, 1.0, 3)).tolist()
        else:
            ks = (ks_g * rng.uniform(0.95, 1.05, 3)).tolist()
        if model == "lambert":
            ks = [0.0, 0.0, 0.0]
    full_well = float(rng.uniform(6000, 40000))
    qe = [float(rng.uniform(0.4, 0.8)), 1.0, float(rng.uniform(0.3, 0.7))]
    s = Scene(
        seed=seed, width=width, height=height, bits=bits, adc_bits=adc_bits, black_dn=black_dn,
        bayer=bayer, curve_kind=kind, curve_params=params,
        lens=dict(fx=lens.fx, fy=lens.fy, cx=lens.cx, cy=lens.cy, k=lens.k, p=lens.p),
        blur_px=float(rng.uniform(0.3, 0.8)), fill_factor=float(rng.uniform(0.5, 1.0)),
        camera_mm=cam.tolist(), target_mm=target.tolist(), roll_deg=float(roll), lamp_mm=lamp.tolist(),
        tile_outline=outline, tile_thickness=thick, model=model, kd=kd, ks=ks, n=n, ward=ward_p,
        qe=qe, full_well=full_well, read_e=float(rng.uniform(2, 12)),
        dark_e_per_s=float(rng.uniform(5, 100)), exposures_us=[], dark_exposures_us=[],
        grid_exposure_us=0, grid_lamp_on=bool(rng.random() < 0.5),
        room={"level": 0.0, "gx": float(rng.uniform(-0.3, 0.3)), "gy": float(rng.uniform(-0.3, 0.3)),
              "tint": (rng.uniform(0.8, 1.0, 3)).tolist()},
        board_margin_mm=float(rng.uniform(8, 30)),
        albedo={"dark": float(rng.uniform(0.03, 0.1)), "light": float(rng.uniform(0.7, 0.9)),
                "table": float(rng.uniform(0.15, 0.45)), "tint": (rng.uniform(0.85, 1.0, 3)).tolist()},
    )
    s.curves = curves
    return s


# ----------------------------------------------------------------------------------------
# The camera: electrons, noise, ADC, mosaic, tone curve.


def adc_max(s):
    return (1 << s.adc_bits) - 1


def electrons_per_unit(s, L_tile, tile_mask):
    """Scale so that a 1000 µs exposure takes the brightest tile pixel to 0.3-3 full wells:
    the lamp's power and the lens's aperture, unknown to Glint."""
    peak = float(np.max(L_tile[tile_mask] * np.array(s.qe)[None, :]))
    return s.full_well * s._scale_draw / (peak * 1000.0)


def sensor(s, L, t_us, k, rng):
    """One frame's output values (H x W x 3, integers) for radiance L at exposure t_us."""
    H, W = L.shape[:2]
    mean_e = L * np.array(s.qe)[None, None, :] * k * t_us + s.dark_e_per_s * t_us * 1e-6
    if s.bayer:
        plane = np.empty((H, W))
        plane[0::2, 0::2] = mean_e[0::2, 0::2, 0]
        plane[0::2, 1::2] = mean_e[0::2, 1::2, 1]
        plane[1::2, 0::2] = mean_e[1::2, 0::2, 1]
        plane[1::2, 1::2] = mean_e[1::2, 1::2, 2]
        mean_e = plane
    e = rng.poisson(np.clip(mean_e, 0, None)).astype(float) + rng.normal(0, s.read_e, mean_e.shape)
    e = np.clip(e, 0, s.full_well)
    amax = adc_max(s)
    gain = s.full_well / (amax - s.black_dn)  # electrons per DN
    dn = np.clip(np.round(e / gain + s.black_dn), 0, amax).astype(np.uint16)
    if s.bayer:
        # The camera's own demosaic, bilinear, on the linear ADC values (OpenCV's RG pattern
        # names the second row's second pixel; our top-left pixel is red).
        dn = cv2.cvtColor(dn, cv2.COLOR_BayerBG2RGB)
    dn = dn.astype(float)
    out_max = (1 << s.bits) - 1
    if s.curve_kind == "linear":
        return np.clip(np.round(dn * (out_max + 1) / (amax + 1)), 0, out_max).astype(np.uint16)
    x = np.clip((dn - s.black_dn) / (amax - s.black_dn), 0, 1)
    grid = np.linspace(0, 1, 1024)
    y = np.empty_like(x)
    for c in range(3):
        y[..., c] = np.interp(x[..., c], grid, s.curves[c])
    return np.clip(np.round(y * out_max), 0, out_max).astype(np.uint16)


def operator_bracket(s, L_tile, tile_mask, k, rng):
    """The exposures an operator picks from a test shot: the shortest puts the brightest
    tile pixel at 60-97% of full scale, then steps of 1 or 2 stops until the darkest tile
    pixel (5th percentile of its dimmest channel) reaches 20-50% of full scale, 3 to 13
    exposures, at most 12 stops."""
    e = L_tile[tile_mask] * np.array(s.qe)[None, :] * k  # electrons per µs
    brightest = float(e.max())
    darkest = float(np.percentile(e.min(axis=1), 5))
    top = rng.uniform(0.6, 0.97)
    low = rng.uniform(0.2, 0.5)
    step = int(rng.choice([1, 2]))
    t0 = max(20.0, top * s.full_well / brightest)
    ts = [t0]
    while darkest * ts[-1] < low * s.full_well and len(ts) < 13 and math.log2(ts[-1] * 2**step / t0) <= 12:
        ts.append(ts[-1] * 2**step)
    while len(ts) < 3:
        ts.append(ts[-1] * 2**step)
    return [int(round(t)) for t in ts], step


# ----------------------------------------------------------------------------------------
# Writing the session.


def write_png(path, img, bits):
    if img.ndim == 3:
        img = img[..., ::-1]  # OpenCV writes BGR
    img = img.astype(np.uint8 if bits == 8 else np.uint16)
    if not cv2.imwrite(str(path), img):
        raise RuntimeError(f"cannot write {path}")


def rig_of(s: Scene):
    return {
        "rig": {"name": f"family2-{s.seed}", "description": "a scene of the second family (benches/family2)"},
        "camera": {"backend": "external", "width": s.width, "height": s.height, "bit_depth": s.bits},
        "lamp": {"backend": "external"},
        "geometry": {
            "lamp_position_mm": [round(x, 3) for x in s.lamp_mm],
            "tile_thickness_mm": s.tile_thickness,
            "tile_outline_mm": s.tile_outline,
            "grid_inner_corners": list(GRID),
            "grid_square_mm": SQUARE,
        },
        "bracket": {
            "exposures_us": s.exposures_us,
            "frames_per_exposure": 1,
            "dark_frames_per_exposure": 1 if s.dark_exposures_us else 0,
            "grid_exposure_us": s.grid_exposure_us,
            "grid_frames": 1,
        },
    }


def toml_of(rig):
    lines = []
    for sec, kv in rig.items():
        lines.append(f"[{sec}]")
        for k, v in kv.items():
            lines.append(f"{k} = {json.dumps(v)}")
        lines.append("")
    return "\n".join(lines)


def make(seed: int, out: Path, width=640, height=480, ward=False, emor=None, lens_poses=0):
    """Write scene `seed` as a session in `out` (which must not exist) and its truth beside
    it (`out.truth/`: scene.json, radiance.npy, tile_mask.npy, lens photos)."""
    s = draw(seed, width, height, ward, emor)
    rng = np.random.default_rng([0xFA2, seed, 1])
    L_tile, kind = radiance_image(s, "tile")
    tile_mask = kind == 1
    s._scale_draw = float(rng.uniform(0.3, 3.0))
    k = electrons_per_unit(s, L_tile, tile_mask)
    s.exposures_us, step = operator_bracket(s, L_tile, tile_mask, k, rng)
    mode = rng.choice(["none", "longest", "both"], p=[0.3, 0.4, 0.3])
    s.dark_exposures_us = {"none": [], "longest": [s.exposures_us[-1]],
                           "both": sorted({s.exposures_us[0], s.exposures_us[-1]})}[mode]
    # The grid photo: room light comparable to the lamp's light on the board.
    lamp_E = I_LAMP / float(np.sum((np.array(s.lamp_mm) - np.array([100, 62.5, 0])) ** 2)) * float(
        np.clip((np.array(s.lamp_mm)[2]) / np.linalg.norm(np.array(s.lamp_mm) - np.array([100, 62.5, 0])), 0, 1))
    s.room["level"] = lamp_E * float(rng.uniform(0.3, 2.0))
    L_grid, _ = radiance_image(s, "grid")
    light = float(np.percentile((L_grid * np.array(s.qe)).max(-1), 99)) * k
    s.grid_exposure_us = int(round(max(20.0, rng.uniform(0.5, 0.85) * s.full_well / light)))
    s.operator_note = f"{step}-stop steps, darks: {mode}"

    out = Path(out)
    truth = Path(str(out) + ".truth")
    (out / "frames").mkdir(parents=True)
    truth.mkdir(parents=True, exist_ok=True)
    frames = []
    stamp = 1_790_000_000.0 + seed * 1000

    def add(kind_, img, t_us, lamp_on):
        i = len(frames)
        name = f"frames/{i:04d}-{kind_}-{t_us}us.png"
        write_png(out / name, img, s.bits)
        sha = hashlib.sha256((out / name).read_bytes()).hexdigest()
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(stamp + i)) + ".000000Z"
        frames.append({
            "index": i, "file": name, "kind": kind_, "exposure_requested_us": t_us,
            "exposure_reported_us": t_us, "exposure_verified_by": "metadata", "timestamp": ts,
            "device_timestamp_us": None, "sequence": i, "lamp": {"on": lamp_on, "level": 1000 if lamp_on else 0},
            "width": s.width, "height": s.height, "bit_depth": s.bits, "sha256": sha,
        })

    zero = np.zeros_like(L_tile)
    for t in s.exposures_us:
        add("tile", sensor(s, L_tile, t, k, rng), t, True)
    for t in s.dark_exposures_us:
        add("dark", sensor(s, zero, t, k, rng), t, False)
    add("grid", sensor(s, L_grid, s.grid_exposure_us, k, rng), s.grid_exposure_us, s.grid_lamp_on)
    rig = rig_of(s)
    (out / "rig.toml").write_text(toml_of(rig))
    created = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(stamp))
    manifest = {
        "format": "glint-session", "format_version": 1, "state": "complete", "failure": None,
        "software": {"name": "family2", "version": "1"},
        "created": created, "finished": created, "rig_file": "rig.toml", "rig": rig,
        "camera": {"model": f"family2 camera {seed}", "width": s.width, "height": s.height, "bit_depth": s.bits},
        "lamp_identity": "family2 lamp", "lamp_off_confirmed": True, "plan": {"steps": []}, "frames": frames,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    # The truth, outside the session.
    np.save(truth / "radiance.npy", (L_tile * k).astype(np.float32))  # electrons per µs, per channel before qe
    np.save(truth / "tile_mask.npy", tile_mask)
    d = asdict(s)
    d.pop("curves", None)
    d["truth"] = s.truth()
    d["electrons_per_unit"] = k
    (truth / "scene.json").write_text(json.dumps(d, indent=1))
    # A lens calibration's photos: the board alone in tilted poses, room light.
    if lens_poses:
        lens_photos(s, truth, k, rng, lens_poses)
    return s


def lens_photos(s, truth, k, rng, poses):
    R0, t0 = s.R_t()
    tilts = [(0, 0), (25, 0), (-25, 0), (0, 25), (0, -25), (20, 20), (-20, -20), (20, -20), (-20, 20)][:poses]
    files = []
    for i, (ax, ay) in enumerate(tilts):
        a, b = math.radians(ax), math.radians(ay)
        Bx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        By = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        B = Bx @ By
        c = np.array([100.0, 62.5, 0.0])
        bvec = c - B @ c + np.array([0, 0, 20.0])  # rotate about the board's centre, lifted 20 mm
        R = R0 @ B
        t = R0 @ bvec + t0
        L, _ = radiance_image(s, "grid", ss=2, Rt=(R, t))
        img = sensor(s, L, s.grid_exposure_us, k, rng)
        f = truth / f"lens-{i:02d}.png"
        write_png(f, img, s.bits)
        files.append(str(f))
    return files


# ----------------------------------------------------------------------------------------
# Running Glint and scoring.


def glint(bin_, *args, json_out=True):
    cmd = [bin_, *args] + (["--json"] if json_out else [])
    p = subprocess.run(cmd, capture_output=True, text=True)
    return p.returncode, p.stdout, p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ""


def hdr_no_radiance(session: Path, truth: Path):
    """The share of the tile's pixels (edge left out) with no radiance in some channel: the
    median error above is taken over the pixels that have one, so a channel gone dark
    (a valid range that ends below the tile's readings) must be counted apart."""
    import OpenEXR
    from scipy.ndimage import binary_erosion

    with OpenEXR.File(str(session / "hdr/radiance.exr")) as f:
        ch = f.channels()
        rad = (ch["RGB"].pixels if "RGB" in ch else np.stack([ch[k].pixels for k in "RGB"], -1)).astype(float)
    mask = binary_erosion(np.load(truth / "tile_mask.npy"), iterations=2)
    return float((~np.isfinite(rad[mask])).any(axis=-1).mean())


def hdr_error(session: Path, truth: Path):
    """Median relative error of the radiance on the tile, one scale per channel."""
    import OpenEXR

    with OpenEXR.File(str(session / "hdr/radiance.exr")) as f:
        ch = f.channels()
        rad = (ch["RGB"].pixels if "RGB" in ch else np.stack([ch[k].pixels for k in "RGB"], -1)).astype(float)
    true = np.load(truth / "radiance.npy").astype(float)
    mask = np.load(truth / "tile_mask.npy")
    # Leave out the tile's edge (2 px), where the photo mixes tile and board.
    from scipy.ndimage import binary_erosion
    mask = binary_erosion(mask, iterations=2)
    errs = []
    for c in range(3):
        a, b = rad[..., c][mask], true[..., c][mask]
        ok = np.isfinite(a) & (b > 0)
        if ok.sum() < 10:
            continue
        scale = np.median(a[ok] / b[ok])
        errs.append(np.abs(a[ok] / (scale * b[ok]) - 1))
    if not errs:
        return None, None
    return float(np.median(np.concatenate(errs))), float(max(np.median(e) for e in errs))


def score_fit(fit: dict, truth: dict):
    """Per interval of n and ks/kd of the true model's candidate: value, sd, ci95, truth."""
    samp = fit.get("sampling") or {}
    out = {"chosen": fit.get("chosen"), "intervals": [],
           "mosaic": samp.get("mosaic"), "mosaic_contrast": samp.get("mosaic_contrast")}
    if truth["model"] == "ward":
        ch = next((c for c in fit.get("candidates", []) if c.get("model") == fit.get("chosen")), {})
        out["reduced_chi2"] = ch.get("reduced_chi2")
        out["held_out"] = ch.get("held_out")
        out["verdict"] = fit.get("verdict")
        out["trade_off"] = {c.get("model"): c.get("trade_off") for c in fit.get("candidates", []) if c.get("trade_off")}
        out["alpha"] = next((c.get("alpha") for c in fit.get("candidates", []) if c.get("model") == "ggx"), None)
        return out
    cand = next((c for c in fit.get("candidates", []) if c.get("model") == truth["model"]), None)
    if cand is None:
        return out
    out["n_variance_share"] = cand.get("n_variance_share")
    out["reduced_chi2"] = cand.get("reduced_chi2")
    if truth["model"] != "lambert":
        nn = cand.get("n") or {}
        out["intervals"].append({"what": "n", "truth": truth["n"], **{k: nn.get(k) for k in ("value", "sd", "ci95")}})
        for c, (r, e) in enumerate(zip(truth["ks_over_kd"], cand.get("ks_over_kd") or [])):
            if r is None or e is None:
                continue
            out["intervals"].append({"what": f"ks/kd {'RGB'[c]}", "truth": r, **{k: e.get(k) for k in ("value", "sd", "ci95")}})
    return out


def covers(iv):
    lo, hi = (iv.get("ci95") or [None, None])
    t = iv["truth"]
    return (lo is None or lo <= t) and (hi is None or t <= hi)


def run_scene(seed, args, emor):
    work = Path(args.work)
    sess = work / f"scene-{seed}"
    truth = Path(str(sess) + ".truth")
    for p in (sess, truth):
        shutil.rmtree(p, ignore_errors=True)
    t0 = time.time()
    w, h = map(int, args.size.split("x"))
    s = make(seed, sess, w, h, ward=args.ward, emor=emor, lens_poses=9 if args.lens else 0)
    row = {"seed": seed, "make_s": round(time.time() - t0, 1), "scene": {
        "bits": s.bits, "adc_bits": s.adc_bits, "curve": s.curve_kind, "bayer": s.bayer,
        "model": s.model, "n": s.n, "exposures": len(s.exposures_us),
        "stops": round(math.log2(s.exposures_us[-1] / s.exposures_us[0]), 1),
        "darks": len(s.dark_exposures_us), "grid_lamp": s.grid_lamp_on, "k": s.lens["k"],
        "camera_mm": s.camera_mm, "lamp_mm": s.lamp_mm, "ward": s.ward, "note": s.operator_note}}
    rc, out, err = glint(args.glint, "hdr", str(sess))
    if rc != 0:
        row["error"] = f"hdr: {err}"
        return row
    row["hdr_error"], row["hdr_error_worst_channel"] = hdr_error(sess, truth)
    row["hdr_no_radiance"] = hdr_no_radiance(sess, truth)
    variants = [("one_photo", [])]
    if args.lens:
        lensdir = truth / "lens"
        photos = sorted(str(p) for p in truth.glob("lens-*.png"))
        rc, out, err = glint(args.glint, "calibrate", "--images", *photos, "--grid", "9x6",
                             "--square-mm", "25", "--out", str(lensdir), "--response",
                             str(sess / "hdr/response.json"))
        if rc == 0:
            variants.append(("lens", ["--intrinsics", str(lensdir / "camera.json")]))
        else:
            row["lens_error"] = err
    for name, extra in variants:
        rc, out, err = glint(args.glint, "calibrate", str(sess), *extra)
        if rc != 0:
            row[name] = {"error": f"calibrate: {err}"}
            continue
        cam = json.loads((sess / "calib/camera.json").read_text())
        view = cam["calibration"]["views"][0]
        centre = np.array(view["camera_centre"])
        rc, out, err = glint(args.glint, "fit", str(sess))
        if rc != 0:
            row[name] = {"error": f"fit: {err}"}
            continue
        fit = json.loads((sess / "fit/fit.json").read_text())
        shutil.copy(sess / "fit/fit.json", truth / f"fit-{name}.json")
        shutil.copy(sess / "calib/camera.json", truth / f"camera-{name}.json")
        r = score_fit(fit, s.truth())
        r["camera_centre_error_mm"] = float(np.linalg.norm(centre - np.array(s.camera_mm)))
        if fit.get("camera_refined"):
            r["refined_centre_error_mm"] = float(np.linalg.norm(np.array(fit["camera_refined"]["centre_mm"]) - np.array(s.camera_mm)))
        r["warnings"] = fit.get("warnings", [])
        if args.validate:
            rc, out, err = glint(args.glint, "validate", str(sess))
            if rc == 0:
                v = json.loads(out)
                r["validation"] = {m.get("model"): {"rmse": (m.get("pixels") or {}).get("rmse"),
                                                    "noise_rmse": (m.get("pixels") or {}).get("noise_rmse")}
                                   for m in v.get("models", [])}
        row[name] = r
    if not args.keep:
        shutil.rmtree(sess, ignore_errors=True)
        shutil.rmtree(truth, ignore_errors=True)
    row["seconds"] = round(time.time() - t0, 1)
    return row


def seeds_of(spec):
    out = []
    for part in spec.split(","):
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def table(rows):
    """The accuracy figures over rows (as run() writes them)."""
    lines = []
    for variant in ("one_photo", "lens"):
        ivs, n_ok, n_all, chosen, centre = [], 0, 0, [0, 0], []
        for r in rows:
            v = r.get(variant)
            if not v or "error" in v:
                continue
            if r["scene"]["model"] != "ward":
                chosen[1] += 1
                chosen[0] += v.get("chosen") == r["scene"]["model"]
            centre.append(v.get("camera_centre_error_mm", float("nan")))
            for iv in v["intervals"]:
                ivs.append(iv)
                if iv["what"] == "n" and iv["truth"] >= 40 and iv.get("value"):
                    n_all += 1
                    n_ok += abs(iv["value"] / iv["truth"] - 1) <= (0.05 if variant == "one_photo" else 0.02)
        if not ivs and not chosen[1]:
            continue
        cov = sum(covers(iv) for iv in ivs)
        z = [abs(iv["value"] - iv["truth"]) / iv["sd"] for iv in ivs if iv.get("sd") and iv.get("value") is not None]
        within3 = sum(x <= 3 for x in z)
        # The rms of errors in sds over those within 10 sd (a failed fit's thousands of sds
        # would hide the rest; the count beyond 3 sd names them).
        zs = [x for x in z if x <= 10]
        rms = math.sqrt(sum(x * x for x in zs) / len(zs)) if zs else float("nan")
        n_ivs = [iv for iv in ivs if iv["what"] == "n"]
        n_cov = sum(covers(iv) for iv in n_ivs)
        beyond = sorted({r["seed"] for r in rows for iv in ((r.get(variant) or {}).get("intervals") or [])
                         if iv.get("sd") and iv.get("value") is not None and abs(iv["value"] - iv["truth"]) / iv["sd"] > 3})
        lines.append(f"{variant}: true model chosen {chosen[0]} of {chosen[1]}; intervals covering {cov} of {len(ivs)}"
                     f" ({100 * cov / max(1, len(ivs)):.1f}%); |error| <= 3 sd {within3} of {len(z)}; rms {rms:.2f} sd;"
                     f" n within {'5' if variant == 'one_photo' else '2'}% where n >= 40: {n_ok} of {n_all};"
                     f" camera centre median {np.nanmedian(centre) if centre else float('nan'):.2f} mm;"
                     f" n's intervals covering {n_cov} of {len(n_ivs)}; beyond 3 sd in scenes {beyond}")
    # By camera: a Bayer mosaic (demosaicked by the camera) or every channel at every pixel.
    for variant in ("one_photo", "lens"):
        parts = []
        for bayer in (True, False):
            ivs = [iv for r in rows if r["scene"].get("bayer") == bayer
                   for iv in ((r.get(variant) or {}).get("intervals") or []) if iv.get("value") is not None]
            z = [abs(iv["value"] - iv["truth"]) / iv["sd"] for iv in ivs if iv.get("sd")]
            if ivs:
                parts.append(f"{'Bayer' if bayer else 'full'}: covering {sum(covers(iv) for iv in ivs)} of {len(ivs)},"
                             f" within 3 sd {sum(x <= 3 for x in z)} of {len(z)}")
        if parts:
            lines.append(f"{variant} by camera: " + "; ".join(parts))
    # The fit's reading of the colour filter layout (rows written since it records it).
    found = [(r["scene"].get("bayer"), r["one_photo"].get("mosaic"), r["one_photo"].get("mosaic_contrast"))
             for r in rows if isinstance(r.get("one_photo"), dict) and "mosaic_contrast" in r["one_photo"]]
    if found:
        def span(xs):
            xs = [x for x in xs if x is not None]
            return f"{min(xs):.2f}..{max(xs):.2f}" if xs else "-"
        b = [f for f in found if f[0]]
        o = [f for f in found if not f[0]]
        lines.append(f"mosaic read by the fit: {sum(f[1] is not None for f in b)} of {len(b)} Bayer scenes (contrast {span([f[2] for f in b])}),"
                     f" {sum(f[1] is not None for f in o)} of {len(o)} others (contrast {span([f[2] for f in o])})")
    hdr = [r["hdr_error"] for r in rows if r.get("hdr_error") is not None]
    if hdr:
        worst = max(rows, key=lambda r: r.get("hdr_error") or 0)
        lines.append(f"HDR median error: worst {100 * max(hdr):.2f}% (seed {worst['seed']}), median {100 * float(np.median(hdr)):.2f}%,"
                     f" over 1%: {sum(h > 0.01 for h in hdr)} of {len(hdr)}")
        ch = [r["hdr_error_worst_channel"] for r in rows if r.get("hdr_error_worst_channel") is not None]
        if ch:
            lines.append(f"HDR median error of the worst channel: worst {100 * max(ch):.2f}%, over 1%: {sum(h > 0.01 for h in ch)} of {len(ch)}")
        nr = [(r["hdr_no_radiance"], r["seed"]) for r in rows if r.get("hdr_no_radiance") is not None]
        if nr:
            lines.append(f"tile pixels without radiance in a channel: over 1% of the tile in {sum(x > 0.01 for x, _ in nr)} of {len(nr)}"
                         f" scenes {[s for x, s in nr if x > 0.01]}")
    errs = [r for r in rows if "error" in r or any(isinstance(r.get(v), dict) and "error" in r[v] for v in ("one_photo", "lens"))]
    if errs:
        lines.append(f"errors: {len(errs)} scenes: " + "; ".join(
            f"{r['seed']}: {r.get('error') or (r.get('one_photo') or {}).get('error') or (r.get('lens') or {}).get('error')}" for r in errs[:8]))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make", help="write one scene's session")
    m.add_argument("seed", type=int)
    m.add_argument("out")
    m.add_argument("--size", default="640x480")
    m.add_argument("--ward", action="store_true")
    m.add_argument("--lens", action="store_true")
    r = sub.add_parser("run", help="make and run scenes through Glint, write one JSON line per scene")
    r.add_argument("--seeds", default="1000-1009")
    r.add_argument("--glint", default=str(ROOT / "target/release/glint"))
    r.add_argument("--work", default="/tmp/family2")
    r.add_argument("--size", default="640x480")
    r.add_argument("--out", default=None)
    r.add_argument("--lens", action="store_true", help="also calibrate a lens from 9 tilted board photos and fit holding it")
    r.add_argument("--ward", action="store_true", help="the Ward materials instead of the candidates")
    r.add_argument("--validate", action="store_true")
    r.add_argument("--keep", action="store_true", help="keep the sessions")
    r.add_argument("--jobs", type=int, default=2, help="scenes at once")
    t = sub.add_parser("table", help="the figures of a results file")
    t.add_argument("results")
    a = ap.parse_args()
    emor = load_emor()
    if a.cmd == "make":
        w, h = map(int, a.size.split("x"))
        s = make(a.seed, Path(a.out), w, h, ward=a.ward, emor=emor, lens_poses=9 if a.lens else 0)
        print(json.dumps({"seed": s.seed, "model": s.model, "n": s.n, "exposures_us": s.exposures_us,
                          "bits": s.bits, "curve": s.curve_kind, "bayer": s.bayer}))
    elif a.cmd == "run":
        if emor is None:
            print("note: the EMoR response model (../shared/data) is absent; a filmic curve family stands in", file=sys.stderr)
        Path(a.work).mkdir(parents=True, exist_ok=True)
        out = open(a.out, "a") if a.out else None
        rows = []
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(a.jobs) as pool:
            futures = [pool.submit(run_scene, seed, a, emor) for seed in seeds_of(a.seeds)]
            for fut in futures:
                row = fut.result()
                rows.append(row)
                line = json.dumps(row)
                if out:
                    out.write(line + "\n")
                    out.flush()
                brief = {k: row.get(k) for k in ("seed", "hdr_error", "error", "seconds")}
                for v in ("one_photo", "lens"):
                    if v in row:
                        x = row[v]
                        brief[v] = x.get("error") or [(i["what"], round((i["value"] - i["truth"]) / i["sd"], 2) if i.get("sd") else None) for i in x["intervals"]]
                print(json.dumps(brief), file=sys.stderr)
        print(table(rows))
    else:
        rows = [json.loads(x) for x in open(a.results) if x.strip()]
        print(table(rows))


if __name__ == "__main__":
    main()
