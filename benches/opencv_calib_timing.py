#!/usr/bin/env python3
"""Time OpenCV's single-view pipeline on one photo, one thread, for `glint bench calib`.

    pip install opencv-python-headless numpy
    python3 benches/opencv_calib_timing.py [PHOTO]

findChessboardCorners + cornerSubPix (11x11) + calibrateCamera with the principal point
fixed, no tangential terms and no k3 (the single-view settings of reference.json in
../shared/data/opencv_stereo_chessboard_9x6). Prints the median of 30 runs, wall time and
the thread's CPU time (the latter holds up on a machine shared with other work).
"""
import sys
import time

import cv2
import numpy as np

path = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/opencv_stereo_chessboard_9x6/images/left01.jpg"
im = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
if im is None:
    sys.exit(f"cannot read {path}")
cv2.setNumThreads(1)
obj = np.array([[i, j, 0] for j in range(6) for i in range(9)], np.float32)
crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
flags = cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
ts, cpu = [], []
for _ in range(30):
    t = time.perf_counter()
    c0 = time.thread_time()
    ok, c = cv2.findChessboardCorners(im, (9, 6))
    c = cv2.cornerSubPix(im, c, (11, 11), (-1, -1), crit)
    cv2.calibrateCamera([obj], [c], im.shape[::-1], None, None, flags=flags)
    ts.append(time.perf_counter() - t)
    cpu.append(time.thread_time() - c0)
ts.sort()
cpu.sort()
print(f"OpenCV {cv2.__version__}, {path} ({im.shape[1]}x{im.shape[0]}), one thread: median {1e3 * ts[len(ts) // 2]:.2f} ms (CPU {1e3 * cpu[len(cpu) // 2]:.2f} ms)")
