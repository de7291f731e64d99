"""photostereo: photographs of an object under known lights -> albedo, normals and depth.

The Python face of the photostereo Rust library: the same stages, on numpy arrays, with the
GIL released while they work.

    >>> import numpy as np, photostereo as ps
    >>> lights = ps.light_ring(8, 45.0)
    >>> scene = ps.render("sphere", 64, lights)
    >>> result = ps.solve(scene["images"], lights, mask=scene["mask"])
    >>> depth = ps.integrate(result.normals, result.solved)["depth"]

Conventions (as the library's): camera frame x right, y up, z towards the camera; image row 0
is the top; light directions point from the surface towards the light; normals point out of
the surface.

Images are N x H x W (grey) or N x H x W x C (C = 1, 2, 3 or 4; alpha ignored) arrays of
uint8, uint16, float32 or float64, one image per light along the first axis, any strides.
They are converted as image files of the same samples are: integers scaled to [0, 1] by their
largest code (which marks a sample saturated; saturated samples are left out of the fit),
uint8 decoded from sRGB unless ``transfer="linear"``, each image divided by its light's
intensity, then mixed to grey (BT.601) or kept per channel (``color``).

Errors are raised as :class:`Error` (a ``ValueError``) naming the parameter, image or file;
``TypeError`` for arrays of the wrong type; ``OSError`` for files. Things worth knowing about
a result that was still computed are issued as :class:`PhotostereoWarning` and listed in
``result.warnings``.
"""

from __future__ import annotations

import json
import os
import warnings as _warnings
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np

from . import _native
from ._native import Error

__all__ = [
    "Error",
    "PhotostereoWarning",
    "Capture",
    "Solution",
    "STATUS",
    "METHODS",
    "INTEGRATORS",
    "load",
    "solve",
    "estimate_model",
    "convert",
    "integrate",
    "render",
    "light_ring",
    "reflectance_map",
    "calibrate",
    "sfs",
    "SFS_METHODS",
    "read_image",
    "read_mask",
    "read_exr",
    "write_exr",
    "__version__",
]

__version__: str = _native.version()

#: Per-pixel outcome codes of ``Solution.status``.
STATUS: Dict[int, str] = {
    0: "outside the mask",
    1: "solved",
    2: "too few usable samples",
    3: "ill-conditioned light set",
    4: "dark in every image",
    5: "filled from its neighbours",
}

#: The per-pixel estimators (``method`` of :func:`solve`).
METHODS = ("auto", "ls", "threshold", "weighted", "trim", "huber", "tukey", "l1", "specular")

#: The normal integrators (``method`` of :func:`integrate`).
INTEGRATORS = ("auto", "masked-ls", "poisson", "path", "fc", "bilateral")

PathLike = Union[str, "os.PathLike[str]"]


class PhotostereoWarning(UserWarning):
    """Something the user should know about a result that was still computed."""


def _f64_2d(value: Any, name: str, width: Optional[int] = None) -> np.ndarray:
    """``value`` as a C-contiguous float64 matrix, or a ValueError naming ``name``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name}: cannot be read as numbers ({e})") from None
    if a.ndim == 1 and width == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise ValueError(f"{name}: shape {a.shape}; a matrix (N x 3) expected")
    return np.ascontiguousarray(a)


def _intensities(value: Any) -> Optional[np.ndarray]:
    if value is None:
        return None
    return _f64_2d(value, "intensities", width=1)


def _check_array(value: Any, name: str) -> np.ndarray:
    """``value`` if it is a numpy array the library can read in place; a native-endian,
    aligned copy of a byte-swapped or misaligned one; TypeError for anything else."""
    if not isinstance(value, np.ndarray):
        raise TypeError(
            f"{name}: got a {type(value).__name__}; a numpy array expected "
            f"(np.asarray(...) it, or load it with photostereo.load)"
        )
    if not value.dtype.isnative or not value.flags.aligned:
        value = value.astype(value.dtype.newbyteorder("="))
    return value


def _mask(value: Any, name: str = "mask") -> Optional[np.ndarray]:
    """A mask as an H x W bool array: bool as given, numbers > 0 set; None stays None."""
    if value is None:
        return None
    m = np.asarray(value)
    if m.dtype == np.bool_:
        return _check_array(m, name)
    if np.issubdtype(m.dtype, np.integer) or np.issubdtype(m.dtype, np.floating):
        return m > 0
    raise TypeError(
        f"{name}: got an array of dtype {m.dtype}; bool (or numbers, > 0 meaning set) expected"
    )


def _int(value: Any, name: str, low: int, high: int) -> int:
    """An integer argument in [low, high], or ValueError/TypeError naming it."""
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: got {value!r}; an integer expected") from None
    if v != value or not low <= v <= high:
        raise ValueError(f"{name}: {value!r}; an integer from {low} to {high} expected")
    return v


@dataclass
class Capture:
    """A capture read from files: the images as stored, their lights, intensities and mask.

    ``images`` is N x H x W x C in the files' own type (uint8, uint16 or float32), exactly what
    :func:`solve` converts as the command-line tool does.
    """

    images: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    mask: Optional[np.ndarray]
    files: List[str]
    #: The frame taken with every lamp off (H x W x C, as the images), when one was given.
    ambient: Optional[np.ndarray] = None

    def solve(self, **options: Any) -> "Solution":
        """:func:`solve` on this capture (its intensities, mask and ambient frame)."""
        if self.ambient is not None:
            options.setdefault("ambient", self.ambient)
        return solve(
            self.images, self.lights, mask=self.mask, intensities=self.intensities, **options
        )


def _with_ambient(images: np.ndarray, ambient: Any) -> np.ndarray:
    """The images with the ambient frame appended as a last image (the native solve takes
    it from there), after checking that it is stored as each image is."""
    frame = np.asarray(ambient)
    if frame.dtype != images.dtype or frame.shape != images.shape[1:]:
        raise Error(
            f"ambient: {frame.shape} {frame.dtype} but each image is {images.shape[1:]} "
            f"{images.dtype}; the frame taken with every lamp off must be stored as the images are"
        )
    return np.concatenate([images, frame[None]])


@dataclass
class Solution:
    """What :func:`solve` returns: per-pixel maps (H x W numpy arrays) and summaries."""

    #: Unit normals, H x W x 3 (n_x, n_y, n_z), NaN where none was found.
    normals: np.ndarray
    #: Albedo: H x W, or H x W x 3 for a colour solve; NaN where no normal.
    albedo: np.ndarray
    #: RMS residual of the fit over the samples used (image units).
    residual: np.ndarray
    #: Samples used per pixel (uint16).
    samples: np.ndarray
    #: Condition number of the lights the pixel used: its confidence (lower is better).
    condition: np.ndarray
    #: Outcome per pixel (uint8, see :data:`STATUS`).
    status: np.ndarray
    #: Pixels with a normal (bool).
    solved: np.ndarray
    #: Pixels fitted by a robust estimator (bool).
    robust: np.ndarray
    #: Curl of the gradient field (the integrability check; 0 for a true surface).
    curl: np.ndarray
    #: Pixel outcome counts.
    counts: Dict[str, int]
    #: Summary of |curl|.
    integrability: Dict[str, Any]
    #: How much model the data needed (robust pixels, intensity corrections, noise).
    model_summary: Dict[str, Any]
    #: The capture-wide models the solve used (pass to ``solve(..., models=...)``).
    models: List[Dict[str, Any]]
    #: Things the user should know about this result (also issued as PhotostereoWarning).
    warnings: List[str] = field(default_factory=list)
    #: Wall time of the solve and the normals, seconds.
    solve_seconds: float = 0.0
    #: The capture-wide checks (shadow light, each light against the others) as counts and
    #: sums that add up over the parts of a capture, with the pixel and sample counts and the
    #: capture's own warnings (JSON text; :mod:`photostereo.dask` adds its tiles' and judges
    #: and warns of them as one).
    checks: str = ""

    def __getitem__(self, key: str) -> Any:
        return getattr(self, key)


def solve(
    images: np.ndarray,
    lights: Any,
    mask: Optional[np.ndarray] = None,
    *,
    intensities: Any = None,
    method: str = "auto",
    color: str = "grey",
    transfer: str = "auto",
    saturation: Optional[float] = None,
    fill: Optional[bool] = None,
    models: Optional[Sequence[Dict[str, Any]]] = None,
    ambient: Optional[np.ndarray] = None,
) -> Solution:
    """Per-pixel photometric stereo: g = rho N from every image, robustly.

    Args:
        images: N x H x W or N x H x W x C array (uint8, uint16, float32, float64).
        lights: N x 3 light directions (camera frame, towards the light; normalised here).
        mask: H x W bool array of object pixels (default: every pixel). Only its bounding box
            is converted.
        intensities: per light, N x 1 (or N) or N x 3 (R, G, B); images are divided by them.
        method: the estimator, one of :data:`METHODS` (``"auto"``: least squares with shadow
            rejection where Lambert's law fits, specular rejection where it does not).
        color: ``"grey"`` (BT.601 mix), ``"shared"`` (one normal, RGB albedo) or
            ``"per-channel"`` (three solves).
        transfer: ``"auto"`` (sRGB for uint8, linear otherwise), ``"linear"`` or ``"srgb"``.
        saturation: stored level (integers scaled to [0, 1]) at or above which a sample is
            saturated; default the largest code for integers, none for floats.
        fill: fill holes in the mask from neighbouring normals (reported as status 5);
            default: inside a given mask only, as the command-line tool does.
        models: the capture-wide models to solve under (from :func:`estimate_model` on the
            whole capture) instead of estimating them from these images: for a capture
            solved in parts (see :mod:`photostereo.dask`).
        ambient: the frame taken with every lamp off (H x W or H x W x C, stored as each
            image: same dtype and shape), converted as each image is (transfer function,
            intensity) and subtracted from it; without it, ``model_summary["shadow_light"]``
            measures the light left in the attached shadows and a warning says when it bends
            the normals.

    Returns:
        A :class:`Solution`.
    """
    images = _check_array(images, "images")
    lights = _f64_2d(lights, "lights")
    r = _native.solve(
        images if ambient is None else _with_ambient(images, ambient),
        lights,
        _mask(mask),
        _intensities(intensities),
        method,
        color,
        transfer,
        saturation,
        fill,
        list(models) if models is not None else None,
        ambient is not None,
    )
    for w in r["warnings"]:
        _warnings.warn(w, PhotostereoWarning, stacklevel=2)
    for key in ("counts", "integrability", "model_summary"):
        r[key] = json.loads(r[key])
    return Solution(**r)


def estimate_model(
    images: np.ndarray,
    lights: Any,
    mask: Optional[np.ndarray] = None,
    *,
    intensities: Any = None,
    method: str = "auto",
    color: str = "grey",
    transfer: str = "auto",
    saturation: Optional[float] = None,
    ambient: Optional[np.ndarray] = None,
) -> List[Dict[str, Any]]:
    """The capture-wide models (noise sigma and intensity gains per image, and ``lobe_limit``,
    the relative-residual limit of ``auto``'s refit with specular lobes) a solve of these
    images would estimate: estimate them once on the whole capture (or a sample of its rows)
    and pass them to :func:`solve` for each part. Arguments as :func:`solve`."""
    images = _check_array(images, "images")
    return _native.estimate_model(
        images if ambient is None else _with_ambient(images, ambient),
        _f64_2d(lights, "lights"),
        _mask(mask),
        _intensities(intensities),
        method,
        color,
        transfer,
        saturation,
        ambient is not None,
    )


def convert(
    images: np.ndarray,
    lights: Any,
    *,
    intensities: Any = None,
    color: str = "grey",
    transfer: str = "auto",
    saturation: Optional[float] = None,
):
    """The images as the solver sees them: float32 linear radiance divided by the intensities,
    N x H x W (grey) or N x H x W x 3, and the N x H x W bool saturation flags."""
    images = _check_array(images, "images")
    return _native.convert(
        images, _f64_2d(lights, "lights"), _intensities(intensities), color, transfer, saturation
    )


def integrate(
    normals: np.ndarray,
    mask: Optional[np.ndarray] = None,
    method: str = "auto",
    K: Any = None,
) -> Dict[str, Any]:
    """Normals (H x W x 3 float32) -> depth.

    Args:
        normals: normals in the camera frame (x right, y up, z towards the viewer), of any
            length: the integration reads their directions, so ``g = albedo * n`` integrates
            as ``n``. NaN and the zero vector are "no normal": no depth there.
        mask: H x W bool domain (default: the pixels with a normal: finite and not the zero
            vector, so that NaN and zeros, the usual "no normal", are left out).
        method: one of :data:`INTEGRATORS`; ``"auto"`` chooses masked least squares, or the
            bilateral integrator when the normals show depth jumps (reported as ``method``).
        K: 3 x 3 pinhole intrinsics (pixels) for perspective integration; None: orthographic.

    Returns:
        ``{"depth": H x W (orthographic: height towards the camera in pixel units; perspective:
        depth up to scale), "residual": H x W, "method": str (the integrator that ran),
        "iterations": int, "auto": dict or None (the figures behind auto's choice), "reason":
        str or None (auto's choice in words), "solve": dict or None (the linear solve:
        ``unknowns``, ``method``, ``iterations`` and ``convergence``: "exact", "residual",
        "data-noise", or "iteration-limit" / "breakdown" when it did not converge),
        "closed_off": dict or None (bilateral only: ``regions``, ``pixels`` and ``largest`` of
        the regions that depth jumps close off all around, whose offset from the rest is not
        in the normals and is a guess), "warnings": list of str (pixels of the mask without a
        normal, a solve that did not converge, regions whose depth offset is a guess; each
        also issued as :class:`PhotostereoWarning`)}``; NaN outside the mask.
    """
    normals = _check_array(normals, "normals")
    if normals.dtype != np.float32:
        if normals.dtype == np.float64:
            normals = normals.astype(np.float32)
        else:
            raise TypeError(f"normals: dtype {normals.dtype}; float32 or float64 expected")
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"normals: shape {normals.shape}; H x W x 3 expected")
    k = None if K is None else _f64_2d(K, "K")
    r = _native.integrate(normals, _mask(mask), method, k)
    for key in ("auto", "solve", "closed_off"):
        if r[key] is not None:
            r[key] = json.loads(r[key])
    for w in r["warnings"]:
        _warnings.warn(w, PhotostereoWarning, stacklevel=2)
    return r


def render(
    scene: str,
    size: int,
    lights: Any,
    *,
    material: str = "lambert",
    material_params: Optional[Dict[str, float]] = None,
    albedo: float = 0.8,
    noise: float = 0.0,
    seed: int = 0,
    cast_shadows: bool = True,
    light_radius_deg: Optional[float] = None,
    ambient: float = 0.0,
    pixel_samples: int = 1,
) -> Dict[str, np.ndarray]:
    """Renders a named scene (``"sphere"``, ``"vase"``, ``"peaks"``, ``"torus"``, ``"bumps"``,
    ``"groove"``, ``"bowl"``, ``"relief"``, ``"step"``, ``"ramp"``, ``"ellipsoid"``,
    ``"bust"``, ``"demo"``) at size x size pixels under ``lights`` (N x 3), with a reflectance model
    (``"lambert"``, ``"oren-nayar"``, ``"phong"``, ``"blinn-phong"``, ``"torrance-sparrow"``,
    ``"ward"``, ``"mirror"``; parameters ``ks``, ``shininess``, ``roughness``, ``f0``,
    ``alpha_x``, ``alpha_y``, ``sigma``), cast shadows and Gaussian noise. ``light_radius_deg``
    is each distant light's angular radius (the size of mirror highlights; default the
    renderer's 1.5); ``ambient`` adds ambient x albedo to every pixel (a ball's outline in a
    lit room); ``pixel_samples`` (n x n per pixel) integrates mirror highlights over the
    pixel's area, as a camera does.

    Returns ``{"images": N x H x W float32, "lights", "normals": H x W x 3, "depth", "albedo",
    "mask", "cast_shadows": N x H x W bool, "attached_shadows"}`` (truth NaN outside the mask),
    and with ``ambient`` > 0 ``"ambient"``: H x W, the frame with every lamp off (the ambient
    light through the same camera noise), which a rig would subtract.
    """
    return _native.render(
        scene,
        _int(size, "size", 8, 8192),
        _f64_2d(lights, "lights"),
        material,
        material_params,
        float(albedo),
        float(noise),
        _int(seed, "seed", 0, 2**64 - 1),
        bool(cast_shadows),
        None if light_radius_deg is None else float(light_radius_deg),
        float(ambient),
        _int(pixel_samples, "pixel_samples", 1, 16),
    )


def light_ring(count: int, elevation_deg: float, azimuth0_deg: float = 0.0) -> np.ndarray:
    """``count`` light directions (N x 3) evenly spaced in azimuth at ``elevation_deg`` above
    the image plane."""
    return _native.light_ring(
        _int(count, "count", 1, 65536), float(elevation_deg), float(azimuth0_deg)
    )


def reflectance_map(
    light: Sequence[float],
    material: str = "lambert",
    material_params: Optional[Dict[str, float]] = None,
    extent: float = 2.0,
    size: int = 256,
) -> np.ndarray:
    """R(p, q) under one distant light, sampled on a size x size grid over
    [-extent, extent]^2 of the gradient (p, q) = (dz/dx, dz/dy); row 0 is q = +extent."""
    light = [float(v) for v in light]
    if len(light) != 3:
        raise ValueError(f"light: {len(light)} values; x, y, z expected")
    return _native.reflectance_map(
        light, material, material_params, float(extent), _int(size, "size", 2, 8192)
    )


#: The shape-from-shading methods (``method`` of :func:`sfs`).
SFS_METHODS = ("horn", "tsai-shah", "fast-marching", "perspective")


def _vec3(value: Any, name: str) -> Optional[List[float]]:
    if value is None:
        return None
    v = np.asarray(value, dtype=np.float64).ravel()
    if v.shape != (3,):
        raise ValueError(f"{name}: {v.size} values; x, y, z expected")
    return [float(x) for x in v]


def _float(value: Any, name: str) -> Optional[float]:
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: got {value!r}; a number expected") from None


def sfs(
    image: np.ndarray,
    mask: Optional[np.ndarray] = None,
    *,
    light: Optional[Sequence[float]] = None,
    albedo: Optional[float] = None,
    method: Optional[str] = None,
    material: str = "lambert",
    material_params: Optional[Dict[str, float]] = None,
    transfer: str = "auto",
    boundary: str = "occluding",
    iterations: int = 0,
    smoothness: Optional[float] = None,
    shadow_level: Optional[float] = None,
    camera: Any = None,
    light_position: Optional[Sequence[float]] = None,
    light_intensity: Optional[float] = None,
    refine: bool = True,
    refine_smoothness: Optional[float] = None,
    refine_iterations: int = 0,
    coarse_to_fine: bool = True,
    outline_repair: bool = True,
    restarts: bool = True,
    start: Optional[np.ndarray] = None,
) -> Dict[str, Any]:
    """Shape from shading of one image, as the ``photostereo sfs`` command.

    ``image``: H x W, or H x W x 3 mixed to grey (BT.601) as the command mixes a colour file;
    uint8, uint16, float32 or float64, integers scaled to [0, 1] by their largest code and
    ``transfer`` as :func:`solve`'s (``"auto"``: uint8 decoded from sRGB, everything else
    linear; ``"linear"``; ``"srgb"``).

    Distant light, orthographic camera (``method`` ``"horn"``, the default without
    ``light_position``; ``"tsai-shah"``; ``"fast-marching"`` for a light at the viewer):
    ``light`` is the direction towards the light (x right, y up, z towards the camera) and
    ``albedo`` the surface's; either one left out is estimated from the image (Zheng and
    Chellappa 1991: a Lambertian surface with sphere-like normals assumed), and a reflectance
    other than Lambert's needs both. ``boundary``: ``"occluding"`` (the mask's edge is an
    occluding contour, except where the image shows it is none: brighter than a surface turning
    away can be, as at a cut end; the report's "occluding" counts those pixels, and above 5% of
    the outline a warning says so) or ``"free"``; ``smoothness``: Horn's final weight (1e-4);
    ``shadow_level``: pixels darker than this fraction of the albedo are in shadow (0.01);
    ``coarse_to_fine``: ``"horn"`` first solves the image's 2 x 2 block means where the mask
    keeps 3000 pixels at half resolution (the command's ``--single-resolution`` is
    ``coarse_to_fine=False``; refused for the other methods); ``outline_repair``: when
    ``"horn"``'s result contradicts the occluding boundary on an image too small for a
    coarse-to-fine start, it solves the image again upsampled 2x and returns that result if it
    honours the boundary (the report's "outline_repair" says what was done; the command's
    ``--no-outline-repair`` is ``outline_repair=False``); ``restarts``: ``"horn"`` repeats its
    continuation in the smoothness weight from its own result while that lowers the energy
    without contradicting the occluding boundary (the report's "restarts" counts the repeats
    kept; ``restarts=False``, the command's ``--no-restarts``, runs it once: faster, and on
    most shapes less accurate); ``start``: a height map (towards the camera, in its own pixels,
    as ``"depth"`` below; NaN where unknown) that ``"horn"`` refines at the final smoothness
    instead of solving from its convex or plane start, with no continuation, coarse-to-fine
    start, repeat or outline repair: the result is the solution nearest it (a sensor's or a
    coarse reconstruction's depth whose detail the shading is to add; the command's
    ``--start DEPTH.exr``). It may be H x W or the same field of view at another resolution
    (h x w such that one factor rounds the one size to the other; a row or column short is a
    crop, and refused): it is resampled to the image's (a finer one averaged first), its
    heights scaled with it, and its samples inside the mask without a height are filled by
    biharmonic interpolation; ``"start_scale"`` (image pixels a start pixel) and ``"start_filled"``
    (samples filled) in the result say what was done (None without a start).

    Pinhole camera and a point light with fall-off (``"perspective"``, Prados and Faugeras
    2005, the default when ``light_position`` is given): ``camera`` is the 3 x 3 intrinsics K,
    ``light_position`` the light in the camera frame (in the unit of depth; (0, 0, 0) at the
    camera centre), ``light_intensity`` and ``albedo`` its intensity and the surface's (1 when
    not given, which a warning says); ``shadow_level`` is then a fraction of the image's 99th
    percentile. The swept solution is refined variationally unless ``refine=False``
    (``refine_smoothness``, 0.01; ``refine_iterations``).

    ``material`` and ``material_params`` as :func:`render`, with its parameter defaults (so that
    a scene rendered and solved with the same material agrees; the command's ``--brdf``
    defaults differ: Oren-Nayar 20 degrees, specular 0.5, shininess 40). Any of them but the
    mirror, whose reflection shading does not show; a non-Lambertian one with the perspective
    method needs the light at the camera centre. ``mask``: H x W bool; None: the non-black
    pixels connected inside the image's border (a warning says so: attached shadows touching
    the background are left out).

    Returns ``{"depth": H x W (orthographic: height towards the camera in pixels; perspective:
    absolute depth along the optical axis), "normals": H x W x 3, "residual", "shadow": H x W
    bool, "mask", "method", "light": the direction used (perspective: from the surface's
    centre to the light), "albedo", "light_source" and "albedo_source" ("given", "estimated"
    or "assumed"), "estimate": dict or None, "report": dict (iterations, convergence,
    assumptions, warnings, the refinement, and for horn with an occluding boundary and for
    perspective "outline": how well the normals beside the mask's outline agree with it),
    "warnings": list,
    "start_scale", "start_filled": with ``start``, as above}``; NaN outside the mask.
    Each warning is also issued as a :class:`PhotostereoWarning`.
    """
    image = _check_array(image, "image")
    r = _native.sfs(
        image,
        _mask(mask),
        _vec3(light, "light"),
        _float(albedo, "albedo"),
        method,
        material,
        material_params,
        transfer,
        boundary,
        _int(iterations, "iterations", 0, 1_000_000),
        _float(smoothness, "smoothness"),
        _float(shadow_level, "shadow_level"),
        None if camera is None else _f64_2d(camera, "camera"),
        _vec3(light_position, "light_position"),
        _float(light_intensity, "light_intensity"),
        bool(refine),
        _float(refine_smoothness, "refine_smoothness"),
        _int(refine_iterations, "refine_iterations", 0, 1_000_000),
        bool(coarse_to_fine),
        bool(outline_repair),
        bool(restarts),
        None if start is None else _f64_2d(start, "start"),
    )
    r["report"] = json.loads(r["report"])
    if r["estimate"] is not None:
        r["estimate"] = json.loads(r["estimate"])
    for w in r["warnings"]:
        _warnings.warn(w, PhotostereoWarning, stacklevel=2)
    return r


def calibrate(
    images: np.ndarray,
    mask: Optional[np.ndarray] = None,
    camera: Optional[np.ndarray] = None,
    ball_radius: Optional[float] = None,
) -> Dict[str, Any]:
    """Light directions from images of a chrome sphere (N x H x W[ x C]), one per light.

    Returns ``{"lights": N x 3 or None (when some image has no highlight or its light is in
    doubt: ambiguous, at the rim, or more uncertain than 0.5 degrees rms), "positions": N x 3
    or None, "report": dict}``: the sphere fitted (from ``mask``, or detected and verified
    against the images), and per image the highlight, its light, its uncertainty, confidence
    and whether it is accepted, or why there is none.

    ``camera``: the 3 x 3 intrinsics K of a pinhole camera; the ball's outline is then fitted as
    the cone of rays it subtends and each pixel reflects its own view ray. With ``ball_radius``
    too (in any unit of length), two balls in the images place each light in 3-D where the rays
    it reflects off them meet: ``positions`` (camera frame, the unit of the radius; None when a
    position is missing or more uncertain than 0.5% of its distance) and ``lights`` the
    directions to them from the balls' midpoint; the mask, if given, outlines both balls.
    """
    images = _check_array(images, "images")
    if camera is not None:
        camera = np.ascontiguousarray(camera, dtype=np.float64)
    if ball_radius is not None:
        ball_radius = float(ball_radius)
    lights, positions, report = _native.calibrate(images, _mask(mask), camera, ball_radius)
    return {"lights": lights, "positions": positions, "report": json.loads(report)}


def read_image(path: PathLike) -> np.ndarray:
    """An image file's samples as stored: H x W x C (C = 1 or 3) uint8, uint16 or float32."""
    return _native.read_image(os.fspath(path))


def read_mask(path: PathLike) -> np.ndarray:
    """A mask file as an H x W bool array (pixels > 0 set)."""
    return _native.read_mask(os.fspath(path))


def load(
    inputs: Union[PathLike, Sequence[PathLike]],
    lights: Optional[PathLike] = None,
    mask: Optional[PathLike] = None,
    ambient: Optional[PathLike] = None,
) -> Capture:
    """Reads a capture as the command-line tool does: a DiLiGenT-layout folder, an image list
    (``<name>.txt``) or image files with a lights file (JSON or ``x y z`` lines, matched to
    the images by name when it names them), with an optional mask file and an optional
    ambient frame (the scene taken with every lamp off, which :meth:`Capture.solve`
    subtracts as ``--ambient`` does)."""
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    paths = [os.fspath(p) for p in inputs]
    files, directions, intensities, mask_path = _native.resolve(
        paths,
        None if lights is None else os.fspath(lights),
        None if mask is None else os.fspath(mask),
    )
    first = read_image(files[0])
    stack = np.empty((len(files),) + first.shape, dtype=first.dtype)
    stack[0] = first

    def read_into(k: int) -> None:
        img = read_image(files[k])
        if img.shape != first.shape or img.dtype != first.dtype:
            raise Error(
                f"{files[k]}: image {k} is {img.shape} {img.dtype} but image 0 ({files[0]}) "
                f"is {first.shape} {first.dtype}; all images must match"
            )
        stack[k] = img

    # Decoding releases the GIL: the files are read in parallel.
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(read_into, range(1, len(files))))
    m = None if mask_path is None else read_mask(mask_path)
    frame = None
    if ambient is not None:
        frame = read_image(ambient)
        if frame.shape != first.shape or frame.dtype != first.dtype:
            raise Error(
                f"ambient image {os.fspath(ambient)}: {frame.shape} {frame.dtype} but image 0 "
                f"({files[0]}) is {first.shape} {first.dtype}; it must be taken and stored as "
                "the images are"
            )
    return Capture(stack, directions, intensities, m, [str(f) for f in files], frame)


def read_exr(path: PathLike) -> Dict[str, np.ndarray]:
    """Every channel of an EXR file as ``{name: H x W float32}``, in the file's order."""
    return dict(_native.read_exr(os.fspath(path)))


def write_exr(
    path: PathLike, channels: Dict[str, np.ndarray], overwrite: bool = False
) -> None:
    """Writes ``{name: H x W array}`` as a float32 EXR (ZIP), atomically: the file appears
    whole or not at all. An existing file is replaced only with ``overwrite=True``."""
    if not channels:
        raise ValueError("channels: none given")
    items = []
    for name, a in channels.items():
        a = np.asarray(a)
        if a.dtype not in (np.float32, np.float64, np.float16):
            raise TypeError(f"channels[{name!r}]: dtype {a.dtype}; a float array expected")
        items.append((str(name), np.ascontiguousarray(a, dtype=np.float32)))
    _native.write_exr(os.fspath(path), items, bool(overwrite))
