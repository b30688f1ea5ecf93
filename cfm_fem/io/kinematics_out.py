"""Outputs of ``cfm-fem kinematics`` and ``cfm-fem tolerance``: per-point CSV, .vtu, JSON.

All writes are atomic (temporary name, then rename).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from ._atomic import atomic_paths, json_text, write_text
from .vtk import write_vtu

__all__ = [
    "PAPER_TABLE_IV",
    "bench_description",
    "kinematics_summary",
    "write_kinematics",
    "write_points_csv",
    "write_points_vtu",
]

#: Table IV of the paper, simulated and experimental columns (um).
PAPER_TABLE_IV = {
    "simulation": {
        "x": {"systematic_um": 16, "std_um": 11},
        "y": {"systematic_um": 8, "std_um": 11},
        "z": {"systematic_um": 8, "std_um": 13},
    },
    "experiment": {
        "x": {"systematic_um": 7, "std_um": 13},
        "y": {"systematic_um": 11, "std_um": 13},
        "z": {"systematic_um": 11, "std_um": 14},
    },
}

_QTY = ("x", "y", "z", "norm")


def bench_description(bench) -> dict:
    """The geometry and every stated assumption of a bench, for outputs."""
    return {
        "name": bench.name,
        "source": bench.source,
        "stack_from_foundation": list(bench.stack),
        "strokes_mm": {a: bench.axes[a].stroke_mm for a in "xyz"},
        "mount_offsets_mm": {a: np.asarray(bench.axes[a].mount_offset_mm).tolist() for a in "xyz"},
        "tool_offset_mm": np.asarray(bench.tool_offset_mm).tolist(),
        "grid_mm": {a: list(getattr(bench.grid, a)) for a in "xyz"},
        "vibration_std_um": (np.asarray(bench.vibration_std_mm) * 1e3).tolist(),
        "reading_delay": (
            {"model": "normal", "std_um": (np.asarray(bench.delay.std_mm) * 1e3).tolist()}
            if bench.delay.model == "normal"
            else {
                "model": "speed_tau",
                "speed_mm_s": np.asarray(bench.delay.speed_mm_s).tolist(),
                "tau_s": bench.delay.tau_pdf.describe("s"),
            }
        ),
        "errors": {
            e.name: e.pdf.scaled(1e6 if e.is_angle else 1e3).describe(
                "urad" if e.is_angle else "um"
            )
            + ("" if tuple(e.profile) == (1.0,) else f" x poly{list(e.profile)}(q/stroke)")
            for e in bench.errors
        },
        "assumptions": list(bench.assumptions),
    }


def kinematics_summary(result, bench, budget=None, gum=None, extra=None) -> dict:
    """The ``summary.json`` document: the stable keys ``axes`` (``x``, ``y``, ``z``, each
    ``systematic_um``, ``std_um``, ``U_p_um``), ``trials`` and ``points``, plus context."""
    axes = {a: dict(result.pooled[a]) for a in "xyz"}
    doc = {
        "axes": axes,
        "trials": int(result.trials),
        "points": int(result.n_points),
        "seed": int(result.seed),
        "norm": dict(result.pooled["norm"]),
        "pooling": (
            "systematic = RMS over points of the per-point mean error; std = RMS over points of "
            "the per-point standard uncertainty; U_p = sqrt(systematic^2 + std^2)"
        ),
        "paper_table_iv": PAPER_TABLE_IV,
        "coverage_probability": result.p,
        "interval_method": result.interval_method,
        "bench": bench_description(bench),
        "notes": list(result.notes),
        "seconds": dict(result.seconds),
    }
    if result.adaptive is not None:
        doc["adaptive"] = result.adaptive
    if budget is not None:
        doc["budget"] = budget
    if gum is not None:
        doc["gum_validation"] = gum
    if extra:
        doc.update(extra)
    return doc


def write_points_csv(path, result, bench, provenance: dict | None = None) -> None:
    """Per-point statistics, one row per point, um for errors, mm for positions.

    ``provenance`` (input hashes, version, command line) goes into a ``# provenance:`` line.
    """
    buf = io.StringIO()
    buf.write(f"# cfm-fem kinematics: {bench.name}; trials={result.trials}; seed={result.seed}\n")
    if provenance:
        buf.write(f"# provenance: {json.dumps(provenance, sort_keys=True)}\n")
    buf.write("# bench frame, mm; errors E = actual - nominal probe position, um\n")
    buf.write(
        f"# intervals: {int(round(100 * result.p))} % probabilistically symmetric; "
        f"{result.interval_method}\n"
    )
    for note in bench.assumptions:
        buf.write(f"# assumption: {note}\n")
    cols = ["point", "x_cmd_mm", "y_cmd_mm", "z_cmd_mm", "x_nom_mm", "y_nom_mm", "z_nom_mm"]
    for q in _QTY:
        cols += [f"{q}_sys_um", f"{q}_std_um", f"{q}_low_um", f"{q}_high_um", f"{q}_Up_um"]
    buf.write(",".join(cols) + "\n")
    up = result.up
    data = [np.arange(result.n_points)[:, None], result.q_cmd, result.nominal]
    for c in range(4):
        data.append(
            1e3
            * np.stack(
                [
                    result.mean[:, c],
                    result.std[:, c],
                    result.low[:, c],
                    result.high[:, c],
                    up[:, c],
                ],
                axis=1,
            )
        )
    table = np.hstack(data)
    fmt = ["%d"] + ["%.6f"] * 6 + ["%.6g"] * 20
    np.savetxt(buf, table, delimiter=",", fmt=fmt)
    write_text(path, buf.getvalue())


def write_points_vtu(path, result, bench, provenance: dict | None = None) -> None:
    """Point cloud at the nominal probe positions (bench frame, mm) with the statistics (um).

    ``provenance`` goes into the field data ``provenance_utf8`` (the UTF-8 bytes of its JSON
    text, `cfm_fem.io.vtk.write_vtu`; `cfm_fem.io.sweep_out.read_provenance` decodes it)."""
    pd = {
        "E_systematic_um": 1e3 * result.mean[:, :3],
        "E_std_um": 1e3 * result.std[:, :3],
        "E_low95_um": 1e3 * result.low[:, :3],
        "E_high95_um": 1e3 * result.high[:, :3],
        "U_p_um": 1e3 * result.up[:, :3],
        "norm_systematic_um": 1e3 * result.mean[:, 3],
        "norm_std_um": 1e3 * result.std[:, 3],
        "norm_high95_um": 1e3 * result.high[:, 3],
        "q_cmd_mm": result.q_cmd,
    }
    # the bench and its assumptions are in summary.json and points.csv
    fd = {"trials": result.trials, "seed": result.seed, "coverage_probability": result.p}
    if provenance:
        fd["provenance"] = json.dumps(provenance, sort_keys=True)
    write_vtu(path, result.nominal, point_data=pd, field_data=fd)


def write_kinematics(out_dir, result, bench, summary: dict) -> dict:
    """Write ``summary.json``, ``points.csv`` and ``points.vtu`` into ``out_dir``: all three
    or, if any fails, none.

    Returns
    -------
    dict of str -> Path
    """
    out = Path(out_dir)
    paths = {
        "summary": out / "summary.json",
        "csv": out / "points.csv",
        "vtu": out / "points.vtu",
    }
    text = json_text(summary)  # a summary JSON refuses fails here, before any file is written
    with atomic_paths(paths.values()) as (summary_tmp, csv_tmp, vtu_tmp):
        write_points_csv(csv_tmp, result, bench, summary.get("provenance"))
        write_points_vtu(vtu_tmp, result, bench, summary.get("provenance"))
        write_text(summary_tmp, text)
    return paths
