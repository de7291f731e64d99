"""Shared fixtures of the Python tests: the repository, the shared data, the command-line tool."""

import os
import pathlib
import subprocess

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
