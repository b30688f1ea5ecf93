"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

#: Real field-map files (``../shared/data`` beside the repository); tests that read them skip
#: when the folder is absent.
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# Every test fits its maps afresh (and leaves the user's cache alone); tests of the fits' cache
# name a folder of their own.
os.environ["CFM_FEM_FIT_CACHE"] = "off"


def grid_nodes(n: int) -> np.ndarray:
    """The nodes of an n x n x n grid with 1 mm spacing from the origin, shape (n**3, 3), mm."""
    ax = np.arange(float(n))
    return np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)


def curved_field(pts: np.ndarray) -> np.ndarray:
    """A smooth field with curvature in every component, shape (m, 3), T, at ``pts`` (m, 3) mm."""
    return np.c_[0.03 * pts[:, 0] ** 2, -0.02 * pts[:, 1] * pts[:, 2], 1.0 + 0.1 * pts[:, 2]]


def write_map_csv(path: Path, pts: np.ndarray, B: np.ndarray) -> Path:
    """Write nodes (m, 3) mm and field (m, 3) T as a CSV field map with units in the header."""
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


@pytest.fixture(scope="session")
def grid_csv(tmp_path_factory):
    """Factory ``grid_csv(n, field) -> path``: a new CSV map of the n x n x n grid
    (`grid_nodes`) with the field ``field(pts) -> B`` (T)."""

    def make(n: int, field) -> Path:
        pts = grid_nodes(n)
        return write_map_csv(tmp_path_factory.mktemp("map") / "map.csv", pts, field(pts))

    return make


@pytest.fixture(scope="module")
def bench():
    """The packaged CFM reference bench."""
    from cfm_fem.io.bench_toml import read_reference_bench

    return read_reference_bench()
