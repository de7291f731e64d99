"""Shared fixtures of the Python tests: the repository, the shared data, the command-line tool."""

import os
import pathlib
import subprocess

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHARED = pathlib.Path(os.environ.get("PHOTOSTEREO_SHARED", ROOT.parent / "shared")) / "data"


def shared(*parts):
    """A path under ../shared/data, or a skip (printed as SKIPPED) when it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        print(f"SKIPPED: {p} is absent (the shared data sits beside the repository)")
        pytest.skip(f"{p} is absent")
    return p


@pytest.fixture(scope="session")
def cli():
    """The command-line tool, built in release mode if it is not there yet."""
    exe = ROOT / "target" / "release" / "photostereo"
    if not exe.exists():
        subprocess.run(
            ["cargo", "build", "--release", "--bin", "photostereo"], cwd=ROOT, check=True
        )
    return exe


def turned(lights, k, deg):
    """Unit copies of `lights` (N x 3) with row `k` turned by `deg` degrees about the axis
    across it and the view (a wrong row of a lights file), and the original unit row."""
    unit = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    l = unit[k]
    axis = np.cross(l, [0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    t = np.radians(deg)
    wrong = unit.copy()
    wrong[k] = l * np.cos(t) + np.cross(axis, l) * np.sin(t) + axis * (axis @ l) * (1 - np.cos(t))
    return wrong, l
