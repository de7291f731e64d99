"""photostereo.dask on a LocalCluster of 2 worker processes on loopback: tiles give the normals
of the single-process solve. The size is PHOTOSTEREO_DASK_SIZE (default 1024; the figures in
docs/python.md are of 4096, from python/benches/dask_tiles.py)."""

import os
import time

import numpy as np
import pytest

import photostereo as ps
from conftest import turned

dask = pytest.importorskip("dask")
distributed = pytest.importorskip("distributed")
import dask.array as da  # noqa: E402

import photostereo.dask as psd  # noqa: E402


def capture(size, count=12, seed=3):
    """A rendered bumpy surface under `count` lights, with noise, as float32."""
    lights = ps.light_ring(count, 40.0)
    s = ps.render("bumps", size, lights, noise=0.005, seed=seed)
    return s, lights


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
        dashboard_address=None, memory_limit="6GiB",
    )
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_tiles_on_a_local_cluster_equal_the_single_process_solve(client):
    size = int(os.environ.get("PHOTOSTEREO_DASK_SIZE", "1024"))
    chunk = max(64, size // 8)
    s, lights = capture(size)
    images = da.from_array(s["images"], chunks=(12, chunk, chunk))
    mask = s["mask"]
    t = time.perf_counter()
    maps = psd.solve(images, lights, mask=mask, chunks=chunk)
    normals = maps["normals"].compute()
    status = maps["status"].compute()
    wall = time.perf_counter() - t
    # The single-process solve under the same capture-wide model, without hole filling
    # (which needs neighbours across tiles).
    single = ps.solve(s["images"], lights, mask=mask, fill=False, models=maps["models"])
    both = ~np.isnan(single.normals[..., 0])
    assert np.array_equal(both, ~np.isnan(normals[..., 0]))
    assert np.abs(normals[both] - single.normals[both]).max() <= 1e-6
    assert np.array_equal(status, single.status)
    err = np.degrees(np.arccos(np.clip(np.sum(normals[mask] * s["normals"][mask], -1), -1, 1)))
    assert err.mean() < 1.0
    # The model from a sample of rows is close to the one from every row.
    whole = ps.estimate_model(s["images"], lights, mask)[0]["sigma"]
    assert np.allclose(maps["models"][0]["sigma"], whole, rtol=0.2)
    peaks = client.run(lambda: __import__("resource").getrusage(0).ru_maxrss)
    print(
        f"\ndask {size}² x 12 in {chunk}² tiles on 2 workers: {wall:.2f} s; peak RSS per "
        f"worker {[round(v / 1024) for v in peaks.values()]} MiB; mean error {err.mean():.3f}°"
    )


def test_depth_of_the_assembled_normals(client):
    s, lights = capture(256)
    maps = psd.solve(da.from_array(s["images"], chunks=(12, 64, 64)), lights, mask=s["mask"], chunks=64)
    d = psd.integrate(maps["normals"], s["mask"], method="masked-ls")["depth"]
    single = ps.solve(s["images"], lights, mask=s["mask"], fill=False, models=maps["models"])
    ref = ps.integrate(single.normals, s["mask"], method="masked-ls")["depth"]
    m = s["mask"]
    assert np.abs(d[m] - ref[m]).max() < 1e-3


def test_bad_dask_input_is_named():
    s, lights = capture(64)
    with pytest.raises(ValueError, match="lights"):
        psd.solve(da.from_array(s["images"]), lights[:5])
    with pytest.raises(ValueError, match="chunks"):
        psd.solve(da.from_array(s["images"]), lights, chunks=2)
    with pytest.raises(TypeError, match="images"):
        psd.solve(s["images"].tolist(), lights)


def test_tiles_dark_under_a_light_and_outside_the_object(client):
    # No mask: tiles of the black background are dark in every image, which the whole capture
    # is not; they are solved as what they are (status "dark"), not refused.
    lights = ps.light_ring(8, 40.0)
    s = ps.render("sphere", 96, lights, cast_shadows=False)
    maps = psd.solve(s["images"], lights, chunks=32)
    normals = maps["normals"].compute()
    single = ps.solve(s["images"], lights, fill=False, models=maps["models"])
    assert np.array_equal(normals, single.normals, equal_nan=True)
    assert np.array_equal(maps["status"].compute(), single.status)
    # Residual and condition are NaN outside the mask, as the library's maps are.
    masked = psd.solve(s["images"], lights, mask=s["mask"], chunks=32)
    res = masked["residual"].compute()
    assert np.isnan(res[~s["mask"]]).all() and np.isfinite(res[s["mask"]]).all()


def test_tiles_subtract_an_ambient_frame(client):
    # Room light (8% of a lamp) in every image: tiles given the frame taken with every lamp off
    # subtract it as the single-process solve does (grey and RGB stacks, numpy and Dask
    # frames), and get the dark room's normals back; without it the normals flatten.
    lights = np.vstack([ps.light_ring(8, 30.0), ps.light_ring(8, 60.0, 20.0)])
    lit = ps.render("sphere", 96, lights, noise=0.003, ambient=0.08, seed=5)
    m = lit["mask"]

    def err(n):
        return np.degrees(np.arccos(np.clip(np.sum(n[m] * lit["normals"][m], -1), -1, 1))).mean()

    images, frame = lit["images"], lit["ambient"]
    rgb = (np.repeat(images[..., None], 3, 3), np.repeat(frame[..., None], 3, 2))
    for imgs, frm in ((images, frame), rgb):
        for f in (frm, da.from_array(frm, chunks=40)):
            stack = da.from_array(imgs, chunks=(16, 48, 48) + imgs.shape[3:])
            maps = psd.solve(stack, lights, mask=m, chunks=32, ambient=f)
            normals = maps["normals"].compute()
            single = ps.solve(imgs, lights, mask=m, fill=False, models=maps["models"], ambient=frm)
            both = ~np.isnan(single.normals[..., 0])
            assert np.array_equal(both, ~np.isnan(normals[..., 0]))
            assert np.abs(normals[both] - single.normals[both]).max() <= 1e-6
        with_frame = err(normals)
    left = err(psd.solve(images, lights, mask=m, chunks=32)["normals"].compute())
    assert with_frame < 0.6 and left > with_frame + 1.0, (with_frame, left)
    with pytest.raises(ValueError, match="stored as the images are"):
        psd.solve(images, lights, mask=m, chunks=32, ambient=frame[:-1])
    with pytest.raises(ValueError, match="stored as the images are"):
        psd.solve(images, lights, mask=m, chunks=32, ambient=frame.astype(np.float64))
    print(f"\ndask tiles, room light 8%: {left:.2f}° left in, {with_frame:.2f}° with its frame")


def test_tiles_judge_the_capture_wide_checks_as_one(client):
    # Room light (8% of a lamp, no frame) and one row of the lights turned by 10°: every tile
    # sees a part of the object, none could judge the lights or the shadows' light alone; their
    # counts and sums added say what the single-process solve says (the same light named, the
    # same directions, the same shadow level), and compute() warns as photostereo.solve does.
    lights = np.vstack([ps.light_ring(8, 30.0), ps.light_ring(8, 60.0, 20.0)])
    s = ps.render("sphere", 96, lights, noise=0.003, ambient=0.08, seed=6)
    wrong, l = turned(lights, 5, 10.0)
    m = s["mask"]
    # 16² tiles: the corner tiles hold no pixel of the sphere and add nothing.
    maps = psd.solve(da.from_array(s["images"], chunks=(16, 40, 40)), wrong, mask=m, chunks=16)
    assert not m[:16, :16].any()
    with pytest.warns(ps.PhotostereoWarning) as caught:
        out = psd.compute(maps)
    said = [str(w.message) for w in caught if issubclass(w.category, ps.PhotostereoWarning)]
    with pytest.warns(ps.PhotostereoWarning):
        single = ps.solve(s["images"], wrong, mask=m, fill=False, models=maps["models"])
    assert np.array_equal(out["normals"], single.normals, equal_nan=True)
    whole = single.model_summary
    tiles = out["model_summary"]
    a, b = tiles["light_agreement"][0], whole["light_agreement"][0]
    assert a["disagreeing"] == b["disagreeing"] == [5], (a, b)
    for x, y in zip(a["lights"], b["lights"]):
        assert x["pixels"] == y["pixels"]
        assert abs(x["disagreement_deg"] - y["disagreement_deg"]) < 1e-9
        assert np.abs(np.subtract(x["direction"], y["direction"])).max() < 1e-9
    assert tiles["shadow_light"] == whole["shadow_light"]
    assert whole["shadow_light"][0]["predicted_bias_deg"] > 1.0
    for kind in ("disagrees with the light given", "in attached shadow"):
        mine = [w for w in said if kind in w]
        theirs = [w for w in single.warnings if kind in w]
        assert len(mine) == 1 and mine == theirs, (kind, said, single.warnings)
    assert out["warnings"] == said
    print(
        f"\ndask tiles of 16², light 6 turned 10°: named at {a['lights'][5]['disagreement_deg']:.2f}° "
        f"(whole {b['lights'][5]['disagreement_deg']:.2f}°, threshold {a['threshold_deg']:.2f}°); "
        f"room light {tiles['shadow_light'][0]['level']:.4f} of a lit surface, "
        f"{tiles['shadow_light'][0]['predicted_bias_deg']:.2f}° (whole {whole['shadow_light'][0]['level']:.4f})"
    )
    # Under the rendered lights with the room light's frame: nothing to say.
    maps = psd.solve(s["images"], lights, mask=m, chunks=32, ambient=s["ambient"])
    with _no_photostereo_warning():
        clean = psd.compute(maps)
    assert clean["warnings"] == [] and clean["model_summary"]["light_agreement"][0]["disagreeing"] == []
    # The checks computed with one map in one call: the same as compute()'s, and every tile
    # solved once (the checks' graph shares the maps' tiles).
    calls = []
    solve_tile = psd._solve_tile
    psd._solve_tile = lambda *a, **k: calls.append(1) or solve_tile(*a, **k)
    try:
        maps = psd.solve(s["images"], lights, mask=m, chunks=32, ambient=s["ambient"])
        n, checks = dask.compute(maps["normals"], maps["checks"], scheduler="threads")
        assert len(calls) == 9, len(calls)
        # Stored elsewhere (as to_zarr stores) in the same call: once too.
        target = np.zeros(n.shape, np.float32)
        stored = da.store(maps["normals"], target, compute=False, lock=False)
        dask.compute(stored, maps["checks"], scheduler="threads")
        assert len(calls) == 18, len(calls)
    finally:
        psd._solve_tile = solve_tile
    assert np.array_equal(n, clean["normals"], equal_nan=True)
    assert np.array_equal(target, n, equal_nan=True)
    assert checks[0, 0]["light_agreement"] == clean["model_summary"]["light_agreement"]


def test_tiles_warn_of_the_counts_and_the_capture_as_one(client):
    # A capture whose first six images are 15% dimmer than their lights say, with a row of
    # saturated samples in another, pixels lit by two lights only and a light behind the
    # surface: every tile gives its
    # counts and the capture's own warnings, and compute() says what the single-process solve
    # says of them (the integrability check, which needs the assembled map, apart), each once.
    lights = np.vstack([ps.light_ring(8, 30.0), ps.light_ring(8, 55.0, 20.0)])
    s = ps.render("sphere", 96, lights, albedo=0.6, noise=0.003, seed=7, cast_shadows=False)
    # A 17th light behind the surface, lighting the rim that turns towards it.
    behind = np.array([0.3, 0.2, -0.5]) / np.linalg.norm([0.3, 0.2, -0.5])
    rim = 0.6 * np.clip(np.nan_to_num(s["normals"]) @ behind, 0, None).astype(np.float32)
    images = np.concatenate([s["images"], rim[None]])
    lights = np.vstack([lights, behind])
    images[:6] *= 0.85
    level = 0.7
    images[9, 48, 20:76] = level
    for y, x in ((40, 40), (41, 40), (60, 30)):
        images[2:, y, x] = 0.0
    m = s["mask"]
    maps = psd.solve(da.from_array(images, chunks=(17, 40, 40)), lights, mask=m, chunks=32,
                     saturation=level)
    with pytest.warns(ps.PhotostereoWarning) as caught:
        out = psd.compute(maps)
    said = [str(w.message) for w in caught if issubclass(w.category, ps.PhotostereoWarning)]
    with pytest.warns(ps.PhotostereoWarning):
        single = ps.solve(images, lights, mask=m, fill=False, models=maps["models"],
                          saturation=level)
    theirs = [w for w in single.warnings if not w.startswith("poor integrability")]
    for kind in ("behind", "56 saturated samples", "3 of ", "intensit"):
        assert sum(kind in w for w in theirs) == 1, (kind, theirs)
    assert out["warnings"] == said == theirs
    assert out["counts"] == single.counts
    assert out["counts"]["too_few_samples"] == 3


class _no_photostereo_warning:
    def __enter__(self):
        import warnings

        self._c = warnings.catch_warnings()
        self._c.__enter__()
        warnings.simplefilter("error", ps.PhotostereoWarning)

    def __exit__(self, *exc):
        return self._c.__exit__(*exc)
