#!/usr/bin/env python3
"""How far OpenCV's CalibrateDebevec curve for the Memorial bracket is from Glint's, as
OpenCV is given more samples (its default is 70).

    pip install opencv-python-headless numpy
    glint import ../shared/data/debevec_memorial_hdr_stack/images --times times.txt --out /tmp/mem
    glint hdr /tmp/mem
    python3 benches/opencv_memorial_response_samples.py /tmp/mem/hdr/response.csv

(times.txt: `memorial00.png 1/0.03125` ..., from images/list.txt, which holds 1/t.)
Prints the largest difference per channel over pixel values 32..232, up to a per-channel
scale. Measured here: 70 samples R 36%, G 28%, B 42%; 300 samples R 9%, G 8%, B 20%;
1000 samples R 8%, G 9%, B 13%: OpenCV's curve moves towards Glint's as its own noise
falls.
"""
import sys

import cv2
import numpy as np

D = "../shared/data/debevec_memorial_hdr_stack/images/"
lines = [l.split() for l in open(D + "list.txt")]
imgs = [cv2.imread(D + f) for f, _ in lines]
t = np.array([1 / float(v) for _, v in lines], dtype=np.float32)
ours = np.loadtxt(sys.argv[1], delimiter=",", skiprows=1)[:, 1:][:, ::-1]  # RGB -> BGR
z = np.arange(32, 233)
for n in [70, 300, 1000]:
    r = cv2.createCalibrateDebevec(samples=n, random=False).process(imgs, t)[:, 0, :]
    out = []
    for c in range(3):
        d = np.log(ours[z, c]) - np.log(r[z, c])
        d -= 0.5 * (d.max() + d.min())
        out.append("%s %.0f%%" % ("BGR"[c], 100 * (np.exp(np.abs(d).max()) - 1)))
    print(f"OpenCV with {n} samples vs Glint:", ", ".join(out))
