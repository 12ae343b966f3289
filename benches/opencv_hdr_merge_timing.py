#!/usr/bin/env python3
"""Time OpenCV's MergeDebevec on the frames `glint bench hdr` merges (same generator).

    pip install opencv-python-headless numpy
    python3 benches/opencv_hdr_merge_timing.py [WIDTHxHEIGHT] [EXPOSURES]

Defaults: 4000x3000 and 7 exposures (glint bench hdr's defaults); the other comparison
point is 6000x4000 with 5 exposures. Prints the median of 3 runs.
"""
import sys
import time

import cv2
import numpy as np

size = sys.argv[1] if len(sys.argv) > 1 else "4000x3000"
n = int(sys.argv[2]) if len(sys.argv) > 2 else 7
w, h = (int(v) for v in size.split("x"))

# The generator of src/bench_hdr.rs: a 16-stop ramp with a hash texture, gamma 2.2.
x = np.arange(w, dtype=np.uint64)
y = np.arange(h, dtype=np.uint64)
k = np.arange(3, dtype=np.uint64)
frames, times = [], []
for j in range(n):
    t = 125.0 * 2**j
    kk = x[None, :, None] * 3 + k[None, None, :]
    hsh = ((x[None, :, None] * 0x9E3779B9 + y[:, None, None] * 0x85EBCA6B + kk) >> 7) & 0xFF
    rad = 2.0 ** (16.0 * x[None, :, None] / w - 12.0) * (1.0 + hsh / 2048.0)
    e = np.minimum(rad * t * 1e-3, 1.0)
    frames.append((e ** (1 / 2.2) * 255 + 0.5).astype(np.uint8))
    times.append(t * 1e-6)
times = np.array(times, dtype=np.float32)
response = ((np.maximum(np.arange(256), 0.5) / 255.0) ** 2.2).astype(np.float32)
response = np.repeat(response[:, None, None], 3, axis=2)

merge = cv2.createMergeDebevec()
walls = []
for _ in range(3):
    t0 = time.perf_counter()
    merge.process(frames, times, response)
    walls.append(time.perf_counter() - t0)
walls.sort()
mp = w * h / 1e6
print(f"OpenCV {cv2.__version__} MergeDebevec, {n} exposures at {w}x{h} ({mp:.1f} MP), "
      f"{cv2.getNumThreads()} threads: median {walls[1]*1e3:.0f} ms = {mp / walls[1]:.1f} MP/s")
