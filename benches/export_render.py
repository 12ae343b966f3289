#!/usr/bin/env python3
"""Render a session's exported Mitsuba material in the rig's own view and compare with the photo.

    python3 benches/export_render.py SESSION [--out PNG] [--spp N] [--model M] [--margin PX]

Builds a Mitsuba 3 scene (variant scalar_rgb) from the session itself:
- camera: SESSION/calib/camera.json's pose (X_cam = R(rvec) X_grid + t, mm) and intrinsics
  (fx as the horizontal field of view, cx, cy as principal_point_offset_x/y); the film is the
  session's image size, cropped to the tile (plus the reference standard, if the rig has one)
  to save time. Mitsuba's perspective camera has no lens distortion: the pinhole render is
  resampled afterwards onto the calibrated distorted pixel grid (k1, k2 of camera.json), and
  the comparison is printed both ways.
- lamp: a point light at rig.toml's [geometry] lamp_position_mm, intensity = fit.json's
  reference factor F_c per channel, so the render is in radiance.exr's units
  (radiance = F_c f_r (n.l) / D^2, D in mm; Mitsuba's point light gives I f_r cos / D^2).
- tile: its outline polygon (rig.toml tile_outline_mm) at z = tile_thickness_mm, as a mesh
  with the exported <bsdf> (SESSION/export/<model>.xml, `glint export SESSION --to mitsuba`).
- reference standard (if [reference] is in rig.toml): its top face, a diffuse of the
  certificate's reflectance; its render/photo ratio checks the lamp's units alone.

Compares render/photo - 1 over the tile's pixels (the tile hit in both the pinhole and the
distorted model, eroded by --erode pixels), per channel: median and rms, and the ratio at the
highlight. Checks the conventions first: the tile's corners projected with the pinhole model
must fall on the rendered tile's edges, and with the distorted model on the photo's.
Writes a side-by-side PNG (photo left, render right, one tone map) to --out (default
docs/export_render.png beside this script's repository).

Exit 0 on success (or SKIP when mitsuba is absent), 1 on a failed check, 2 on bad usage.
"""

import argparse
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time

import numpy as np

try:
    import tomllib
except ImportError:  # Python < 3.11
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def fail(msg):
    print(f"FAIL: {msg}", flush=True)
    sys.exit(1)


def rodrigues(rvec):
    r = np.asarray(rvec, float)
    th = np.linalg.norm(r)
    if th < 1e-15:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


class Camera:
    """The calibrated camera: OpenCV conventions, pixel (0, 0) the centre of the top-left pixel."""

    def __init__(self, cal_json):
        c = cal_json["calibration"]
        it = c["intrinsics"]
        self.w, self.h = int(c["width"]), int(c["height"])
        self.fx, self.fy, self.cx, self.cy = it["fx"], it["fy"], it["cx"], it["cy"]
        rad = list(it.get("radial") or [])
        self.k = (rad + [0.0, 0.0, 0.0])[:3]
        if it.get("tangential"):
            print(f"  note: tangential distortion {it['tangential']} ignored")
        pose = c["views"][0]["pose"]
        self.R = rodrigues(pose["rvec"])
        self.t = np.asarray(pose["t"], float)
        self.C = -self.R.T @ self.t
        if "rotations" in cal_json:
            dR = np.abs(np.asarray(cal_json["rotations"][0]) - self.R).max()
            if dR > 1e-6:
                fail(f"Rodrigues of rvec differs from camera.json's rotation matrix by {dR:.3g}")

    def _dist(self, r2):
        k1, k2, k3 = self.k
        return 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3

    def project(self, X, distort):
        Xc = (self.R @ np.asarray(X, float).T).T + self.t
        x, y = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
        if distort:
            d = self._dist(x * x + y * y)
            x, y = x * d, y * d
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], 1)

    def undistort_normalized(self, xd, yd):
        x, y = xd.copy(), yd.copy()
        for _ in range(30):
            d = self._dist(x * x + y * y)
            x, y = xd / d, yd / d
        return x, y

    def rays(self, u, v, distort):
        """World ray directions through pixels (u, v) (arrays)."""
        x, y = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        if distort:
            x, y = self.undistort_normalized(x, y)
        d = np.stack([x, y, np.ones_like(x)], -1)
        return d @ self.R  # R^T d, row-wise


def point_in_polygon(px, py, poly):
    inside = np.zeros(px.shape, bool)
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        crosses = (y1 > py) != (y2 > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = x1 + (py - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (px < xint)
    return inside


def plane_mask(cam, poly, z, u, v, distort):
    """Pixels (u, v) whose ray (from the camera centre) hits polygon `poly` at height z."""
    d = cam.rays(u, v, distort)
    s = (z - cam.C[2]) / d[..., 2]
    X = cam.C[0] + s * d[..., 0]
    Y = cam.C[1] + s * d[..., 1]
    return point_in_polygon(X, Y, poly) & (s > 0)


def erode(mask, r):
    out = mask.copy()
    H, W = mask.shape
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            sh = np.zeros_like(mask)
            sh[max(0, dy):H + min(0, dy), max(0, dx):W + min(0, dx)] = \
                mask[max(0, -dy):H + min(0, -dy), max(0, -dx):W + min(0, -dx)]
            out &= sh
    return out


def box_mean(img, r):
    """Mean over a (2r+1)^2 window (edges: zero-padded sums divided by the full window)."""
    p = np.pad(img, ((r + 1, r), (r + 1, r)) + ((0, 0),) * (img.ndim - 2))
    c = p.cumsum(0).cumsum(1)
    n = 2 * r + 1
    s = c[n:, n:] - c[:-n, n:] - c[n:, :-n] + c[:-n, :-n]
    return s / (n * n)


def bilinear(img, u, v):
    """Sample img (H, W, C) at continuous pixel coords (u, v) (pixel centres at integers)."""
    H, W = img.shape[:2]
    u = np.clip(u, 0, W - 1.000001)
    v = np.clip(v, 0, H - 1.000001)
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = (u - u0)[..., None], (v - v0)[..., None]
    return ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u0 + 1]
            + (1 - fu) * fv * img[v0 + 1, u0] + fu * fv * img[v0 + 1, u0 + 1])


def write_obj(path, poly, z):
    poly = [tuple(p) for p in poly]
    area = sum(x1 * y2 - x2 * y1 for (x1, y1), (x2, y2) in zip(poly, poly[1:] + poly[:1])) / 2
    if area < 0:  # make it counter-clockwise seen from +z, so the normal points up
        poly = poly[::-1]
    with open(path, "w") as f:
        for x, y in poly:
            f.write(f"v {x!r} {y!r} {z!r}\n")
        for i in range(1, len(poly) - 1):  # a fan: the outline must be convex
            f.write(f"f 1 {i + 1} {i + 2}\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session")
    ap.add_argument("--out", default=os.path.join(REPO, "docs", "export_render.png"))
    ap.add_argument("--model", default=None, help="the exported model (default: fit.json's chosen)")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--margin", type=int, default=40, help="pixels around the tile in the PNG")
    ap.add_argument("--erode", type=int, default=4, help="pixels eroded from the tile mask")
    a = ap.parse_args()

    try:
        import mitsuba as mi
    except ImportError:
        print("SKIP: the `mitsuba` Python package is absent (pip install mitsuba)")
        sys.exit(0)
    mi.set_variant("scalar_rgb")
    from PIL import Image, ImageDraw

    if tomllib is None:
        fail("no TOML reader (Python >= 3.11's tomllib, or pip install tomli)")
    S = a.session
    rig = tomllib.load(open(os.path.join(S, "rig.toml"), "rb"))
    cal = json.load(open(os.path.join(S, "calib", "camera.json")))
    fit = json.load(open(os.path.join(S, "fit", "fit.json")))
    geo = rig["geometry"]
    lamp = np.asarray(geo["lamp_position_mm"], float)
    z_tile = float(geo["tile_thickness_mm"])
    poly = [tuple(map(float, p)) for p in geo["tile_outline_mm"]]
    ref = rig.get("reference")

    if fit.get("units") != "absolute" or "reference" not in fit:
        fail(f"fit.json's units are {fit.get('units')!r}: the lamp's factor F_c is known only for an "
             "absolute session (a reference standard in the rig)")
    F = [float(f["value"]) for f in fit["reference"]["factor"]]
    model = a.model or fit.get("chosen")
    if isinstance(model, dict):
        model = model.get("model") or model.get("name")
    xml_path = os.path.join(S, "export", f"{model}.xml")
    if not os.path.exists(xml_path):
        fail(f"{xml_path} is absent: run `glint export {S} --to mitsuba` first")
    bsdf_xml = "\n".join(l for l in open(xml_path).read().splitlines() if not l.lstrip().startswith("<!--"))

    cam = Camera(cal)
    W, H = cam.w, cam.h
    photo = np.array(mi.Bitmap(os.path.join(S, "hdr", "radiance.exr")), dtype=np.float64)[..., :3]
    if photo.shape[:2] != (H, W):
        fail(f"radiance.exr is {photo.shape[1]}x{photo.shape[0]}, the calibration {W}x{H}")
    print(f"session {S}: {W}x{H}, model {model} ({xml_path})")
    print(f"  camera: centre {np.round(cam.C, 2).tolist()} mm, fx {cam.fx:.2f} fy {cam.fy:.2f}, "
          f"cx {cam.cx:.2f} cy {cam.cy:.2f}, radial k {cam.k}")
    print(f"  lamp {lamp.tolist()} mm, intensity F_c = {[f'{f:.6g}' for f in F]}; tile z = {z_tile} mm, outline {poly}")
    if abs(cam.fx - cam.fy) > 1e-6 * cam.fx:
        print(f"  note: fx != fy ({cam.fx} vs {cam.fy}); Mitsuba's pixels are square: fx is used")

    # --- the crop: the tile's (and the reference's) pixels, plus the margin ---------------
    corners3 = np.array([[x, y, z_tile] for x, y in poly])
    boxes = [corners3]
    ref_poly = None
    if ref is not None:
        ref_poly = [tuple(map(float, p)) for p in ref["outline_mm"]]
        z_ref = float(ref["thickness_mm"])
        boxes.append(np.array([[x, y, z_ref] for x, y in ref_poly]))
    allpx = np.concatenate([np.concatenate([cam.project(b, False), cam.project(b, True)]) for b in boxes])
    m = a.margin + 4
    x0 = max(0, int(math.floor(allpx[:, 0].min())) - m)
    y0 = max(0, int(math.floor(allpx[:, 1].min())) - m)
    x1 = min(W, int(math.ceil(allpx[:, 0].max())) + m + 1)
    y1 = min(H, int(math.ceil(allpx[:, 1].max())) + m + 1)
    cw, ch = x1 - x0, y1 - y0

    # --- the Mitsuba scene -------------------------------------------------------------------
    # Mitsuba's camera frame: +z forward, +y up, +x left; OpenCV's: +z forward, +y down, +x
    # right. to_world = [R^T | C] diag(-1, -1, 1).
    M = np.eye(4)
    M[:3, :3] = cam.R.T @ np.diag([-1.0, -1.0, 1.0])
    M[:3, 3] = cam.C
    fov_x = math.degrees(2 * math.atan(W / (2 * cam.fx)))
    # Mitsuba's film coordinates are continuous, the pixel (0, 0) covering [0, 1)^2: the
    # OpenCV principal point cx sits at cx + 0.5. principal_point_offset is in units of the
    # film's size and moves the sample position: the optical axis lands at 0.5 - offset.
    ppx = 0.5 - (cam.cx + 0.5) / W
    ppy = 0.5 - (cam.cy + 0.5) / H
    tmp = tempfile.mkdtemp(prefix="glint-export-render-")
    tile_obj = os.path.join(tmp, "tile.obj")
    write_obj(tile_obj, poly, z_tile)
    mat = " ".join(repr(float(v)) for v in M.flatten())
    ref_xml = ""
    if ref_poly is not None:
        ref_obj = os.path.join(tmp, "reference.obj")
        write_obj(ref_obj, ref_poly, z_ref)
        rr = ref.get("reflectance", 0.99)
        rr = rr if isinstance(rr, list) else [rr] * 3
        ref_xml = f"""
  <shape type="obj"><string name="filename" value="{ref_obj}"/><boolean name="face_normals" value="true"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="{rr[0]!r}, {rr[1]!r}, {rr[2]!r}"/></bsdf>
  </shape>"""
    scene_xml = f"""<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="{float(fov_x)!r}"/>
    <string name="fov_axis" value="x"/>
    <float name="principal_point_offset_x" value="{float(ppx)!r}"/>
    <float name="principal_point_offset_y" value="{float(ppy)!r}"/>
    <float name="near_clip" value="1"/>
    <float name="far_clip" value="100000"/>
    <transform name="to_world"><matrix value="{mat}"/></transform>
    <sampler type="independent"><integer name="sample_count" value="{a.spp}"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="{W}"/><integer name="height" value="{H}"/>
      <integer name="crop_offset_x" value="{x0}"/><integer name="crop_offset_y" value="{y0}"/>
      <integer name="crop_width" value="{cw}"/><integer name="crop_height" value="{ch}"/>
      <string name="pixel_format" value="rgb"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <emitter type="point">
    <point name="position" x="{float(lamp[0])!r}" y="{float(lamp[1])!r}" z="{float(lamp[2])!r}"/>
    <rgb name="intensity" value="{F[0]!r}, {F[1]!r}, {F[2]!r}"/>
  </emitter>
  <shape type="obj"><string name="filename" value="{tile_obj}"/><boolean name="face_normals" value="true"/>
{bsdf_xml}
  </shape>{ref_xml}
</scene>"""
    try:
        scene = mi.load_string(scene_xml)
    except Exception as e:  # noqa: BLE001 - the loader's message is the finding
        fail(f"mitsuba {mi.__version__} cannot load the scene with {xml_path}: {str(e).splitlines()[0]}")
    shutil.rmtree(tmp, ignore_errors=True)  # the meshes are loaded
    print(f"PASS: mitsuba {mi.__version__} loads the rig scene with {os.path.basename(xml_path)} "
          f"(fov_x {fov_x:.4f} deg, principal_point_offset {ppx:+.5f}, {ppy:+.5f}; crop {cw}x{ch} at {x0},{y0})")

    # Units check: the point light's contribution at a tile point against I f_r cos / D^2.
    tile_shape = scene.shapes()[0]
    bsdf = tile_shape.bsdf()
    p = np.array([100.0, 80.0, z_tile])
    si = mi.SurfaceInteraction3f()
    si.p = mi.Point3f(*p)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    emitter = scene.emitters()[0]
    ds, spec = emitter.sample_direction(si, mi.Point2f(0.5, 0.5), True)
    D = np.linalg.norm(lamp - p)
    got = np.array(spec)
    want = np.array(F) / D ** 2
    print(f"  point light at D = {D:.2f} mm: Mitsuba's incident {got[0]:.6g} vs F_c / D^2 = {want[0]:.6g} "
          f"(ratio {got[0] / want[0]:.6f}); bsdf.eval includes the cosine (export_check.py: f_r (n.l))")
    if abs(got[0] / want[0] - 1) > 1e-4:
        fail("Mitsuba's point light is not intensity / D^2")

    t0 = time.time()
    img = np.array(mi.render(scene), dtype=np.float64)[..., :3]
    print(f"  rendered {cw}x{ch} at {a.spp} spp in {time.time() - t0:.1f} s")
    render = np.zeros((H, W, 3))
    render[y0:y1, x0:x1] = img

    # The pinhole render resampled onto the distorted (calibrated) pixel grid.
    vv, uu = np.mgrid[y0:y1, x0:x1].astype(float)
    xd, yd = (uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy
    xu, yu = cam.undistort_normalized(xd, yd)
    render_d = np.zeros_like(render)
    render_d[y0:y1, x0:x1] = bilinear(img, cam.fx * xu + cam.cx - x0, cam.fy * yu + cam.cy - y0)

    # --- conventions: the tile's corners against the render and the photo -------------------
    U, V = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    sub = (slice(y0, y1), slice(x0, x1))
    mask_pin = np.zeros((H, W), bool)
    mask_dis = np.zeros((H, W), bool)
    mask_pin[sub] = plane_mask(cam, poly, z_tile, U[sub], V[sub], False)
    mask_dis[sub] = plane_mask(cam, poly, z_tile, U[sub], V[sub], True)
    lum_r = render[..., :3].mean(-1)
    hit = lum_r > 0
    # the rendered tile against the pinhole model (the reference is not the tile)
    if ref_poly is not None:
        ref_pin = np.zeros((H, W), bool)
        ref_pin[sub] = plane_mask(cam, ref_poly, z_ref, U[sub], V[sub], False)
        hit_tile = hit & erode(~ref_pin, 3)  # away from the reference's pixels
    else:
        hit_tile = hit
    print(f"  tile corners (pinhole) px: {np.round(cam.project(corners3, False), 1).tolist()}")
    print(f"  tile corners (distorted) px: {np.round(cam.project(corners3, True), 1).tolist()}")
    # Edge positions: along the row/column through each edge's middle, where the render and the
    # photo step, against the projections.
    cp = cam.project(corners3, False)
    cd = cam.project(corners3, True)

    def edge_offsets(image_lum, corners, min_step=0.15):
        """Per edge of the projected polygon: the median over points along it (10%..90%) of
        where the image's step crosses its half level, in px along the outward normal
        (+ = the image's edge lies outside the projection). Points where the step is below
        min_step of the inside level (the grid beneath as bright as the tile) are skipped."""
        offs = []
        n = len(corners)
        poly_px = [tuple(c) for c in corners]
        ts = np.arange(-6, 6.0001, 0.05)
        for i in range(n):
            a_, b_ = corners[i], corners[(i + 1) % n]
            e = b_ - a_
            nrm = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            mid = (a_ + b_) / 2
            if point_in_polygon(np.array([mid[0] + 3 * nrm[0]]), np.array([mid[1] + 3 * nrm[1]]), poly_px)[0]:
                nrm = -nrm  # outward
            found = []
            for f in np.linspace(0.1, 0.9, 17):
                q = a_ + f * e
                pts = q[None] + ts[:, None] * nrm[None]
                prof = bilinear(image_lum[..., None], pts[:, 0], pts[:, 1])[:, 0]
                inside = np.median(prof[ts < -3])
                outside = np.median(prof[ts > 3])
                if not np.isfinite(inside) or abs(inside - outside) < min_step * abs(inside):
                    continue
                g = prof - (inside + outside) / 2
                k = np.nonzero((np.sign(g[:-1]) != np.sign(g[1:])) & (np.abs(ts[:-1]) < 3))[0]
                if len(k) == 0:
                    continue
                k = k[np.argmin(np.abs(ts[k]))]
                found.append(ts[k] + (ts[k + 1] - ts[k]) * g[k] / (g[k] - g[k + 1]))
            offs.append(float(np.median(found)) if found else float("nan"))
        return offs

    def worst(offs):
        ok = [abs(o) for o in offs if np.isfinite(o)]
        return max(ok) if ok else float("nan")

    off_r = edge_offsets(lum_r, cp)
    photo_lum = np.nan_to_num(photo, nan=0.0).mean(-1)
    off_p = edge_offsets(photo_lum, cd)
    off_pp = edge_offsets(photo_lum, cp)
    print(f"  edge offsets (px along the outward normal; edges in the order of the outline): render vs pinhole "
          f"{[round(o, 2) for o in off_r]}; photo vs distorted {[round(o, 2) for o in off_p]}; "
          f"photo vs pinhole {[round(o, 2) for o in off_pp]}")
    # every pixel 1 px inside the projection is hit, none 1 px outside
    inner = erode(mask_pin, 1)
    outer = erode(~mask_pin, 1)
    miss_in = int((inner & ~hit_tile).sum())
    hit_out = int((outer & hit_tile).sum())
    okr = miss_in == 0 and hit_out == 0 and worst(off_r) < 0.5
    okp = sum(np.isfinite(off_p)) >= 2 and worst(off_p) < 1.0
    print(f"{'PASS' if okr else 'FAIL'}: the rendered tile is its pinhole projection (edges within "
          f"{worst(off_r):.2f} px; pixels 1 px inside not hit: {miss_in}, 1 px outside hit: {hit_out})")
    print(f"{'PASS' if okp else 'FAIL'}: the photo's tile edges lie on the distorted projection "
          f"(within {worst(off_p):.2f} px where the step is visible)")

    # --- the comparison ----------------------------------------------------------------------
    mask = erode(mask_pin & mask_dis, a.erode) & np.all(np.isfinite(photo), -1) & np.all(photo > 0, -1)
    npx = int(mask.sum())
    if npx < 100:
        fail(f"only {npx} tile pixels to compare")
    chans = "RGB"

    def stats(rend, label):
        r = rend[mask] / photo[mask] - 1
        med = np.median(r, 0)
        rms = np.sqrt(np.mean(r ** 2, 0))
        print(f"  {label}: render/photo - 1 over {npx} tile pixels: median "
              + ", ".join(f"{c} {m * 100:+.2f}%" for c, m in zip(chans, med))
              + "; rms " + ", ".join(f"{c} {s * 100:.2f}%" for c, s in zip(chans, rms)))
        return med, rms

    print("comparison (tile mask: hit in both camera models, eroded %d px)" % a.erode)
    med_p, rms_p = stats(render, "pinhole render (distortion ignored)")
    med_d, rms_d = stats(render_d, "render resampled with k1, k2")

    # the photo's own noise (variance.exr) and the comparison after a 9x9 box mean (noise / 9)
    var_path = os.path.join(S, "hdr", "variance.exr")
    if os.path.exists(var_path):
        var = np.array(mi.Bitmap(var_path), dtype=np.float64)[..., :3]
        nz = np.sqrt(np.mean(var[mask] / photo[mask] ** 2, 0))
        print("  the photo's noise (variance.exr) over the tile: rms sd/radiance "
              + ", ".join(f"{c} {x * 100:.2f}%" for c, x in zip(chans, nz)))
    mask9 = erode(mask, 4)
    r9 = box_mean(np.where(mask[..., None], render_d, 0), 4)[mask9] / \
        box_mean(np.where(mask[..., None], photo, 0), 4)[mask9] - 1
    print("  9x9 box means (noise averaged): render/photo - 1: median "
          + ", ".join(f"{c} {x * 100:+.2f}%" for c, x in zip(chans, np.median(r9, 0)))
          + "; rms " + ", ".join(f"{c} {x * 100:.2f}%" for c, x in zip(chans, np.sqrt(np.mean(r9 ** 2, 0))))
          + "; 1st..99th percentile " + ", ".join(
              f"{c} {np.percentile(r9[:, i], 1) * 100:+.1f}..{np.percentile(r9[:, i], 99) * 100:+.1f}%"
              for i, c in enumerate(chans)))

    # Where the difference comes from: the Glint model itself (fit.json's f_r, as the XML's
    # comment gives it) in the same units, per pixel, against the photo and the render.
    gm = re.search(r"glint model: f_r = kd \+ ks \(n\.h\)\^n / \(n\.l\); kd = \[([^]]*)\] 1/sr, "
                   r"ks = \[([^]]*)\] 1/sr, n = ([0-9.eE+-]+)", open(xml_path).read())
    if gm:
        kd = np.array([float(x) for x in gm.group(1).split(",")])
        ks = np.array([float(x) for x in gm.group(2).split(",")])
        nexp = float(gm.group(3))
        d = cam.rays(U[mask], V[mask], True)
        sgeo = (z_tile - cam.C[2]) / d[:, 2]
        X = cam.C[None] + sgeo[:, None] * d
        L = lamp[None] - X
        D2 = (L ** 2).sum(1)
        l_ = L / np.sqrt(D2)[:, None]
        v_ = cam.C[None] - X
        v_ /= np.linalg.norm(v_, axis=1)[:, None]
        h_ = l_ + v_
        h_ /= np.linalg.norm(h_, axis=1)[:, None]
        frcos = kd[None] * l_[:, 2:3] + ks[None] * np.clip(h_[:, 2:3], 0, 1) ** nexp
        model_rad = np.array(F)[None] * frcos / D2[:, None]
        for lab, num, den in (("Glint model (blinn-phong, fit.json) / photo", model_rad, photo[mask]),
                              ("render / Glint model (the roughplastic conversion)", render_d[mask], model_rad)):
            q = num / den - 1
            print(f"  {lab} - 1: median " + ", ".join(f"{c} {x * 100:+.2f}%" for c, x in zip(chans, np.median(q, 0)))
                  + "; rms " + ", ".join(f"{c} {x * 100:.2f}%" for c, x in zip(chans, np.sqrt(np.mean(q ** 2, 0)))))
        # the conversion error along the tile's y (grid mm): near (low y) to far
        yb = np.linspace(min(p[1] for p in poly), max(p[1] for p in poly), 6)
        q = render_d[mask] / model_rad - 1
        parts = []
        for lo, hi in zip(yb[:-1], yb[1:]):
            sel = (X[:, 1] >= lo) & (X[:, 1] < hi)
            if sel.any():
                parts.append(f"y {lo:.0f}..{hi:.0f}: {np.median(q[sel, 1]) * 100:+.1f}%")
        print("  render / Glint model - 1 (G) by the tile's y (mm; the lamp is at y "
              f"{lamp[1]:.0f}, the camera at y {cam.C[1]:.0f}): " + ", ".join(parts))

    # The export's own claim (its XML comment): the conversion's rms relative error of f_r (n.l)
    # at fit/samples.csv's geometries; here the render at those pixels against their prediction.
    smp = os.path.join(S, "fit", "samples.csv")
    if os.path.exists(smp):
        import csv
        rows = [r for r in csv.DictReader(open(smp)) if "predicted_r" in r]
        su = np.array([int(float(r["u"])) for r in rows])
        sv = np.array([int(float(r["v"])) for r in rows])
        pred = np.array([[float(r[f"predicted_{c}"]) for c in "rgb"] for r in rows])
        meas = np.array([[float(r[f"radiance_{c}"]) for c in "rgb"] for r in rows])
        inside = (su >= x0) & (su < x1) & (sv >= y0) & (sv < y1)
        if inside.any():
            rs = render_d[sv[inside], su[inside]]
            q = rs / pred[inside] - 1
            q2 = rs / meas[inside] - 1
            claim = re.search(r"rms relative error of f_r \(n\.l\) against the glint model over \d+ measured angles: "
                              r"([0-9.]+)%", open(xml_path).read())
            print(f"  at samples.csv's {int(inside.sum())} pixels: render / predicted (the Glint model) - 1: rms "
                  f"{np.sqrt(np.mean(q ** 2)) * 100:.2f}% over channels (per channel "
                  + ", ".join(f"{c} {x * 100:.2f}%" for c, x in zip(chans, np.sqrt(np.mean(q ** 2, 0))))
                  + f"); render / measured - 1: rms {np.sqrt(np.mean(q2 ** 2)) * 100:.2f}%"
                  + (f"; the XML claims {claim.group(1)}% (its own roughplastic code)" if claim else ""))

    # the highlight: the photo's brightest 9x9 mean inside the mask, and the render's
    sm_p = box_mean(np.where(mask[..., None], photo, 0), 4)
    full = box_mean(mask.astype(float), 4) > 0.999
    lp = np.where(full, sm_p.mean(-1), -1)
    iv, iu = np.unravel_index(np.argmax(lp), lp.shape)
    sm_r = box_mean(np.where(mask[..., None], render_d, 0), 4)
    lr = np.where(full, sm_r.mean(-1), -1)
    jv, ju = np.unravel_index(np.argmax(lr), lr.shape)
    ratio = sm_r[iv, iu] / sm_p[iv, iu]
    print(f"  highlight: photo's peak at px ({iu}, {iv}), render's at ({ju}, {jv}); render/photo over 9x9 "
          "at the photo's peak: " + ", ".join(f"{c} {x:.4f}" for c, x in zip(chans, ratio))
          + f"  (photo {np.round(sm_p[iv, iu], 2).tolist()}, render {np.round(sm_r[iv, iu], 2).tolist()})")
    if ref_poly is not None:
        rm = np.zeros((H, W), bool)
        rm[sub] = plane_mask(cam, ref_poly, z_ref, U[sub], V[sub], True) & \
            plane_mask(cam, ref_poly, z_ref, U[sub], V[sub], False)
        rm = erode(rm, a.erode) & np.all(np.isfinite(photo), -1)
        if rm.sum() > 50:
            rr_ = np.median(render_d[rm] / photo[rm], 0)
            print(f"  reference standard ({int(rm.sum())} px, diffuse {rr}): median render/photo "
                  + ", ".join(f"{c} {x:.4f}" for c, x in zip(chans, rr_))
                  + " (checks the lamp units alone: F_c was measured on it)")

    # --- the PNG -------------------------------------------------------------------------------
    tm = np.argwhere(mask_dis | mask_pin)
    (by0, bx0), (by1, bx1) = tm.min(0), tm.max(0)
    by0, bx0 = max(0, by0 - a.margin), max(0, bx0 - a.margin)
    by1, bx1 = min(H, by1 + a.margin + 1), min(W, bx1 + a.margin + 1)
    white = np.percentile(photo[mask], 99)  # one value over channels: keeps the colour
    exposure = 1.0 / white

    def tone(x):
        x = np.nan_to_num(x[by0:by1, bx0:bx1], nan=0.0) * exposure
        return (np.clip(x, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)

    left, right = tone(photo), tone(render)
    gap = 8
    label_h = 22
    hh, ww = left.shape[:2]
    canvas = np.full((hh + label_h, 2 * ww + gap, 3), 255, np.uint8)
    canvas[label_h:, :ww] = left
    canvas[label_h:, ww + gap:] = right
    im = Image.fromarray(canvas)
    dr = ImageDraw.Draw(im)
    dr.text((4, 5), "photo: radiance.exr", fill=(0, 0, 0))
    dr.text((ww + gap + 4, 5), f"Mitsuba {mi.__version__}: {model}.xml ({a.spp} spp, pinhole)", fill=(0, 0, 0))
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    im.save(a.out)
    print(f"  wrote {a.out} ({im.size[0]}x{im.size[1]}; tone map: radiance / {white:.4g} (the photo's tile "
          "99th percentile) then gamma 2.2; pixels " + f"x {bx0}..{bx1 - 1}, y {by0}..{by1 - 1})")

    ok = okr and okp and bool(np.all(np.isfinite(med_d)))
    print(("PASS" if ok else "FAIL") + " overall")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
