"""Region of interest of a map: a box, or a cylinder about the z axis over a z range.

The statistics of ``sweep`` and the answer of ``design`` can be restricted to one (the magnet's
good-field region, say), so that the map's extent (its field-free ends, its corners outside
the good-field radius) does not move them. Text form (option ``--region``):

- box: ``XMIN:XMAX,YMIN:YMAX,ZMIN:ZMAX`` (mm; an empty end is unbounded, e.g. ``-5:5,-5:5,:``);
- cylinder: ``cylinder:R,ZMIN:ZMAX`` (mm): the nodes with sqrt(x^2 + y^2) <= R and z in the
  range (an empty end is unbounded), e.g. ``cylinder:7,-30:30``.

Bounds are included.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError

__all__ = ["Region", "parse_region", "region_mask", "REGION_SYNTAX"]

#: The two spellings `parse_region` reads.
REGION_SYNTAX = "XMIN:XMAX,YMIN:YMAX,ZMIN:ZMAX or cylinder:R,ZMIN:ZMAX"


@dataclass(frozen=True)
class Region:
    """A box or a cylinder about the z axis, mm.

    Attributes
    ----------
    box : ndarray, shape (3, 2), mm
        Lower and upper bound per axis (x, y, z); for a cylinder, x and y are +-radius and z
        its range. Infinite where unbounded.
    radius_mm : float or None
        Cylinder radius about the z axis; None for a box.
    """

    box: np.ndarray
    radius_mm: float | None = None

    def mask(self, points) -> np.ndarray:
        """Nodes inside the region (bounds included), shape (n,), bool; ``points`` (n, 3) mm."""
        p = np.asarray(points, dtype=np.float64)
        inside = np.all((p >= self.box[:, 0]) & (p <= self.box[:, 1]), axis=1)
        if self.radius_mm is not None:
            inside &= p[:, 0] ** 2 + p[:, 1] ** 2 <= self.radius_mm**2
        return inside

    def to_json(self):
        """For summary.json: a box as ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` (None for
        an unbounded end), a cylinder as ``{"cylinder_radius_mm": R, "z_mm": [zmin, zmax]}``."""

        def finite(v):
            return float(v) if np.isfinite(v) else None

        if self.radius_mm is None:
            return [[finite(lo), finite(hi)] for lo, hi in self.box]
        return {"cylinder_radius_mm": self.radius_mm, "z_mm": [finite(v) for v in self.box[2]]}

    def describe(self) -> str:
        """``box x -5:5, y -5:5, z any`` or ``cylinder r <= 7 mm, z -30:30`` (mm)."""

        def span(lo, hi):
            if not (np.isfinite(lo) or np.isfinite(hi)):
                return "any"
            return f"{lo:g}:{hi:g}".replace("-inf", "").replace("inf", "")

        if self.radius_mm is None:
            axes = ", ".join(f"{a} {span(*self.box[i])}" for i, a in enumerate("xyz"))
            return f"box {axes} mm"
        return f"cylinder r <= {self.radius_mm:g} mm about the z axis, z {span(*self.box[2])} mm"


def _range(text: str, bad: CfmInputError) -> tuple[float, float]:
    ends = text.split(":")
    if len(ends) != 2:
        raise bad
    try:
        lo = float(ends[0]) if ends[0].strip() else -np.inf
        hi = float(ends[1]) if ends[1].strip() else np.inf
    except ValueError:
        raise bad from None
    if np.isnan(lo) or np.isnan(hi) or lo > hi:
        raise bad
    return lo, hi


def parse_region(text: str) -> Region:
    """``XMIN:XMAX,YMIN:YMAX,ZMIN:ZMAX`` or ``cylinder:R,ZMIN:ZMAX`` (mm) to a `Region`.

    Raises
    ------
    CfmInputError
        Another form, a bound that is not a number, a lower bound above the upper one, or a
        radius that is not a positive finite number.
    """
    bad = CfmInputError(
        f"--region must be {REGION_SYNTAX} in mm (an end may be empty); got {text!r}"
    )
    parts = text.split(",")
    if parts[0].strip().lower().startswith("cylinder:"):
        if len(parts) != 2:
            raise bad
        try:
            radius = float(parts[0].split(":", 1)[1])
        except ValueError:
            raise bad from None
        if not (np.isfinite(radius) and radius > 0):
            raise bad
        box = np.array([[-radius, radius], [-radius, radius], _range(parts[1], bad)])
        return Region(box, radius)
    if len(parts) != 3:
        raise bad
    return Region(np.array([_range(part, bad) for part in parts]))


def region_mask(points, region) -> np.ndarray:
    """Nodes inside ``region`` (a `Region`, a (3, 2) box in mm, or None for every node), shape
    (n,), bool; ``points`` (n, 3) mm."""
    points = np.asarray(points)
    if region is None:
        return np.ones(len(points), dtype=bool)
    if not isinstance(region, Region):
        region = Region(np.asarray(region, dtype=np.float64))
    return region.mask(points)
