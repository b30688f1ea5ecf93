"""Files of ``cfm-fem quality``: ``quality.json`` (keys in docs/quality.md), ``planes.csv``,
and the tolerance table a user gives with ``--tolerances``.

Tolerance table: CSV with a header row ``quantity,tolerance`` (``#`` comment lines allowed), one
quantity a row: ``b1`` .. ``b15``, ``a1`` .. ``a15`` (units of 1e-4 of the main harmonic),
``centre_x_um``, ``centre_y_um`` (um), ``roll_mrad`` (mrad), ``magnetic_length_mm`` (mm).
"""

from __future__ import annotations

import io

import numpy as np

from ..errors import CfmInputError
from ..models.quality.harmonics import N_HARMONICS, VECTOR_NAMES
from ._files import check_regular
from .compare_out import NO_FIGURE, _cell
from .run_files import json_ready as _finite
from .run_files import write_run

__all__ = [
    "TOLERANCE_NAMES",
    "read_tolerances",
    "quality_summary",
    "planes_csv",
    "write_quality",
]

#: Quantities of a tolerance table -> (column of `VECTOR_NAMES`, factor from the file's unit to
#: the vector's unit, unit).
TOLERANCE_NAMES = {
    **{f"b{n}": (f"b{n}", 1.0, "units") for n in range(1, N_HARMONICS + 1)},
    **{f"a{n}": (f"a{n}", 1.0, "units") for n in range(1, N_HARMONICS + 1)},
    "centre_x_um": ("centre_x", 1e-3, "um"),
    "centre_y_um": ("centre_y", 1e-3, "um"),
    "roll_mrad": ("roll", 1.0, "mrad"),
    "magnetic_length_mm": ("length", 1.0, "mm"),
}


def read_tolerances(path) -> dict:
    """Tolerance table (module docstring) -> {quantity: tolerance in the file's unit}.

    Raises
    ------
    CfmInputError
        Missing header, unknown quantity, a tolerance that is not a positive number, or a
        quantity given twice, naming the file and line.
    """
    check_regular(path)
    try:
        text = open(path, encoding="utf-8").read()  # noqa: SIM115
    except (OSError, UnicodeDecodeError) as exc:
        raise CfmInputError(f"cannot read the tolerance table: {exc}", file=str(path)) from None
    out, header = {}, None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if header is None:
            if [c.lower() for c in cells[:2]] != ["quantity", "tolerance"]:
                raise CfmInputError(
                    f"expected the header 'quantity,tolerance'; found {line!r}",
                    file=str(path), line=lineno,
                )  # fmt: skip
            header = cells
            continue
        if len(cells) < 2:
            raise CfmInputError(f"expected 'quantity,tolerance'; found {line!r}",
                                file=str(path), line=lineno)  # fmt: skip
        name = cells[0]
        if name not in TOLERANCE_NAMES:
            raise CfmInputError(
                f"column 'quantity' must be one of b1..b{N_HARMONICS}, a1..a{N_HARMONICS}, "
                f"centre_x_um, centre_y_um, roll_mrad, magnetic_length_mm; found {name!r}",
                file=str(path), line=lineno, column="quantity",
            )  # fmt: skip
        try:
            tol = float(cells[1])
        except ValueError:
            tol = float("nan")
        if not (np.isfinite(tol) and tol > 0):
            raise CfmInputError(
                f"column 'tolerance' must be a positive number; found {cells[1]!r}",
                file=str(path), line=lineno, column="tolerance",
            )  # fmt: skip
        if name in out:
            raise CfmInputError(f"quantity {name!r} is given twice", file=str(path), line=lineno)
        out[name] = tol
    if header is None:
        raise CfmInputError("the tolerance table holds no header row", file=str(path))
    return out


def _lists(vec) -> dict:
    """The scalars of a `QualityNumbers.vector`-shaped array, by output name."""
    v = np.asarray(vec, dtype=np.float64)
    return {
        "b_n_units": v[:N_HARMONICS].tolist(),
        "a_n_units": v[N_HARMONICS : 2 * N_HARMONICS].tolist(),
        "centre_mm": v[2 * N_HARMONICS : 2 * N_HARMONICS + 2].tolist(),
        "roll_mrad": float(v[VECTOR_NAMES.index("roll")]),
        "magnetic_length_mm": float(v[VECTOR_NAMES.index("length")]),
        "main_integral_Tmm": float(v[VECTOR_NAMES.index("main_integral")]),
    }


def _tolerance_rows(tolerances: dict, u95) -> list:
    rows = []
    for name, tol in tolerances.items():
        col, factor, unit = TOLERANCE_NAMES[name]
        u = None if u95 is None else float(u95[VECTOR_NAMES.index(col)]) / factor
        rows.append({"quantity": name, "tolerance": tol, "unit": unit, "U95": u,
                     "ratio": None if u is None else u / tol,
                     "determined": None if u is None else bool(u <= tol)})  # fmt: skip
    return rows


def quality_summary(run) -> dict:
    """``quality.json`` of a `cfm_fem.workflows.quality.QualityRun` (docs/quality.md)."""
    nom = run.nominal
    v = nom.vector()
    mc = run.mc
    u = _lists(mc.u95) if mc is not None else None
    integ = {
        "n": list(range(1, N_HARMONICS + 1)),
        "B_n_Tmm": nom.integrated.real.tolist(),
        "A_n_Tmm": nom.integrated.imag.tolist(),
        "b_n_units": v[:N_HARMONICS].tolist(),
        "a_n_units": v[N_HARMONICS : 2 * N_HARMONICS].tolist(),
        "U95_b_n_units": None if u is None else u["b_n_units"],
        "U95_a_n_units": None if u is None else u["a_n_units"],
    }
    out = {
        "r_ref_mm": run.plan.r_ref_mm,
        "main_order": run.main_order,
        "z_range_mm": [float(run.plan.z[0]), float(run.plan.z[-1])],
        "integrated": integ,
        "centre_mm": nom.centre_mm.tolist(),
        "U95_centre_mm": None if u is None else u["centre_mm"],
        "roll_mrad": float(nom.roll_mrad),
        "U95_roll_mrad": None if u is None else u["roll_mrad"],
        "magnetic_length_mm": float(nom.length_mm),
        "U95_magnetic_length_mm": None if u is None else u["magnetic_length_mm"],
        "main_integral_Tmm": float(nom.main_integral_Tmm),
        "U95_main_integral_Tmm": None if u is None else u["main_integral_Tmm"],
        "length_plane_mm": run.z_length,
        "trajectory": run.trajectory,
        "uncertainty": None if mc is None else _uncertainty(run),
        "tolerances": None if run.tolerances is None else _tolerance_rows(
            run.tolerances, None if mc is None else mc.u95),
        "sampling": {
            "kind": run.plan.sampling, "description": run.plan.describe(),
            "radius_mm": run.plan.r_fit_mm, "planes": run.plan.n_planes,
            "points_per_plane": run.plan.per_plane, "orders_fitted": run.plan.n_orders,
            "condition_number": run.plan.condition,
            "pseudo_multipole_orders": run.plan.pseudo_orders,
        },
        "field": {"source": run.source, "nodes": run.n_nodes, "model": run.model_description},
        "definitions": DEFINITIONS,
        "notes": list(run.notes),
        "seconds": run.seconds,
    }  # fmt: skip
    if run.provenance is not None:
        out["provenance"] = run.provenance
    return _finite(out)


def _uncertainty(run) -> dict:
    mc = run.mc
    cov = np.cov(mc.deviations[:, [2 * N_HARMONICS, 2 * N_HARMONICS + 1]].T)
    out = {
        "mode": mc.mode, "trials": mc.trials, "seed": mc.seed,
        "sources": run.sources_description,
        "lost_trials": mc.lost,
        "centre_covariance_mm2": np.atleast_2d(cov).tolist(),
        "numerical_tolerance": {
            "digits": mc.digits, "converged": mc.converged, "batches": mc.batches,
            "batch_trials": mc.batch_trials,
            "U95_spread": _lists(mc.u95_spread), "std_target": _lists(mc.delta),
            "definition": "U95_spread: twice the standard deviation of the batch values of "
            "U95 over sqrt(batches); std_target: JCGM 101 7.9.2 tolerance of the standard "
            "deviation for the given digits, which the adaptive procedure reaches for the mean, "
            "the standard deviation and both interval ends of every quantity",
        },
        "systematic": _lists(mc.mean),
        "std": _lists(mc.std),
    }  # fmt: skip
    if run.budget:
        groups = [{"name": b.label, "trials": b.trials, **{f"U95_{k}": x for k, x in
                   _lists(b.u95).items()}} for b in run.budget]  # fmt: skip
        u = np.array([b.u95 for b in run.budget])
        with np.errstate(invalid="ignore"):
            top = np.where(np.all(np.isnan(u), axis=0), -1, np.argmax(np.nan_to_num(u, nan=-1), 0))
        dominant = {name: (run.budget[k].label if k >= 0 else None)
                    for name, k in zip(VECTOR_NAMES, top, strict=True)}  # fmt: skip
        out["budget"] = {
            "trials": run.budget[0].trials, "groups": groups, "dominant": dominant,
            "definition": "U95 of each quantity with one error group active and the others "
            "off (same seed); dominant: the group of the largest U95",
        }  # fmt: skip
    else:
        out["budget"] = None
    return out


DEFINITIONS = {
    "harmonics": "F = B_y + i B_x = sum (B_n + i A_n) (w / R_ref)^(n-1), w = x + i y about the "
    "map's line x = y = 0, European n; least-squares fit of the 2-D multipoles to each plane's "
    "(B_x, B_y) at the scan points, integrated over z by the trapezoid rule; null where an order "
    "is not determined",
    "planes": "planes.csv: C_n of each plane on the circle r = R_ref (node sampling: fit of the "
    "2-D multipoles and the pseudo-multipoles r^2 Re(c w^m), m = 0 .. "
    "sampling.pseudo_multipole_orders; circle sampling: the sampled circle's Fourier "
    "coefficients scaled to R_ref as a 2-D field)",
    "units": "b_n, a_n = 1e4 (B_n, A_n) / |B_N + i A_N| of the integrated harmonics, "
    "N = main_order",
    "centre_mm": "point about which the integrated harmonic of order main_order - 1 vanishes "
    "(exact feed-down, Newton's method); null for a dipole",
    "roll_mrad": "-atan2(A_N, B_N) / N of the integrated main harmonic (a normal magnet rolled "
    "by +theta about +z gives +theta)",
    "magnetic_length_mm": "integrated main harmonic over the main harmonic on the circle "
    "r = R_ref in the plane length_plane_mm (z = 0 when the map holds it), both projected on "
    "the phase of the integral: integrated B_N over B_N on that circle for a magnet without "
    "roll",
    "main_integral_Tmm": "|integral of B_N + i A_N| over z at R_ref",
    "U95": "max(|low|, |high|) of the 95 % probabilistically symmetric interval of the "
    "deviation from the map's value over the Monte Carlo trials",
}


def planes_csv(run) -> str:
    """Per-plane harmonics: z, then B_n, A_n (T at R_ref) and b_n, a_n (units of the plane's
    main harmonic) for n = 1 .. 15."""
    c = run.planes
    n = np.arange(1, N_HARMONICS + 1)
    header = (["z_mm"] + [f"B{k}_T" for k in n] + [f"A{k}_T" for k in n]
              + [f"b{k}_units" for k in n] + [f"a{k}_units" for k in n])  # fmt: skip
    main = np.abs(c[:, run.main_order - 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = 1e4 * c / main[:, None]
    buf = io.StringIO()
    buf.write(f"# harmonics per plane at R_ref = {run.plan.r_ref_mm:g} mm, main order "
              f"{run.main_order}; {run.plan.describe()}\n")  # fmt: skip
    buf.write(f"# {NO_FIGURE}\n")
    buf.write(",".join(header) + "\n")
    for p in range(len(run.plan.z)):
        row = [run.plan.z[p], *c[p].real, *c[p].imag, *rel[p].real, *rel[p].imag]
        buf.write(",".join(_cell(x, header[j]) for j, x in enumerate(row)) + "\n")
    return buf.getvalue()


def write_quality(out_dir, files: dict):
    """Write the files of a run into ``out_dir`` (created), each atomically."""
    return write_run(out_dir, files)
