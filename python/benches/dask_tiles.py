#!/usr/bin/env python3
"""photostereo.dask on a LocalCluster of worker processes on loopback, against the
single-process solve of the same capture.

    python python/benches/dask_tiles.py [--size 4096] [--chunk 512] [--workers 2] [--rounds 1]

Renders a bumpy surface (size x size, 12 lights, noise 0.005, no cast shadows), solves it in chunk x chunk tiles
on the cluster and in one process under the same capture-wide model, and prints one JSON
object: wall times (the tiled solve with and without its capture-wide checks, `--rounds`
interleaved, medians), peak RSS of each worker and of this process, the largest normal
difference and the mean angular error against the rendered truth.
"""

import argparse
import json
import resource
import time

import numpy as np

import photostereo as ps
import photostereo.dask as psd


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--chunk", type=int, default=512)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1)
    a = ap.parse_args()

    import dask.array as da
    from distributed import Client, LocalCluster

    lights = ps.light_ring(12, 40.0)
    t = time.perf_counter()
    # No cast shadows: their ray marching costs O(size) a pixel, minutes at 4096² (the solve
    # does not care how the images were made).
    s = ps.render("bumps", a.size, lights, noise=0.005, seed=3, cast_shadows=False)
    render_s = time.perf_counter() - t
    images, mask = s["images"], s["mask"]

    with LocalCluster(
        n_workers=a.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
        dashboard_address=None, memory_limit="8GiB",
    ) as cluster, Client(cluster) as client:
        client.run(lambda: None)
        # The images go to the workers as the cluster's own data, chunked by tile.
        t = time.perf_counter()
        d = da.from_array(images, chunks=(images.shape[0], a.chunk, a.chunk))
        d = client.persist(d)
        from distributed import wait

        wait(d)
        scatter_s = time.perf_counter() - t
        # Normals alone, and normals with the capture-wide checks added over the tiles in the
        # same pass (what psd.compute does), interleaved, --rounds each; medians.
        import dask

        alone, checked = [], []
        for _ in range(a.rounds):
            t = time.perf_counter()
            maps = psd.solve(d, lights, mask=mask, chunks=a.chunk)
            normals = maps["normals"].compute()
            alone.append(time.perf_counter() - t)
            t = time.perf_counter()
            maps = psd.solve(d, lights, mask=mask, chunks=a.chunk)
            normals, checks = dask.compute(maps["normals"], maps["checks"])
            checked.append(time.perf_counter() - t)
        dask_s = float(np.median(alone))
        checks_s = float(np.median(checked))
        peaks = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)

    t = time.perf_counter()
    single = ps.solve(images, lights, mask=mask, fill=False, models=maps["models"])
    single_s = time.perf_counter() - t
    both = ~np.isnan(single.normals[..., 0])
    same_nan = bool(np.array_equal(both, ~np.isnan(normals[..., 0])))
    diff = float(np.abs(normals[both] - single.normals[both]).max())
    cos = np.clip(np.sum(normals[mask] * s["normals"][mask], -1), -1, 1)
    print(
        json.dumps(
            {
                "size": a.size,
                "images": int(images.shape[0]),
                "chunk": a.chunk,
                "workers": a.workers,
                "render_s": round(render_s, 2),
                "to_workers_s": round(scatter_s, 2),
                "dask_solve_s": round(dask_s, 2),
                "dask_solve_with_checks_s": round(checks_s, 2),
                "checks_named_lights": checks[0, 0]["light_agreement"][0]["disagreeing"],
                "checks_warnings": checks[0, 0]["warnings"],
                "single_process_solve_s": round(single_s, 2),
                "peak_rss_per_worker_mib": [round(v / 1024) for v in peaks.values()],
                "peak_rss_this_process_mib": round(
                    resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                ),
                "same_unsolved_pixels": same_nan,
                "max_normal_difference": diff,
                "mean_angular_error_deg": float(np.degrees(np.arccos(cos)).mean()),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
