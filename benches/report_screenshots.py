#!/usr/bin/env python3
"""Screenshots of a Glint report's parts, made in a headless browser (Chromium).

    python3 benches/report_screenshots.py SESSION/report OUT_DIR

Each part of SESSION/report/index.html (the summary; each section by its heading, e.g.
"Reflectance fit") is written as a page of its own beside index.html (so that its figures
load), shot with `chromium --headless --screenshot` at 1100 px wide, and trimmed of the
white below it (Pillow). Needs chromium (Debian: apt-get install chromium) and Pillow
(pip install pillow); says SKIP and exits 0 where either is absent.
"""

import os
import re
import shutil
import subprocess
import sys
import tempfile


def main():
    if len(sys.argv) != 3:
        print(__doc__)
        return 2
    report, out = sys.argv[1], sys.argv[2]
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        print("SKIP: no chromium on the PATH (Debian: apt-get install chromium)")
        return 0
    try:
        from PIL import Image, ImageChops
    except ImportError:
        print("SKIP: Pillow is not installed (pip install pillow)")
        return 0
    html = open(os.path.join(report, "index.html"), encoding="utf-8").read()
    head_end = html.index("<body>") + len("<body>") if "<body>" in html else html.index(">", html.index("<body")) + 1
    head, body = html[:head_end], html[head_end:]
    # Parts: the summary, then each <h2> section.
    parts = {}
    m = re.search(r'<div class="summary">.*?</div>', body, re.S)
    if m:
        parts["summary"] = m.group(0)
    starts = [m.start() for m in re.finditer(r"<h2>", body)] + [len(body)]
    for a, b in zip(starts, starts[1:]):
        title = re.match(r"<h2>([^<]*)", body[a:]).group(1).strip()
        name = re.sub(r"[^a-z0-9]+", "-", title.lower()).strip("-")
        parts[name] = body[a:b]
    os.makedirs(out, exist_ok=True)
    made = []
    for name, part in parts.items():
        page = os.path.join(report, f".shot-{name}.html")
        with open(page, "w", encoding="utf-8") as f:
            f.write(head + part + "</body></html>")
        png = os.path.join(out, f"report-{name}.png")
        with tempfile.TemporaryDirectory() as profile:
            subprocess.run(
                [
                    browser,
                    "--headless",
                    "--no-sandbox",
                    "--disable-gpu",
                    "--hide-scrollbars",
                    f"--user-data-dir={profile}",
                    f"--screenshot={png}",
                    "--window-size=1100,4000",
                    "file://" + os.path.abspath(page),
                ],
                check=True,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                timeout=120,
            )
        os.remove(page)
        img = Image.open(png).convert("RGB")
        bg = Image.new("RGB", img.size, img.getpixel((img.width - 1, img.height - 1)))
        box = ImageChops.difference(img, bg).getbbox()
        if box:
            img = img.crop((0, 0, img.width, min(img.height, box[3] + 16)))
        img.save(png)
        made.append(png)
        print(f"wrote {png} ({img.width}x{img.height})")
    return 0 if made else 1


if __name__ == "__main__":
    sys.exit(main())
