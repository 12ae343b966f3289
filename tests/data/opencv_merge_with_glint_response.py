#!/usr/bin/env python3
"""OpenCV's MergeDebevec with Glint's response (hdr/response.csv) against Glint's merge
(docs/methods.md, "Files other tools read").

    python3 tests/data/opencv_merge_with_glint_response.py SESSION

The session's tile frames (8-bit) and their exposure times (manifest.json) are merged by
cv2.MergeDebevec twice with the CSV's exposure columns as the camera response: the whole
table as written, and the table clamped at each channel's valid range (valid_r/g/b: values
outside it take the exposure at the range's end). Each is compared with Glint's radiance
on the samples Glint measured (hdr/mask.png 0), after one scale factor per channel
(OpenCV's weights differ, and its merge leaves out Glint's dark-frame subtraction).
Glint's radiance is read from hdr/radiance.hdr (this OpenCV build reads no EXR; RGBE keeps
1/256 of a pixel's brightest channel). MergeDebevec gives every value a weight (its
triangle is 1 at 0 and 255), so it cannot leave the values outside the valid range out:
clamping them makes a saturated reading stand for the range's top, too low (on the mock
rig's dry run: 3.5% median, 47% at the 95th percentile, against 0.83% and 3.9% with the
whole table, whose continuation beyond the range is at least monotonic). The third
comparison restricts the table to its valid range sample by sample: on the samples whose
every reading lies in the valid range MergeDebevec reads the table only where it is valid
(dry run: 0.58% median, 1.7% at the 95th percentile, on 20-26% of the samples; what is left
is the two merges' different weights, Glint's dark frames and RGBE's rounding). Exits 1
when the whole table's or the restricted median difference exceeds 2%. Needs numpy and
opencv-python(-headless)."""
import csv
import json
import sys

import cv2
import numpy as np


def main(session):
    m = json.load(open(f"{session}/manifest.json"))
    tiles = [f for f in m["frames"] if f["kind"] == "tile"]
    if any(f["bit_depth"] != 8 for f in tiles):
        sys.exit("MergeDebevec takes 8-bit frames only")
    imgs = [cv2.imread(f"{session}/{f['file']}", cv2.IMREAD_COLOR) for f in tiles]
    times = np.array([f["exposure_reported_us"] * 1e-6 for f in tiles], dtype=np.float32)
    rows = list(csv.DictReader(open(f"{session}/hdr/response.csv")))
    names = ["r", "g", "b"]
    table = np.array([[float(r[f"exposure_{c}"]) for c in names] for r in rows])
    valid = np.array([[r[f"valid_{c}"] == "1" for c in names] for r in rows])
    restricted = table.copy()
    for c in range(3):
        idx = np.flatnonzero(valid[:, c])
        lo, hi = idx[0], idx[-1]
        restricted[:lo, c] = table[lo, c]
        restricted[hi + 1:, c] = table[hi, c]
    glint = cv2.imread(f"{session}/hdr/radiance.hdr", cv2.IMREAD_UNCHANGED)  # BGR
    mask = cv2.imread(f"{session}/hdr/mask.png", cv2.IMREAD_UNCHANGED)  # BGR
    ok = mask == 0
    # Samples every one of whose readings lies in the valid range: there MergeDebevec uses
    # the table only where it is valid (restricted to the valid range sample by sample).
    inside = np.ones(ok.shape, dtype=bool)
    for img in imgs:
        for c in range(3):
            inside[..., c] &= valid[img[..., c], 2 - c]
    out = {}
    for name, t, sel in [("whole table", table, ok),
                         ("clamped at the valid range", restricted, ok),
                         ("samples read within the valid range in every frame", table, ok & inside)]:
        response = t[:, ::-1].reshape(256, 1, 3).astype(np.float32)  # BGR
        hdr = cv2.createMergeDebevec().process(imgs, times, response)
        worst = 0.0
        for c in range(3):
            if sel[..., c].sum() < 100:
                print(f"{name}, channel {'BGR'[c]}: only {sel[..., c].sum()} samples")
                continue
            ratio = hdr[..., c][sel[..., c]] / glint[..., c][sel[..., c]]
            ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
            d = np.abs(ratio / np.median(ratio) - 1.0)
            worst = max(worst, float(np.median(d)))
            p95 = float(np.percentile(d, 95))
            print(f"{name}, channel {'BGR'[c]}: {sel[..., c].sum()} samples, median |difference| {100 * np.median(d):.2f}%, 95th percentile {100 * p95:.2f}%")
        out[name] = worst
    print(f"OpenCV {cv2.__version__}: {len(imgs)} frames; median difference, worst channel: "
          f"whole table {100 * out['whole table']:.2f}%, clamped {100 * out['clamped at the valid range']:.2f}%, "
          f"samples read within the valid range {100 * out['samples read within the valid range in every frame']:.2f}%")
    restricted_ok = out["samples read within the valid range in every frame"] <= 0.02
    return 0 if out["whole table"] <= 0.02 and restricted_ok else 1


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1]))
