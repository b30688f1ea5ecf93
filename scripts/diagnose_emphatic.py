"""Diagnose the EMPHATIC fringe scans against the body scan, and compare with the owners' fit.

The owners stitch each fringe scan to the body scan with fitted offsets (``Inputs.h`` of their
analysis). Each fringe scan, placed at the nominal offset of its ``Zmagnet`` column, is written as a
Hall-map recording of the overlap with the body scan and diagnosed with the command line against
the body scan (``--reference``, inches). The magnet shift the diagnosis finds (released in
``magnet_misalignment``, else calibrated within the survey prior) is printed beside the shift the
owners' offsets imply (``tests/test_diagnose_emphatic.py`` explains the conversion).

    python scripts/diagnose_emphatic.py [--data ../shared/data/emphatic] [--out emphatic/]
"""

from __future__ import annotations

import argparse
import csv
import json
import warnings
from pathlib import Path

import numpy as np

from cfm_fem.cli import main as cli
from cfm_fem.io import read_field
from cfm_fem.io.recordings import write_hall_map
from cfm_fem.models.interpolation import LinearInterpolator
from cfm_fem.models.recordings import Recording

IN = 25.4
#: Magnet shift t (um) implied by the owners' offsets: upstream (small aperture) and
#: downstream (large aperture) fringe scans.
OWNERS = {
    "small": {"magnet_dx": -144.0, "magnet_dy": -411.0, "magnet_dz": -1509.0},
    "large": {"magnet_dx": 375.0, "magnet_dy": 81.0, "magnet_dz": -1959.0},
}
NOMINAL_Z_IN = {"small": -12.362, "large": 7.8}
FILES = {
    "small": "EMPHATIC_smallApertureFringe_cleaned.csv",
    "large": "EMPHATIC_largeApertureFringe_cleaned.csv",
}


def fringe_points(path: Path, z_offset_in: float):
    """Points (mm) and field (T) of a fringe scan, z = Z(stage) + the nominal offset (its
    Zmagnet column has '#REF!' cells in one file)."""
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("%"):
            continue
        f = next(csv.reader([line]))
        rows.append([float(f[0]), float(f[1]), float(f[2]) + z_offset_in, *map(float, f[4:7])])
    a = np.array(rows)
    return a[:, :3] * IN, a[:, 3:6]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    here = Path(__file__).resolve().parents[1]
    ap.add_argument("--data", default=str(here.parent / "shared" / "data" / "emphatic"))
    ap.add_argument("--out", default="emphatic")
    a = ap.parse_args(argv)
    data, out = Path(a.data), Path(a.out)
    body_path = data / "EMPHATIC_body_scan_5280148.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        body = read_field(body_path, length_unit="in")
    interp = LinearInterpolator(body)
    print("| scan | effects | magnet_dx um | magnet_dy um | magnet_dz um | chi2/dof |")
    print("|---|---|---|---|---|---|")
    for side in ("small", "large"):
        pts, B = fringe_points(data / FILES[side], NOMINAL_Z_IN[side])
        inside = interp.field_at(pts)[1]
        n = int(inside.sum())
        rec = Recording(kind="hall", point_id=np.arange(n), rep=np.zeros(n), cmd=pts[inside],
                        B=B[inside])  # fmt: skip
        rec_path = out / f"{side}_fringe_overlap.csv"
        out.mkdir(parents=True, exist_ok=True)
        write_hall_map(rec_path, rec, [f"{FILES[side]} where it overlaps the body scan"])
        argv = ["diagnose", "--hall-map", str(rec_path), "--reference", str(body_path),
                "--length-unit", "in", "--out", str(out / side)]  # fmt: skip
        if cli(argv) != 0:
            return 1
        s = json.loads((out / side / "diagnosis.json").read_text())
        p = {d["name"]: (d["value"], d["std"]) for d in s["calibration"]["parameters"]}
        for e in s["effects"]:
            p.update({k: (v, e["param_std"][k]) for k, v in e["params"].items()})
        cells = [
            f"{p[k][0]:.0f} +- {p[k][1]:.0f} (owners {OWNERS[side][k]:.0f})"
            for k in ("magnet_dx", "magnet_dy", "magnet_dz")
        ]
        names = ", ".join(e["name"] for e in s["effects"]) or "none"
        print(f"| {side} aperture, {n} readings | {names} | {' | '.join(cells)} "
              f"| {s['fit']['chi2_dof_after']:.2f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
