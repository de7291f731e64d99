#!/usr/bin/env python3
"""The Python module's solve beside the Rust library call and the numpy peer, on one DiLiGenT
capture, interleaved in one run (medians).

    python python/benches/solve_speed.py ../shared/data/diligent/catPNG [--rounds 9]

Each round runs, in turn:
- rust: `examples/solve_arrays` (built with `cargo build --release --example solve_arrays`),
  which reads the folder into one N x H x W x C uint16 array and times the library's
  array -> normals call (conversion, capture-wide model, per-pixel solve, normals) in-process;
- python: `photostereo.solve` on the same uint16 array (`photostereo.load`), default method;
- python ls: `photostereo.solve(method="ls")` on the numpy peer's own float32 grey arrays
  (images divided by the intensities and mixed to grey by the peer's loader);
- numpy: the peer's `solve_l2` (one least-squares call over the masked pixels) on those arrays;
- from stored: both again from the stored uint16 arrays (what `photostereo.load` and
  `cv2.imread` give): `photostereo.solve(method="ls")` converting them itself, against the
  peer's own conversion (divide by 65535 and by the intensities, BT.601 grey) then `solve_l2`.
Prints one JSON object: medians in seconds, the ratios, and each method's mean angular error.
"""

import argparse
import importlib.util
import json
import pathlib
import statistics
import subprocess
import time

import numpy as np

import photostereo as ps

ROOT = pathlib.Path(__file__).resolve().parents[2]


def peer():
    path = ROOT.parent / "shared" / "peers" / "numpy_ps.py"
    spec = importlib.util.spec_from_file_location("numpy_ps", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def mean_deg(n, gt, mask):
    c = np.clip(np.sum(n[mask] * gt[mask], axis=1), -1, 1)
    return float(np.degrees(np.arccos(c)).mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("folder", type=pathlib.Path)
    ap.add_argument("--rounds", type=int, default=9)
    a = ap.parse_args()
    exe = ROOT / "target" / "release" / "examples" / "solve_arrays"
    if not exe.exists():
        subprocess.run(
            ["cargo", "build", "--release", "--example", "solve_arrays"], cwd=ROOT, check=True
        )
    np_ps = peer()
    capture = ps.load(a.folder)
    I, L, mask = np_ps.load_diligent(str(a.folder))
    gt_file = a.folder / "normal_gt.exr"
    gt = None
    if gt_file.exists():
        g = ps.read_exr(gt_file)
        gt = np.dstack([g["R"], g["G"], g["B"]])
    times = {
        "rust": [], "python": [], "python_ls": [], "numpy": [],
        "python_ls_from_stored": [], "numpy_from_stored": [],
    }
    grey = np.array([0.299, 0.587, 0.114], dtype=np.float32)
    errors = {}
    for _ in range(a.rounds):
        # Two calls in the one process: the second, warm as the Python process is, is timed.
        out = subprocess.run(
            [str(exe), str(a.folder), "2"], check=True, capture_output=True, text=True
        )
        line = json.loads(out.stdout.strip().splitlines()[-1])
        times["rust"].append(line["seconds"])
        errors["rust"] = line["mean_deg"]

        t = time.perf_counter()
        r = capture.solve()
        times["python"].append(time.perf_counter() - t)

        t = time.perf_counter()
        rl = ps.solve(I, L, mask=mask, method="ls")
        times["python_ls"].append(time.perf_counter() - t)

        t = time.perf_counter()
        n = np_ps.solve_l2(I, L, mask)
        times["numpy"].append(time.perf_counter() - t)

        t = time.perf_counter()
        rs = ps.solve(capture.images, capture.lights, mask=capture.mask,
                      intensities=capture.intensities, method="ls")
        times["python_ls_from_stored"].append(time.perf_counter() - t)

        t = time.perf_counter()
        E = capture.intensities.astype(np.float32)
        Is = ((capture.images.astype(np.float32) / 65535.0) / E[:, None, None, :]) @ grey
        ns = np_ps.solve_l2(Is, L, mask)
        times["numpy_from_stored"].append(time.perf_counter() - t)
    if gt is not None:
        errors["python"] = mean_deg(r.normals, gt, mask)
        errors["python_ls"] = mean_deg(rl.normals, gt, mask)
        errors["numpy"] = mean_deg(n, gt, mask)
        errors["python_ls_from_stored"] = mean_deg(rs.normals, gt, mask)
        errors["numpy_from_stored"] = mean_deg(ns, gt, mask)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(
        json.dumps(
            {
                "folder": str(a.folder),
                "rounds": a.rounds,
                "median_seconds": med,
                "python_over_rust": med["python"] / med["rust"],
                "numpy_over_python_ls": med["numpy"] / med["python_ls"],
                "numpy_over_python_default": med["numpy"] / med["python"],
                "numpy_over_python_ls_from_stored": med["numpy_from_stored"]
                / med["python_ls_from_stored"],
                "mean_angular_error_deg": errors,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
