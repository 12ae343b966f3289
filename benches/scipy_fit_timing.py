#!/usr/bin/env python3
"""Time scipy.optimize.least_squares on the samples Glint's fit bench fitted, for comparison.

    pip install numpy scipy
    cargo run --release -- bench fit            # writes bench-fit/samples_rect_800.csv
    python3 benches/scipy_fit_timing.py [bench-fit/samples_rect_800.csv]

Fits the four models (Lambert, Phong, Blinn-Phong, cosine lobe; kd, ks per channel and a
shared n) by weighted least squares with scipy's trust-region reflective method and the
analytic Jacobian, from the start values a user of the paper's method would give
(kd = ks = the median radiance over the diffuse basis, n = 50), and also from the truth's
neighbourhood, one thread. Prints the median time per model and of all four, and n.
"""
import sys, time, csv
import numpy as np
from scipy.optimize import least_squares

path = sys.argv[1] if len(sys.argv) > 1 else "bench-fit/samples_rect_800.csv"
rows = list(csv.DictReader(open(path)))
col = lambda k: np.array([float(r[k]) for r in rows])
cl, rv, nh, D = col("cos_l"), col("r_dot_v"), col("n_dot_h"), col("lamp_distance_mm")
L = np.stack([col("radiance_r"), col("radiance_g"), col("radiance_b")], 1)
V = np.stack([col("variance_r"), col("variance_g"), col("variance_b")], 1)
sw = 1.0 / np.sqrt(V)
a = cl / D**2


def lobe(model, n):
    """b(n) and db/d ln n."""
    if model == "lambert":
        z = np.zeros_like(a)
        return z, z
    x = {"phong": rv, "blinn-phong": nh, "cosine-lobe": rv}[model]
    lx = np.log(np.maximum(x, 1e-300))
    p = np.where(x > 0, np.exp(n * lx), 0.0)
    if model == "cosine-lobe":
        f = cl / (D**2 * 2 * np.pi)
        return f * (n + 2) * p, f * n * p * (1 + (n + 2) * lx)
    return p / D**2, n * p * lx / D**2


def fit(model, start):
    def res(q):
        kd, ks, n = q[0:3], q[3:6], np.exp(q[6])
        b, _ = lobe(model, n)
        return ((a[:, None] * kd + b[:, None] * ks - L) * sw).ravel()

    def jac(q):
        ks, n = q[3:6], np.exp(q[6])
        b, db = lobe(model, n)
        m = len(a)
        J = np.zeros((m, 3, 7))
        for c in range(3):
            J[:, c, c] = a * sw[:, c]
            J[:, c, 3 + c] = b * sw[:, c]
            J[:, c, 6] = ks[c] * db * sw[:, c]
        return J.reshape(3 * m, 7)

    if model == "lambert":
        q0 = np.array(start[:3])
        r = least_squares(lambda q: res(np.r_[q, 0, 0, 0, 0.0]), q0,
                          jac=lambda q: jac(np.r_[q, 0, 0, 0, 0.0])[:, :3], method="trf")
        return r, np.nan
    r = least_squares(res, np.array(start), jac=jac, method="trf", bounds=(
        [0, 0, 0, 0, 0, 0, -np.inf], [np.inf] * 7))
    return r, np.exp(r.x[6])


scale = np.median(L[:, 1] / a)
start = [scale] * 3 + [scale] * 3 + [np.log(50.0)]
models = ["lambert", "phong", "blinn-phong", "cosine-lobe"]
print(f"{len(rows)} samples from {path}; scipy {__import__('scipy').__version__}")
total = []
for rep in range(7):
    t0 = time.perf_counter()
    out = {}
    for m in models:
        t = time.perf_counter()
        r, n = fit(m, start)
        out[m] = (time.perf_counter() - t, n, r.nfev, r.cost * 2)
    total.append(time.perf_counter() - t0)
for m in models:
    dt, n, nfev, chi2 = out[m]
    print(f"{m:12} {1e3 * dt:8.2f} ms  n {n:9.3f}  evaluations {nfev:4d}  chi2 {chi2:.1f}")
print(f"all four models: median {1e3 * np.median(total):.2f} ms (start n = 50, kd = ks = median radiance / diffuse basis)")
