#!/usr/bin/env bash
# Makes docs/report.png: `glint run` on the simulated lab, then a screenshot of its report in
# headless Chromium (Debian: apt install chromium), cropped to the page by Python if Pillow
# is at hand. Run from anywhere; writes only docs/report.png and a temporary session.
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
cargo run --release -q -- run --rig rigs/mock.toml --out "$tmp/session" > /dev/null
chromium --headless --no-sandbox --disable-gpu --hide-scrollbars \
    --window-size=1280,5200 --screenshot="$tmp/shot.png" \
    "file://$tmp/session/report/index.html" 2> /dev/null
python3 - "$tmp/shot.png" docs/report.png <<'PY' || cp "$tmp/shot.png" docs/report.png
import sys
from PIL import Image
im = Image.open(sys.argv[1]).convert("RGB")
w, h = im.size
px = im.load()
# Crop the blank page below the last non-white row.
last = max(y for y in range(h) if any(px[x, y] != (255, 255, 255) for x in range(0, w, 4)))
im.crop((0, 0, w, min(h, last + 24))).save(sys.argv[2], optimize=True)
PY
echo "wrote docs/report.png (session: $tmp/session)"
