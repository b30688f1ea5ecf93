"""Diagnose family nulls whose readings carry the Hall probe's own noise alone.

Each Hall null of the randomized family (:mod:`cfm_fem.simulation.family`) is written as the
family writes it, then its field readings are replaced by the same configuration's readings
without the axes' vibration and reading error (the drawn bench errors, the surveyed pose, the
gains and the probe's white noise kept). The diagnosis's deterministic model must then
reproduce the readings down to the probe's noise: chi2/dof near 1 against an exact reference
(below 1 against a coarse one, whose stated error is then larger than the noise), nothing
claimed, nothing located. One line per case::

    python scripts/fit_without_vibration.py --first-seed 140001 --cases 40 --size small

A 2-D harmonics reference is kept by the family only where the body's 3-D departure is below
the noise with the vibration in; without it, that departure may show.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from pathlib import Path

import numpy as np

from cfm_fem.cli import main
from cfm_fem.simulation import family, family_hall


def rewrite_readings(recording: Path, values: np.ndarray) -> None:
    """Replace the Bx, By, Bz columns of a family recording by ``values`` (T, shape (n, 3))."""
    lines = recording.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("point_id"))
    cols = lines[head].split(",")
    where = [cols.index(c) for c in ("Bx", "By", "Bz")]
    for k in range(len(values)):
        fields = lines[head + 1 + k].split(",")
        for j, c in enumerate(where):
            fields[c] = f"{values[k, j]:.12f}"
        lines[head + 1 + k] = ",".join(fields)
    recording.write_text("\n".join(lines) + "\n")


def without_vibration(seed: int, size: str, folder: Path) -> dict:
    """Write the Hall null of ``seed`` with its readings free of the axes' vibration and
    diagnose it; returns the case's strata and the diagnosis's figures."""
    files = family.write_family_case(seed, folder, size, role="null", kind="hall")
    case = family.drawn_case(seed, size, "null", "hall", 0)
    cfg, ctx = case["cfg"], case["ctx"]
    readings = family_hall.forward(cfg, ctx, {}, noisy=False) + ctx["noise"]
    rewrite_readings(Path(files["recording"]), readings)
    out = folder / "run"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(["diagnose", *map(str, files["args"]), "--no-report", "--out", str(out)])
    d = json.loads((out / "diagnosis.json").read_text())
    return {
        "rc": rc,
        "strata": cfg["strata"],
        "chi2_dof": d["fit"]["chi2_dof_before"],
        "lack_of_fit_F": [lof["F"] for lof in d["fit"]["lack_of_fit_before"]],
        "claimed": [e["name"] for e in d["effects"]],
        "located": len(d["located"]),
        "mismatch": d["mismatch"],
    }


def main_cli(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--first-seed", type=int, default=140001)
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--size", choices=("small", "full"), default="small")
    a = ap.parse_args(argv)
    clean = 0
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(a.first_seed, a.first_seed + a.cases):
            r = without_vibration(seed, a.size, Path(tmp) / str(seed))
            s = r["strata"]
            ok = not r["claimed"] and not r["located"] and not r["mismatch"]
            clean += ok
            print(f"{seed} {s['magnet']} {s['source']} {s['ends']} {s['bench_stack']} {s['scan']} "
                  f"{s['noise']} {s['reference']}: chi2/dof {r['chi2_dof']:.3f}, lack of fit "
                  f"{', '.join(f'{f:.2f}' for f in r['lack_of_fit_F'])}, claimed {r['claimed']}, "
                  f"located {r['located']}", flush=True)  # fmt: skip
    print(f"{clean} of {a.cases} fit without a claim, a located residual or a mismatch")
    return 0


if __name__ == "__main__":
    raise SystemExit(main_cli())
