"""Photometric stereo over the tiles of a Dask array: captures larger than one machine.

The per-pixel solve is independent per pixel once the capture-wide model (each image's noise
sigma and intensity gain, and the limit of the refit with specular lobes: what
``method="auto"`` estimates before fitting any pixel) is fixed.
So :func:`solve` estimates that model once, from a sample of rows spread over the capture,
then maps the library's solve over spatial tiles (all images of a tile in one chunk) under
that model, and returns lazy Dask arrays. Dask schedules the tiles: the same code runs on a
laptop's threads, a ``LocalCluster``, or a real cluster (dask-jobqueue, Dask Kubernetes)
unchanged; only the ``Client`` differs.

    >>> import dask.array as da, photostereo.dask as psd
    >>> images = da.from_zarr("capture.zarr")          # N x H x W, any chunks
    >>> maps = psd.solve(images, lights, mask=mask, chunks=512)
    >>> normals = maps["normals"].compute()             # or .to_zarr(...)
    >>> depth = psd.integrate(maps["normals"], mask)["depth"]

What needs neighbours across tiles is not done per tile: hole filling (``fill``) and the curl
(the integrability check) are left to the assembled maps (:func:`photostereo.integrate`
integrates them with the library's solver); pixels a tile could not solve keep their status
(``photostereo.STATUS``) and NaN normals.

What is judged over the whole capture is judged over all the tiles: the light left in the
attached shadows and each light against the others (a wrong row of the lights), and the
counts the warnings give (saturated and non-finite samples, pixels left without a normal).
Each tile returns its counts and sums, which add up to the whole's (the lights' check reads
every fourth column of a tile: the whole's columns where the tile side is a multiple of 4, as
the default is; saturated samples are counted in the bounding box of each tile's part of the
mask, the whole solve's in that of the whole mask), and the warnings about the capture as a
whole (lights behind the surface, corrected intensities), said once; ``maps["checks"]`` adds
them, and
:func:`compute` computes the maps and the checks in one pass over the tiles and warns as
:func:`photostereo.solve` does:

    >>> out = psd.compute(maps)                          # numpy arrays, model_summary, warnings
    >>> # or, writing the maps elsewhere, in the same pass over the tiles:
    >>> stored = maps["normals"].to_zarr("n.zarr", compute=False)
    >>> _, checks = dask.compute(stored, maps["checks"])   # checks[0, 0]: the dict
"""

from __future__ import annotations

import json
import numbers
import warnings as _warnings
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

import photostereo as _ps

try:
    import dask
    import dask.array as da
    from dask.sizeof import sizeof as _sizeof
except ImportError as e:  # pragma: no cover - exercised only without dask
    raise ImportError(
        "photostereo.dask needs dask: pip install 'photostereo[dask]' (or dask[array])"
    ) from e

__all__ = ["solve", "compute", "estimate_model", "integrate", "SAMPLE_BLOCK_ROWS"]

#: Rows per block of the sample the capture-wide model is estimated from.
SAMPLE_BLOCK_ROWS = 64
#: Most rows the model sample takes (in blocks spread evenly over the image).
MAX_SAMPLE_ROWS = 1024

# Planes of a solved tile, packed into one float32 array per tile.
_SCALARS = ("residual", "samples", "condition", "status", "robust")
# Those of them that are NaN outside the mask (the others are 0 there).
_NAN_OUTSIDE = ("residual", "condition")


def _as_dask(a: Any, name: str) -> "da.Array":
    if isinstance(a, da.Array):
        return a
    if isinstance(a, np.ndarray):
        return da.from_array(a, chunks=a.shape)
    raise TypeError(f"{name}: got a {type(a).__name__}; a dask or numpy array expected")


def _sample_rows(height: int, max_rows: int = MAX_SAMPLE_ROWS) -> np.ndarray:
    """Row indices of the model sample: blocks of SAMPLE_BLOCK_ROWS spread over the image."""
    if height <= max_rows:
        return np.arange(height)
    blocks = max(1, max_rows // SAMPLE_BLOCK_ROWS)
    starts = np.linspace(0, height - SAMPLE_BLOCK_ROWS, blocks).round().astype(int)
    return np.unique(np.concatenate([np.arange(s, s + SAMPLE_BLOCK_ROWS) for s in starts]))


def estimate_model(
    images: Any,
    lights: Any,
    mask: Any = None,
    *,
    max_rows: int = MAX_SAMPLE_ROWS,
    ambient: Any = None,
    **options: Any,
) -> List[Dict[str, Any]]:
    """The capture-wide models, estimated from at most ``max_rows`` rows of the capture (in
    blocks of :data:`SAMPLE_BLOCK_ROWS` spread evenly over it; every row of a smaller one).
    Only those rows are computed (of the images, the mask and the ``ambient`` frame, H x W or
    H x W x C, numpy or Dask, subtracted as :func:`photostereo.solve` subtracts it).
    ``options`` as :func:`photostereo.solve` (``method``, ``color``, ``intensities``,
    ``transfer``, ``saturation``)."""
    images = _as_dask(images, "images")
    frame = None if ambient is None else _as_dask(ambient, "ambient")
    rows = _sample_rows(images.shape[1], max_rows)
    m = None
    if mask is not None:
        m = _ps._mask(np.asarray(_as_dask(mask, "mask")[rows].compute()))
        if not m.any():
            # No object pixel in the sample: fall back to the whole mask's rows.
            full = _ps._mask(np.asarray(_as_dask(mask, "mask").compute()))
            rows = np.flatnonzero(full.any(axis=1))[:max_rows]
            m = full[rows]
    sample = np.asarray(images[:, rows].compute())
    if frame is not None:
        options["ambient"] = np.asarray(frame[rows].compute())
    return _ps.estimate_model(sample, lights, m, **options)


class _Tile:
    """A solved tile: its planes and its checks' text (None where the tile's mask is empty). The
    block of the internal tiles array; its size is what Dask's memory accounting sees."""

    __slots__ = ("planes", "checks")

    def __init__(self, planes: np.ndarray, checks: Optional[str]) -> None:
        self.planes = planes
        self.checks = checks


@_sizeof.register(_Tile)
def _sizeof_tile(t: _Tile) -> int:
    return int(t.planes.nbytes) + len(t.checks or "")


def _solve_tile(
    block: np.ndarray,
    mask_block: Optional[np.ndarray],
    ambient_block: Optional[np.ndarray],
    *,
    lights: np.ndarray,
    models: List[Dict[str, Any]],
    albedo_channels: int,
    options: Dict[str, Any],
) -> _Tile:
    """One tile: N x h x w[ x C] images (and an h x w mask, an h x w[ x C] ambient frame) ->
    its h x w x K float32 planes (normals (3), albedo (1 or 3), then _SCALARS) and its checks
    as text (None where the tile's mask is empty)."""
    h, w = block.shape[1], block.shape[2]
    base = 3 + albedo_channels
    # Outside the mask, as the library's maps: NaN normals, albedo, residual and condition;
    # no samples, status 0 ("outside the mask"), not robust.
    out = np.full((h, w, base + len(_SCALARS)), np.nan, dtype=np.float32)
    for i, key in enumerate(_SCALARS):
        if key not in _NAN_OUTSIDE:
            out[..., base + i] = 0.0
    if mask_block is not None and not mask_block.any():
        return _Tile(out, None)
    with _warnings.catch_warnings():
        # A tile's warnings speak of its own counts; what they add up to, and the capture's own
        # warnings said once, come from its checks, added over the tiles (_add_checks).
        _warnings.simplefilter("ignore", _ps.PhotostereoWarning)
        r = _ps.solve(
            block, lights, mask_block, fill=False, models=models, ambient=ambient_block,
            **options,
        )
    out[..., 0:3] = r.normals
    alb = r.albedo if r.albedo.ndim == 3 else r.albedo[..., None]
    out[..., 3 : 3 + albedo_channels] = alb
    for i, key in enumerate(_SCALARS):
        out[..., 3 + albedo_channels + i] = getattr(r, key)
    return _Tile(out, r.checks)


def _planes_of(tile: _Tile) -> np.ndarray:
    return tile.planes


def _checks_of(tile: _Tile) -> np.ndarray:
    text = np.empty((1, 1), dtype=object)
    text[0, 0] = tile.checks
    return text


def _add_checks(texts: np.ndarray, ambient_subtracted: bool) -> np.ndarray:
    """Every tile's checks (an object array of texts, None where a tile solved nothing) added:
    a 1 x 1 object array holding what the whole capture's solve would say of them."""
    parts = [t for t in texts.ravel() if t]
    r = _ps._native.add_checks(parts, ambient_subtracted)
    out = np.empty((1, 1), dtype=object)
    out[0, 0] = {
        "shadow_light": json.loads(r["shadow_light"]),
        "light_agreement": json.loads(r["light_agreement"]),
        "counts": json.loads(r["counts"]),
        "warnings": list(r["warnings"]),
    }
    return out


def solve(
    images: Any,
    lights: Any,
    mask: Any = None,
    *,
    chunks: int = 512,
    models: Optional[Sequence[Dict[str, Any]]] = None,
    intensities: Any = None,
    method: str = "auto",
    color: str = "grey",
    transfer: str = "auto",
    saturation: Optional[float] = None,
    ambient: Any = None,
) -> Dict[str, "da.Array"]:
    """Photometric stereo over ``chunks`` x ``chunks`` tiles of a Dask (or numpy) array.

    Args:
        images: N x H x W or N x H x W x C (as :func:`photostereo.solve`); rechunked so that
            each tile holds all N images (and all channels).
        lights: N x 3 directions. mask: H x W bool (numpy or dask), default every pixel.
        chunks: tile side in pixels.
        models: the capture-wide models; default :func:`estimate_model` on a sample of rows.
        intensities, method, color, transfer, saturation: as :func:`photostereo.solve`.
        ambient: the frame taken with every lamp off (H x W or H x W x C, numpy or Dask,
            stored as each image is), tiled as the images are and subtracted in each tile as
            :func:`photostereo.solve` subtracts it. Without it, ``checks`` measures the light
            left in the attached shadows over all the tiles, as a whole-capture solve does.

    Returns:
        Lazy arrays: ``normals`` (H x W x 3), ``albedo`` (H x W, or H x W x 3 for a colour
        solve), ``residual``, ``samples``, ``condition``, ``status`` (uint8), ``robust``
        (bool), ``solved`` (bool); ``models`` (the models used, a list of dicts); and
        ``checks``, a 1 x 1 object array whose element is the capture-wide checks added over
        the tiles: a dict with ``shadow_light`` and ``light_agreement`` (as
        ``model_summary``'s of :func:`photostereo.solve`), ``counts`` (the pixel outcomes) and
        ``warnings`` (every warning of the tiles added up: see :func:`compute`).
        Compute it in the same call as the maps (:func:`compute`, or ``dask.compute`` of the
        arrays), or the tiles are solved twice.
    """
    images = _as_dask(images, "images")
    if images.ndim not in (3, 4):
        raise ValueError(
            f"images: shape {images.shape}; N x H x W or N x H x W x C expected"
        )
    if not isinstance(chunks, numbers.Integral) or isinstance(chunks, bool) or chunks < 8:
        raise ValueError(f"chunks: {chunks!r}; a tile side of at least 8 pixels expected")
    lights = np.ascontiguousarray(np.asarray(lights, dtype=np.float64))
    n, h, w = images.shape[:3]
    if lights.shape != (n, 3):
        raise ValueError(f"lights: shape {lights.shape}; one row per image ({n} x 3) expected")
    options = dict(
        intensities=intensities, method=method, color=color, transfer=transfer,
        saturation=saturation,
    )
    chunks = int(chunks)
    spatial = (chunks, chunks)
    images = images.rechunk((n,) + spatial + ((images.shape[3],) if images.ndim == 4 else ()))
    mask_d = None
    if mask is not None:
        mask_d = _as_dask(mask, "mask")
        if mask_d.shape != (h, w):
            raise ValueError(f"mask: shape {mask_d.shape} differs from the images' {(h, w)}")
        # Numbers > 0 are set, as photostereo.solve reads a mask.
        mask_d = (mask_d if mask_d.dtype == bool else mask_d > 0).rechunk(spatial)
    frame_d = None
    if ambient is not None:
        frame_d = _as_dask(ambient, "ambient")
        if frame_d.shape != images.shape[1:] or frame_d.dtype != images.dtype:
            raise ValueError(
                f"ambient: {frame_d.shape} {frame_d.dtype} but each image is "
                f"{images.shape[1:]} {images.dtype}; the frame taken with every lamp off must be "
                "stored as the images are"
            )
        frame_d = frame_d.rechunk(spatial + ((images.shape[3],) if images.ndim == 4 else ()))
    if models is None:
        models = estimate_model(images, lights, mask_d, ambient=frame_d, **options)
    models = list(models)
    albedo_channels = 1 if color in ("grey", "gray") or images.ndim == 3 else 3
    planes = 3 + albedo_channels + len(_SCALARS)
    # Each output block is one tile's h x w x planes: the image (and channel) axes, one chunk
    # each, are contracted into the tile function's input.
    kwargs = dict(lights=lights, models=models, albedo_channels=albedo_channels, options=options)
    mask_arg = (mask_d, "yx") if mask_d is not None else (None, None)
    frame_arg = (
        (frame_d, "yxc" if images.ndim == 4 else "yx") if frame_d is not None else (None, None)
    )
    # One _Tile per 1 x 1 block: a tile's planes and its checks, taken apart below so that the
    # planes are freed once used, whatever the checks still wait for.
    tiles = da.blockwise(
        _solve_tile, "yx",
        images, "nyxc" if images.ndim == 4 else "nyx",
        *mask_arg,
        *frame_arg,
        adjust_chunks={"y": 1, "x": 1}, concatenate=True, dtype=object,
        meta=np.empty((0, 0), dtype=object), **kwargs,
    )
    packed = tiles.map_blocks(
        _planes_of, chunks=(images.chunks[1], images.chunks[2], (planes,)), new_axis=2,
        dtype=np.float32, meta=np.empty((0, 0, 0), dtype=np.float32),
    )
    # The checks stay a Dask array (one 1 x 1 block), so that computed with the maps in one
    # call the tiles are one graph's shared tasks and are solved once.
    parts = tiles.map_blocks(_checks_of, dtype=object, meta=np.empty((0, 0), dtype=object))
    checks = parts.rechunk(parts.numblocks).map_blocks(
        _add_checks, frame_d is not None, chunks=((1,), (1,)), dtype=object,
        meta=np.empty((0, 0), dtype=object),
    )
    a0 = 3
    out: Dict[str, Any] = {
        "normals": packed[..., 0:3],
        "albedo": packed[..., a0] if albedo_channels == 1 else packed[..., a0 : a0 + 3],
    }
    base = a0 + albedo_channels
    for i, key in enumerate(_SCALARS):
        out[key] = packed[..., base + i]
    out["samples"] = out["samples"].astype(np.uint16)
    out["status"] = out["status"].astype(np.uint8)
    out["robust"] = out["robust"] > 0
    out["solved"] = (out["status"] == 1) | (out["status"] == 5)
    out["models"] = models
    out["checks"] = checks
    return out


def compute(maps: Dict[str, Any], **kwargs: Any) -> Dict[str, Any]:
    """Computes every map of :func:`solve` and its capture-wide checks in one pass over the
    tiles (``kwargs`` go to ``dask.compute``), and issues the checks' warnings as
    :class:`photostereo.PhotostereoWarning`, as :func:`photostereo.solve` does.

    Returns:
        The maps as numpy arrays, ``models``, ``model_summary`` (``shadow_light`` and
        ``light_agreement``, as :func:`photostereo.solve`'s), ``counts`` (the pixel outcomes
        over all the tiles, as :func:`photostereo.solve`'s) and ``warnings`` (what the
        single-process solve without hole filling warns of, but the integrability check:
        see the module's documentation).
    """
    keys = [k for k, v in maps.items() if isinstance(v, da.Array) and k != "checks"]
    *values, checks = dask.compute(*[maps[k] for k in keys], maps["checks"], **kwargs)
    checks = checks[0, 0]
    out: Dict[str, Any] = dict(zip(keys, values))
    out["models"] = maps.get("models")
    out["model_summary"] = {
        "shadow_light": checks["shadow_light"],
        "light_agreement": checks["light_agreement"],
    }
    out["counts"] = checks["counts"]
    out["warnings"] = checks["warnings"]
    for w in checks["warnings"]:
        _warnings.warn(w, _ps.PhotostereoWarning, stacklevel=2)
    return out


def integrate(
    normals: Any, mask: Any = None, method: str = "auto", K: Any = None
) -> Dict[str, Any]:
    """Assembles ``normals`` (a Dask array from :func:`solve`) and integrates them with the
    library's solver (:func:`photostereo.integrate`): depth needs the whole surface at once."""
    n = np.asarray(normals.compute() if hasattr(normals, "compute") else normals, dtype=np.float32)
    m = None
    if mask is not None:
        m = np.asarray(mask.compute() if hasattr(mask, "compute") else mask, dtype=bool)
    return _ps.integrate(n, m, method=method, K=K)
