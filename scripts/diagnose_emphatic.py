"""Diagnose the EMPHATIC fringe scans against the body scan, placed at the owners' stitching.

The owners stitch each fringe scan to the body scan with fitted offsets (``Inputs.h`` of their
analysis): "position in the file minus offset = physical position", (-0.144, -0.411, 312.486) mm
upstream (small-aperture scan) and (0.375, 0.081, -200.079) mm downstream (large aperture). Each
fringe scan, placed there, is written as a Hall-map recording of its overlap with the body scan
(|x|, |y| <= 10 mm) and diagnosed with the command line against the body scan (``--reference``,
inches). Placed at the owners' fit, the magnet shift left to find is the departure from that fit:
the table prints the shift the diagnosis finds (released in ``magnet_misalignment``, else
calibrated within the survey prior) and the Hall gains, beside the direct least-squares stitching
of ``scripts/stitch_emphatic.py``.

    python scripts/diagnose_emphatic.py [--data ../shared/data/emphatic] [--out emphatic/]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from cfm_fem.cli import main as cli
from cfm_fem.io import read_field
from cfm_fem.io.recordings import write_hall_map
from cfm_fem.models.interpolation import LinearInterpolator
from cfm_fem.models.recordings import Recording

IN = 25.4
#: The owners' offsets (mm): position in the file minus offset = physical position.
OWNERS_OFFSET_MM = {"small": (-0.144, -0.411, 312.486), "large": (0.375, 0.081, -200.079)}
FILES = {
    "small": "EMPHATIC_smallApertureFringe_cleaned.csv",
    "large": "EMPHATIC_largeApertureFringe_cleaned.csv",
}
BODY = "EMPHATIC_body_scan_5280148.csv"
#: Half width of the overlap kept, mm.
HALF_WIDTH_MM = 10.0


def fringe_points(path: Path, offset_mm):
    """Points (mm) and field (T) of a fringe scan placed at ``offset_mm``: (X, Y, Z(stage)) of
    the file in mm less the offset (its Zmagnet column has '#REF!' cells in one file)."""
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("%"):
            continue
        f = next(csv.reader([line]))
        rows.append([float(f[0]), float(f[1]), float(f[2]), *map(float, f[4:7])])
    a = np.array(rows)
    return a[:, :3] * IN - np.asarray(offset_mm), a[:, 3:6]


def overlap(points, B, body, half_width_mm: float = HALF_WIDTH_MM) -> Recording:
    """The readings inside the body scan's cells with |x|, |y| <= ``half_width_mm``."""
    inside = LinearInterpolator(body).field_at(points)[1]
    inside &= np.abs(points[:, :2]).max(1) <= half_width_mm + 0.5
    n = int(inside.sum())
    return Recording(kind="hall", point_id=np.arange(n), rep=np.zeros(n), cmd=points[inside],
                     B=B[inside])  # fmt: skip


def read_body(data: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_field(data / BODY, length_unit="in")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    here = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", default=str(here.parent / "shared" / "data" / "emphatic"))
    ap.add_argument("--out", default="emphatic")
    ap.add_argument("--sides", default="small,large")
    a = ap.parse_args(argv)
    data, out = Path(a.data), Path(a.out)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from stitch_emphatic import stitch

    body = read_body(data)
    print("| scan | effects | magnet_dx um | magnet_dy um | magnet_dz um | gains % | chi2/dof |")
    print("|---|---|---|---|---|---|---|")
    for side in a.sides.split(","):
        pts, B = fringe_points(data / FILES[side], OWNERS_OFFSET_MM[side])
        rec = overlap(pts, B, body)
        rec_path = out / f"{side}_fringe_overlap.csv"
        out.mkdir(parents=True, exist_ok=True)
        write_hall_map(rec_path, rec, [f"{FILES[side]} at the owners' offset, |x|, |y| <= 10 mm"])
        argv = ["diagnose", "--hall-map", str(rec_path), "--reference", str(data / BODY),
                "--length-unit", "in", "--out", str(out / side)]  # fmt: skip
        if cli(argv) != 0:
            return 1
        s = json.loads((out / side / "diagnosis.json").read_text())
        p = {d["name"]: (d["value"], d["std"]) for d in s["calibration"]["parameters"]}
        for e in s["effects"]:
            p.update({k: (v, e["param_std"][k]) for k, v in e["params"].items()})
        direct = stitch(pts, B, body.points, body.B)
        cells = [
            f"{p[k][0]:.0f} +- {p[k][1]:.0f} (direct {direct['shift_um'][j]:.0f} +- "
            f"{direct['shift_std_um'][j]:.0f})"
            for j, k in enumerate(("magnet_dx", "magnet_dy", "magnet_dz"))
        ]
        gains = ", ".join(f"{p[f'gain_{c}'][0]:.2f}" for c in "xyz")
        dg = ", ".join(f"{g:.2f}" for g in direct["gain_pct"])
        names = ", ".join(e["name"] for e in s["effects"]) or "none"
        print(f"| {side} aperture, {len(rec)} readings | {names} | {' | '.join(cells)} "
              f"| {gains} (direct {dg}) | {s['fit']['chi2_dof_after']:.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
