#!/usr/bin/env python3
"""OpenCV reads Glint's calib/camera_opencv.yaml and reprojects the grid's corners where
Glint's own projection puts them (expected: within 0.01 px).

    python3 tests/data/opencv_reads_camera.py SESSION/calib

Glint's projection of each corner used in the fit is its detection plus its residual
(camera.json: detections[k].corners, calibration.views[k].residuals, the placed and
doubtful corners left out). OpenCV's is cv2.projectPoints with the YAML's camera_matrix,
distortion_coefficients and the view's row of extrinsic_parameters (rvec, t). Exits 1 when
a corner is more than 0.01 px apart. Needs numpy and opencv-python(-headless)."""
import json
import sys

import cv2
import numpy as np


def main(calib):
    fs = cv2.FileStorage(f"{calib}/camera_opencv.yaml", cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    D = fs.getNode("distortion_coefficients").mat()
    ext = fs.getNode("extrinsic_parameters").mat()
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    fs.release()
    cam = json.load(open(f"{calib}/camera.json"))
    nx, ny = cam["grid"]["inner_corners"]
    sq = cam["grid"]["square_mm"] or 1.0
    obj = np.array([[i * sq, j * sq, 0.0] for j in range(ny) for i in range(nx)])
    worst = 0.0
    total = 0
    for k, (det, view) in enumerate(zip(cam["detections"], cam["calibration"]["views"])):
        skip = set(det["placed"]) | set(det["doubtful"])
        used = [i for i in range(len(det["corners"])) if i not in skip]
        glint = np.array(det["corners"])[used] + np.array(view["residuals"])
        rvec, t = ext[k, :3], ext[k, 3:]
        cv, _ = cv2.projectPoints(obj[used], rvec, t, K, D)
        d = np.hypot(*(cv.reshape(-1, 2) - glint).T)
        worst = max(worst, d.max())
        total += len(used)
    print(f"OpenCV {cv2.__version__}: {size[0]}x{size[1]}, {len(cam['detections'])} view(s), "
          f"{total} corners; worst |OpenCV - Glint| {worst:.2e} px")
    return 0 if worst <= 0.01 else 1


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1]))
