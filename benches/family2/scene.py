"""A second family of scenes for Glint, written apart from the simulated lab (mock/).

It shares none of glint-mock's code and differs from it where a real lab does:

- a pixel integrates light over its area (a 4x4 sub-pixel grid with a fill factor) and
  the lens blurs it (a Gaussian spot), where the simulator samples pixel centres;
- half the cameras have a Bayer mosaic (RGGB) demosaicked bilinearly from linear ADC
  values, as a camera's own pipeline does, so the noise of neighbouring pixels correlates;
- a sensor with an ADC of 10-14 bits and a black level; an 8-bit camera applies a tone
  curve drawn from the EMoR model of measured camera responses (Grossberg and Nayar),
  each channel its own curve near a common one; a 16-bit camera writes the ADC's values
  shifted up (a linear "raw" output, every 16th value used at 12 bits) or a drawn curve;
- stronger lens distortion (k1 -0.35..0.15, k2, k3, and tangential terms on some);
- the grid photographed under room light (a broad, uneven light from above), with or
  without the lamp;
- fewer dark frames (none, one at the longest exposure, or one at each end);
- cameras 250-900 mm from the tile, 15-60 degrees from its normal, lamps 200-1200 mm;
- tiles from weak lobes (the highlight 1.1x the diffuse level) to very strong ones (300x),
  8- and 16-bit, brackets of 1- or 2-stop steps chosen as an operator would from a test
  shot, up to 12 stops, the highlight near full scale at the shortest exposure on some;
- realistic materials outside Glint's candidates: isotropic Ward lobes with the
  parameters Ward (1992) published for measured materials.

Conventions (the project's docs/design.md and docs/session-format.md): grid frame in mm,
origin at the inner corner whose +x,+y square is dark, z up; X_cam = R X + t; pixel (0, 0)
is the centre of the top-left pixel; the BRDF formulas of the four paper models.

Nothing here reads Glint's code; the sessions are written in the public format as a lab's
own tool would write them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data"
EMOR = SHARED / "emor_camera_response_model" / "emor.txt"

GRID = (9, 6)
SQUARE = 25.0

# Ward (1992), "Measuring and modeling anisotropic reflection", Table 1, the isotropic
# fits (rho_d, rho_s, alpha). f = rho_d/pi + rho_s exp(-tan^2(theta_h)/alpha^2) /
# (4 pi alpha^2 sqrt(cos_i cos_o)).
WARD_MATERIALS = {
    "rolled brass": (0.10, 0.33, 0.050),
    "rolled aluminum": (0.10, 0.21, 0.04),
    "lightly brushed aluminum": (0.15, 0.19, 0.088),
    "enamel finished metal": (0.25, 0.047, 0.080),
    "painted cardboard box": (0.19, 0.043, 0.076),
    "white ceramic tile": (0.70, 0.050, 0.071),
    "glossy grey paper": (0.29, 0.083, 0.082),
    "ivory computer plastic": (0.45, 0.043, 0.13),
    "plastic laminate": (0.67, 0.070, 0.092),
}

MODELS = ["lambert", "phong", "blinn-phong", "cosine-lobe"]


# ----------------------------------------------------------------------------------------
# The response model: EMoR (mean curve plus principal components of measured curves).


def load_emor():
    """(E, f0, H[25, 1024]) from the EMoR file, or None where the shared data is absent."""
    if not EMOR.exists():
        return None
    blocks, cur = {}, None
    for line in EMOR.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        if "=" in line:
            cur = line.split("=")[0].strip()
            blocks[cur] = []
        else:
            blocks[cur].extend(float(x) for x in line.split())
    E = np.array(blocks["E"])
    f0 = np.array(blocks["f0"])
    H = np.array([blocks[f"h({k})"] for k in range(1, 26)])
    return E, f0, H


def draw_curve(rng, emor, channels=3):
    """Per channel a tone curve f: [0,1] -> [0,1] on 1024 samples, monotone, drawn from
    EMoR: one common draw (coefficient k with sd 0.9 / k, five terms) plus a small one per
    channel. Without the EMoR file: a filmic S-curve family of our own."""
    x = np.linspace(0.0, 1.0, 1024)
    out = []
    if emor is not None:
        E, f0, H = emor
        while True:
            common = np.array([rng.normal(0, 0.9 / k) for k in range(1, 6)])
            curves = []
            for _ in range(channels):
                c = common + np.array([rng.normal(0, 0.08 / k) for k in range(1, 6)])
                f = f0 + c @ H[:5]
                curves.append(f)
            ok = all(np.all(np.diff(f) > 1e-5) and abs(f[0]) < 1e-6 and abs(f[-1] - 1) < 1e-6
                     for f in curves)
            if ok:
                return curves, "emor", common.tolist()
    g = rng.uniform(1.8, 2.6)
    shoulder = rng.uniform(0.0, 0.35)
    for _ in range(channels):
        gi = g * rng.uniform(0.97, 1.03)
        f = x ** (1 / gi)
        f = (1 + shoulder) * f / (1 + shoulder * f)
        out.append(f / f[-1])
    return out, "filmic", [g, shoulder]


# ----------------------------------------------------------------------------------------
# Geometry.


def rot_look(cam, target, roll_deg):
    """R (world -> camera) for a camera at `cam` looking at `target`, x right, y down."""
    z = np.asarray(target, float) - cam
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    a = math.radians(roll_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return Rz @ R


@dataclass
class Lens:
    fx: float
    fy: float
    cx: float
    cy: float
    k: list  # k1, k2, k3
    p: list  # p1, p2

    def distort(self, x, y):
        r2 = x * x + y * y
        d = 1 + self.k[0] * r2 + self.k[1] * r2 * r2 + self.k[2] * r2 ** 3
        p1, p2 = self.p
        xd = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def project(self, Xc):
        x, y = Xc[..., 0] / Xc[..., 2], Xc[..., 1] / Xc[..., 2]
        xd, yd = self.distort(x, y)
        return self.fx * xd + self.cx, self.fy * yd + self.cy

    def undistort(self, u, v):
        """Normalised undistorted (x, y) for pixel (u, v): Newton steps on the distortion."""
        xd, yd = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        h = 1e-6
        for _ in range(30):
            fx_, fy_ = self.distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            a1, b1 = self.distort(x + h, y)
            a2, b2 = self.distort(x, y + h)
            j11, j21 = (a1 - fx_) / h, (b1 - fy_) / h
            j12, j22 = (a2 - fx_) / h, (b2 - fy_) / h
            det = j11 * j22 - j12 * j21
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (-j21 * ex + j11 * ey) / det
            if max(np.abs(ex).max(), np.abs(ey).max()) < 1e-13:
                break
        return x, y


# ----------------------------------------------------------------------------------------
# The scene.


@dataclass
class Scene:
    seed: int
    width: int
    height: int
    bits: int
    adc_bits: int
    black_dn: int
    bayer: bool
    curve_kind: str  # "emor", "filmic", "linear"
    curve_params: list
    lens: dict
    blur_px: float
    fill_factor: float
    camera_mm: list
    target_mm: list
    roll_deg: float
    lamp_mm: list
    tile_outline: list
    tile_thickness: float
    model: str  # one of MODELS, or "ward"
    kd: list
    ks: list
    n: float
    ward: dict | None
    qe: list  # electrons per (radiance unit x µs), per channel
    full_well: float
    read_e: float
    dark_e_per_s: float
    exposures_us: list
    dark_exposures_us: list
    grid_exposure_us: int
    grid_lamp_on: bool
    room: dict
    board_margin_mm: float
    albedo: dict
    operator_note: str = ""
    curves: list = field(default_factory=list, repr=False)

    # ------------------------------------------------------------------ derived
    def R_t(self):
        C = np.array(self.camera_mm)
        R = rot_look(C, self.target_mm, self.roll_deg)
        return R, -R @ C

    def lens_obj(self):
        return Lens(**self.lens)

    def truth(self):
        """What Glint should find: the model, n and ks/kd per channel (None for Ward)."""
        if self.model == "ward":
            return {"model": "ward", "ward": self.ward}
        ratio = [ks / kd if kd > 0 else None for kd, ks in zip(self.kd, self.ks)]
        return {"model": self.model, "n": self.n, "ks_over_kd": ratio}


def brdf_cos(model, p, l, v, nrm=np.array([0, 0, 1.0])):
    """f_r * max(0, n.l) per point (arrays ... x 3 of unit vectors), per channel: (..., 3).
    p: dict of kd (3), ks (3), n; or ward's rho_d, rho_s, alpha (and tint)."""
    cl = np.clip(l[..., 2], 0, None)
    cv = np.clip(v[..., 2], 0, None)
    kd = np.asarray(p["kd"])
    if model == "ward":
        h = l + v
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        ch = np.clip(h[..., 2], 1e-9, 1)
        tan2 = (1 - ch * ch) / (ch * ch)
        a = p["alpha"]
        spec = np.exp(-tan2 / (a * a)) / (4 * math.pi * a * a * np.sqrt(np.maximum(cl * cv, 1e-12)))
        spec = np.where((cl > 0) & (cv > 0), spec, 0.0)
        return (kd[None, :] * cl[..., None] + np.asarray(p["ks"])[None, :] * (spec * cl)[..., None])
    ks = np.asarray(p["ks"])
    n = p["n"]
    if model == "lambert":
        lobe_cos = np.zeros_like(cl)
    elif model == "phong":
        r = 2 * cl[..., None] * nrm - l
        rv = np.clip((r * v).sum(-1), 0, None)
        lobe_cos = np.where(cl > 0, rv ** n, 0.0)
    elif model == "blinn-phong":
        h = l + v
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        nh = np.clip(h[..., 2], 0, None)
        lobe_cos = np.where(cl > 0, nh ** n, 0.0)
    elif model == "cosine-lobe":
        r = 2 * cl[..., None] * nrm - l
        rv = np.clip((r * v).sum(-1), 0, None)
        lobe_cos = (n + 2) / (2 * math.pi) * rv ** n * cl
    else:
        raise ValueError(model)
    return kd[None, :] * cl[..., None] + ks[None, :] * lobe_cos[..., None]


def params_of(s: Scene):
    if s.model == "ward":
        return {"kd": s.kd, "ks": s.ks, "alpha": s.ward["alpha"]}
    return {"kd": s.kd, "ks": s.ks, "n": s.n}


def board_albedo(s: Scene, x, y):
    """Albedo of the z = 0 plane: the chessboard's squares, its paper margin, the table."""
    a = s.albedo
    nx, ny = GRID
    x0, x1 = -SQUARE, nx * SQUARE
    y0, y1 = -SQUARE, ny * SQUARE
    m = s.board_margin_mm
    out = np.full(x.shape, a["table"])
    paper = (x >= x0 - m) & (x <= x1 + m) & (y >= y0 - m) & (y <= y1 + m)
    out[paper] = a["light"]
    sq = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    i = np.floor(x / SQUARE).astype(int)
    j = np.floor(y / SQUARE).astype(int)
    dark = sq & ((i + j) % 2 == 0)
    out[dark] = a["dark"]
    return out


def intersect(s: Scene, C, d, with_tile):
    """For rays C + t d (d: ... x 3), the hit point, its normal and what it is:
    0 board/table (z = 0), 1 tile top, 2 tile side."""
    poly = np.array(s.tile_outline)
    lo = np.array([poly[:, 0].min(), poly[:, 1].min(), 0.0])
    hi = np.array([poly[:, 0].max(), poly[:, 1].max(), s.tile_thickness])
    shape = d.shape[:-1]
    kind = np.zeros(shape, int)
    t_ground = -C[2] / d[..., 2]
    t = t_ground.copy()
    nrm = np.zeros(d.shape)
    nrm[..., 2] = 1
    if with_tile:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - C) / d
            t2 = (hi - C) / d
        tmin = np.minimum(t1, t2)
        tmax = np.maximum(t1, t2)
        tin = tmin.max(-1)
        tout = tmax.min(-1)
        axis = tmin.argmax(-1)
        hit = (tin <= tout) & (tin > 0)
        t = np.where(hit, tin, t)
        kind = np.where(hit, np.where(axis == 2, 1, 2), 0)
        side = hit & (axis != 2)
        for ax in (0, 1):
            sel = side & (axis == ax)
            nrm[sel] = 0
            nrm[sel, ax] = -np.sign(d[sel, ax])
    P = C + t[..., None] * d
    return P, nrm, kind


def shadowed(s: Scene, P, lamp):
    """Whether the tile box blocks the segment from P to the lamp."""
    poly = np.array(s.tile_outline)
    lo = np.array([poly[:, 0].min(), poly[:, 1].min(), 0.0])
    hi = np.array([poly[:, 0].max(), poly[:, 1].max(), s.tile_thickness])
    d = lamp - P
    Q = P + 1e-6 * d
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - Q) / d
        t2 = (hi - Q) / d
    tin = np.minimum(t1, t2).max(-1)
    tout = np.maximum(t1, t2).min(-1)
    return (tin <= tout) & (tout > 0) & (tin < 1)


def radiance_image(s: Scene, which: str, ss=4, Rt=None):
    """The radiance each pixel integrates (width x height x 3, per channel the scene's
    radiance in its units), area-averaged over the pixel's light-sensitive part (a square
    of side sqrt(fill_factor) in an ss x ss grid) and blurred by the lens.
    which: "tile" (lamp on, tile in place) or "grid" (tile removed, room light, lamp as
    the scene says). Rt: the camera's pose in the board's frame where the board is not in
    its place (a lens calibration's tilted poses); the lamp then stays off.
    Also returns which surface each pixel centre sees (0 board, 1 tile top, 2 tile side)."""
    from scipy.ndimage import gaussian_filter

    R, t = s.R_t() if Rt is None else Rt
    C = -R.T @ t
    lens = s.lens_obj()
    centre_kind = None
    W, H = s.width, s.height
    side = math.sqrt(s.fill_factor)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    offs = offs * side
    lamp = np.array(s.lamp_mm)
    acc = np.zeros((H, W, 3))
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    # The rays in the camera's frame depend on the lens alone: undistorted once per scene.
    cache = s.__dict__.setdefault("_rays", {})
    for oy in offs:
        for ox in offs:
            if (ox, oy, ss) not in cache:
                x, y = lens.undistort(uu + ox, vv + oy)
                cache[(ox, oy, ss)] = np.stack([x, y, np.ones_like(x)], -1)
            dc = cache[(ox, oy, ss)]
            d = dc @ R  # R^T dc
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            P, nrm, kind = intersect(s, C, d, with_tile=(which == "tile"))
            v = -d
            L = np.zeros((H, W, 3))
            if centre_kind is None and abs(ox) < 1e-12 and abs(oy) < 1e-12:
                centre_kind = kind
            lamp_on = (which == "tile" or s.grid_lamp_on) and Rt is None
            if lamp_on:
                ld = lamp - P
                D2 = (ld * ld).sum(-1)
                l = ld / np.sqrt(D2)[..., None]
                I = 1.0e6
                top = kind == 1
                if top.any():
                    L[top] = brdf_cos(s.model, params_of(s), l[top], v[top]) * (I / D2[top])[:, None]
                sidem = kind == 2
                if sidem.any():
                    cl = np.clip((l[sidem] * nrm[sidem]).sum(-1), 0, None)
                    L[sidem] = np.asarray(s.kd)[None, :] * (cl * I / D2[sidem])[:, None]
                gr = kind == 0
                if gr.any():
                    alb = board_albedo(s, P[gr, 0], P[gr, 1])
                    cl = np.clip(l[gr, 2], 0, None)
                    sh = shadowed(s, P[gr], lamp) if which == "tile" else np.zeros(gr.sum(), bool)
                    tint = np.array(s.albedo["tint"])
                    L[gr] = (alb / math.pi * cl * I / D2[gr] * (~sh))[:, None] * tint[None, :]
            if which == "grid":
                # Room light: uniform irradiance from above, with a gradient across the board.
                r = s.room
                gr = kind == 0
                E = r["level"] * (1 + r["gx"] * (P[gr, 0] - 100) / 100 + r["gy"] * (P[gr, 1] - 60) / 100)
                alb = board_albedo(s, P[gr, 0], P[gr, 1])
                L[gr] += (alb / math.pi * np.clip(E, 0, None))[:, None] * np.array(r["tint"])[None, :]
            acc += L
    acc /= ss * ss
    if s.blur_px > 0:
        for c in range(3):
            acc[..., c] = gaussian_filter(acc[..., c], s.blur_px, mode="nearest")
    if centre_kind is None:
        x, y = lens.undistort(uu, vv)
        d = np.stack([x, y, np.ones_like(x)], -1) @ R
        centre_kind = intersect(s, C, d, with_tile=(which == "tile"))[2]
    return acc, centre_kind
