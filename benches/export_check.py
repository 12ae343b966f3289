#!/usr/bin/env python3
"""Check `glint export`'s files with the tools they are for.

    python3 benches/export_check.py MATERIAL.xml MATERIAL.gltf [--keep DIR]

- Mitsuba 3 (the `mitsuba` Python package, variant scalar_rgb): the <bsdf> is put on a
  rectangle lit by a point light and seen by a perspective camera; the scene is loaded,
  rendered (64x48, 16 spp) and written as EXR; the render must be finite and not black.
  The bsdf is also evaluated at one geometry beside its own parameters.
- glTF: Khronos' validator (npm package `gltf-validator`, a library: run with node from a
  cache folder, ~/.cache/glint-export-check). No errors allowed; warnings and infos listed.

Prints one PASS/FAIL/SKIP line per check; exits 1 on any FAIL, 0 otherwise (a SKIP, when
a tool is absent, says how to get it).
"""

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile

failed = False


def report(status, what, detail=""):
    global failed
    if status == "FAIL":
        failed = True
    print(f"{status}: {what}" + (f" ({detail})" if detail else ""), flush=True)


def check_mitsuba(xml_path, out_dir):
    try:
        import mitsuba as mi
    except ImportError:
        report("SKIP", "mitsuba", "the `mitsuba` Python package is absent: pip install mitsuba")
        return
    mi.set_variant("scalar_rgb")
    bsdf_xml = open(xml_path).read()
    scene_xml = f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, -2.2, 2.2" target="0, 0, 0" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="48"/>
      <string name="pixel_format" value="rgb"/></film>
  </sensor>
  <emitter type="point"><point name="position" x="0" y="1.5" z="1.5"/>
    <rgb name="intensity" value="10"/></emitter>
  <shape type="rectangle">
{bsdf_xml}
  </shape>
</scene>"""
    try:
        scene = mi.load_string(scene_xml)
    except Exception as e:  # noqa: BLE001 - any loader error is the finding
        report("FAIL", f"mitsuba loads {xml_path}", str(e).splitlines()[0])
        return
    report("PASS", f"mitsuba {mi.__version__} loads {xml_path} on a rectangle")
    bsdf = scene.shapes()[0].bsdf()
    img = mi.render(scene)
    exr = os.path.join(out_dir, "export_check.exr")
    mi.util.write_bitmap(exr, img)
    try:
        import numpy as np
    except ImportError:
        report("SKIP", "mitsuba renders it", "the `numpy` Python package is absent: pip install numpy")
    else:
        a = np.array(img)
        if np.all(np.isfinite(a)) and a.max() > 0:
            report("PASS", f"mitsuba renders it ({exr}: mean {a.mean():.4g}, max {a.max():.4g})")
        else:
            report("FAIL", "mitsuba renders it", f"finite {np.all(np.isfinite(a))}, max {a.max()}")
    # f_r (n.l) at one geometry: near the mirror direction and away from it.
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(-0.5, 0, 0.8660254)
    ctx = mi.BSDFContext()
    for name, wo in [("mirror", mi.Vector3f(0.5, 0, 0.8660254)), ("off", mi.Vector3f(-0.3, 0.3, 0.9055385))]:
        v = bsdf.eval(ctx, si, mi.Vector3f(wo))
        print(f"  {type(bsdf).__name__} eval at {name}: f_r (n.l) = {[round(float(x), 5) for x in v]}")


def check_gltf(path):
    node = shutil.which("node")
    npm = shutil.which("npm")
    if not node or not npm:
        report("SKIP", "glTF validator", "node and npm are absent (the validator is the npm package gltf-validator)")
        return
    cache = os.path.expanduser("~/.cache/glint-export-check")
    os.makedirs(cache, exist_ok=True)
    if not os.path.isdir(os.path.join(cache, "node_modules", "gltf-validator")):
        r = subprocess.run([npm, "install", "--prefix", cache, "gltf-validator"], capture_output=True, text=True)
        if r.returncode != 0:
            report("SKIP", "glTF validator", "npm install gltf-validator failed: " + r.stderr.strip().splitlines()[-1])
            return
    script = """
const v = require('gltf-validator');
const fs = require('fs');
const data = new Uint8Array(fs.readFileSync(process.argv[1]));
v.validateBytes(data, {uri: process.argv[1]}).then(r => console.log(JSON.stringify(r)))
 .catch(e => { console.error(String(e)); process.exit(2); });
"""
    r = subprocess.run([node, "-e", script, os.path.abspath(path)], capture_output=True, text=True,
                       env={**os.environ, "NODE_PATH": os.path.join(cache, "node_modules")})
    if r.returncode != 0:
        report("FAIL", f"glTF validator on {path}", r.stderr.strip())
        return
    res = json.loads(r.stdout)
    issues = res["issues"]
    for m in issues.get("messages", []):
        sev = ["error", "warning", "info", "hint"][m["severity"]]
        print(f"  {sev}: {m['code']} {m.get('pointer', '')}: {m['message']}")
    detail = (f"validator {res['validatorVersion']}: {issues['numErrors']} errors, {issues['numWarnings']} warnings, "
              f"{issues['numInfos']} infos, {issues['numHints']} hints")
    report("PASS" if issues["numErrors"] == 0 else "FAIL", f"glTF validator on {path}", detail)
    doc = json.load(open(path))
    m = doc["materials"][0]
    print(f"  material: {json.dumps(m)}")


def main():
    args = sys.argv[1:]
    keep = None
    if "--keep" in args:
        i = args.index("--keep")
        keep = args[i + 1]
        del args[i:i + 2]
    if len(args) != 2:
        print(__doc__)
        sys.exit(2)
    out_dir = keep or tempfile.mkdtemp(prefix="glint-export-check-")
    os.makedirs(out_dir, exist_ok=True)
    check_mitsuba(args[0], out_dir)
    check_gltf(args[1])
    print("FAIL" if failed else "PASS", "overall")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
