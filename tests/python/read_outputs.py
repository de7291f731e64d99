"""Reads every EXR that `photostereo` writes with Python's OpenEXR package, as a notebook user
would, and checks channel names, sizes, types, the NaN mask and the values against the demo's
ground truth. Prints a JSON summary; exits non-zero on the first failed check.

Usage: python3 read_outputs.py OUT_DIR   (OUT_DIR written by `photostereo demo -o OUT_DIR`)
"""
import json
import sys

import numpy as np
import OpenEXR


def channels(path):
    """Channel name -> float32 array (H, W); grouped RGB channels are split into R, G, B."""
    with OpenEXR.File(path) as f:
        out = {}
        for name, ch in f.channels().items():
            px = np.asarray(ch.pixels)
            if name == "RGB" and px.ndim == 3:
                for i, c in enumerate("RGB"):
                    out[c] = px[..., i]
            else:
                out[name] = px
        return out, dict(f.header())


def check(cond, msg):
    if not cond:
        print("FAILED: " + msg, file=sys.stderr)
        sys.exit(1)


out = sys.argv[1]
summary = {}
normal, header = channels(f"{out}/normal.exr")
check(sorted(normal) == ["B", "G", "R"], f"normal.exr channels {sorted(normal)}")
for key in ["photostereo:method", "photostereo:frame", "photostereo:units", "photostereo:lights"]:
    check(key in header, f"normal.exr lacks the {key} attribute")
dirs = json.loads(header["photostereo:light_directions"])
check(len(dirs) == int(header["photostereo:lights"]), "light_directions and lights disagree")
check(np.allclose(np.linalg.norm(np.array(dirs), axis=1), 1.0, atol=1e-9), "light directions are not unit vectors")
summary["lights"] = len(dirs)
h, w = normal["R"].shape
n = np.dstack([normal[c] for c in "RGB"])
check(n.dtype == np.float32, f"normal dtype {n.dtype}")
valid = np.isfinite(n).all(axis=2)
check(np.allclose(np.linalg.norm(n[valid], axis=1), 1.0, atol=1e-5), "normals are not unit vectors")

gt, _ = channels(f"{out}/scene/gt/normal_gt.exr")
g = np.dstack([gt[c] for c in "RGB"])
cos = np.clip(np.sum(n[valid] * g[valid], axis=1), -1, 1)
summary["mean_angular_error_deg"] = float(np.degrees(np.arccos(cos)).mean())
check(summary["mean_angular_error_deg"] < 1.0, f"normals disagree with ground truth: {summary}")

depth, _ = channels(f"{out}/depth.exr")
# The integrator that report.json names: bilateral adds its weights wu, wv.
used = json.load(open(f"{out}/report.json"))["integration"]["method"]
expected = ["Z", "residual", "wu", "wv"] if used == "bilateral" else ["Z", "residual"]
check(sorted(depth) == expected and depth["Z"].shape == (h, w), f"depth.exr channels {list(depth)} ({used})")
check((np.isfinite(depth["Z"]) == valid).all(), "depth NaN mask differs from the normal map's")
dgt, _ = channels(f"{out}/scene/gt/depth_gt.exr")
d, t = depth["Z"][valid], dgt["Z"][valid]
rmse = float(np.sqrt(np.mean(((d - d.mean()) - (t - t.mean())) ** 2)))
summary["depth_rmse_over_range"] = rmse / float(t.max() - t.min())
check(summary["depth_rmse_over_range"] < 0.05, f"depth disagrees with ground truth: {summary}")

albedo, _ = channels(f"{out}/albedo.exr")
check(list(albedo) == ["Y"], f"albedo.exr channels {list(albedo)}")
check((np.isfinite(albedo["Y"]) == valid).all(), "albedo NaN mask differs")

res, _ = channels(f"{out}/residual.exr")
check(sorted(res) == ["condition", "filled", "residual", "robust", "samples"], f"residual.exr channels {sorted(res)}")
filled = valid & (res["filled"] == 1.0)
check(np.isin(res["filled"][valid], [0.0, 1.0]).all(), "filled flag is not 0/1 on pixels with a normal")
check((res["samples"][valid & ~filled] >= 3).all(), "solved pixels with fewer than 3 samples")
check(np.isin(res["robust"][valid], [0.0, 1.0]).all(), "robust flag is not 0/1 on solved pixels")

curl, _ = channels(f"{out}/curl.exr")
check(list(curl) == ["curl"], f"curl.exr channels {list(curl)}")

report = json.load(open(f"{out}/report.json"))
check(report["pixels"]["solved"] + report["pixels"]["filled"] == int(valid.sum()), "report pixel count differs from the NaN mask")
check(report["pixels"]["filled"] == int(filled.sum()), "report filled count differs from the filled channel")
check(report["model"]["robust_pixels"] == int((res["robust"][valid] == 1.0).sum()), "report robust count differs from the robust channel")
summary["pixels"] = int(valid.sum())
print(json.dumps(summary))
