"""Type stubs of the compiled module ``photostereo._native`` (private: use the package's
functions, which check and convert their arguments before calling these)."""

from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

class Error(ValueError):
    """An error of photostereo's: bad input, or a capture it cannot solve."""

def version() -> str: ...
def solve(
    images: np.ndarray,
    lights: np.ndarray,
    mask: Optional[np.ndarray],
    intensities: Optional[np.ndarray],
    method: str,
    color: str,
    transfer: str,
    saturation: Optional[float],
    fill: bool,
    models: Optional[List[Dict[str, Any]]],
    ambient_last: bool = False,
) -> Dict[str, Any]: ...
def add_checks(parts: List[str], ambient_subtracted: bool = False) -> Dict[str, Any]: ...
def estimate_model(
    images: np.ndarray,
    lights: np.ndarray,
    mask: Optional[np.ndarray],
    intensities: Optional[np.ndarray],
    method: str,
    color: str,
    transfer: str,
    saturation: Optional[float],
    ambient_last: bool = False,
) -> List[Dict[str, Any]]: ...
def convert(
    images: np.ndarray,
    lights: np.ndarray,
    intensities: Optional[np.ndarray],
    color: str,
    transfer: str,
    saturation: Optional[float],
) -> Tuple[np.ndarray, np.ndarray]: ...
def integrate(
    normals: np.ndarray, mask: Optional[np.ndarray], method: str, k: Optional[np.ndarray]
) -> Dict[str, Any]: ...
def render(
    scene: str,
    size: int,
    lights: np.ndarray,
    material: str,
    material_params: Optional[Dict[str, float]],
    albedo: float,
    noise: float,
    seed: int,
    cast_shadows: bool,
    light_radius_deg: Optional[float],
    ambient: float,
    pixel_samples: int,
) -> Dict[str, np.ndarray]: ...
def light_ring(count: int, elevation_deg: float, azimuth0_deg: float) -> np.ndarray: ...
def reflectance_map(
    light: Sequence[float],
    material: str,
    material_params: Optional[Dict[str, float]],
    extent: float,
    size: int,
) -> np.ndarray: ...
def calibrate(
    images: np.ndarray,
    mask: Optional[np.ndarray],
    camera: Optional[np.ndarray],
    ball_radius: Optional[float],
) -> Tuple[Optional[np.ndarray], Optional[np.ndarray], str]: ...
def sfs(
    image: np.ndarray,
    mask: Optional[np.ndarray],
    light: Optional[List[float]],
    albedo: Optional[float],
    method: Optional[str],
    material: str,
    material_params: Optional[Dict[str, float]],
    transfer: str,
    boundary: str,
    iterations: int,
    smoothness: Optional[float],
    shadow_level: Optional[float],
    camera: Optional[np.ndarray],
    light_position: Optional[List[float]],
    light_intensity: Optional[float],
    refine: bool,
    refine_smoothness: Optional[float],
    refine_iterations: int,
    coarse_to_fine: bool,
    outline_repair: bool,
    restarts: bool,
    start: Optional[np.ndarray],
) -> Dict[str, Any]: ...
def read_image(path: str) -> np.ndarray: ...
def read_mask(path: str) -> np.ndarray: ...
def resolve(
    inputs: List[str], lights: Optional[str], mask: Optional[str]
) -> Tuple[List[str], np.ndarray, np.ndarray, Optional[str]]: ...
def read_exr(path: str) -> List[Tuple[str, np.ndarray]]: ...
def write_exr(path: str, channels: List[Tuple[str, np.ndarray]], overwrite: bool) -> None: ...
