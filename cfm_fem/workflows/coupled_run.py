"""``cfm-fem coupled`` as one function, `run_coupled`, behind both the command line and
`cfm_fem.api.run_coupled`: the reference field (QFDp4, a harmonics file or a field map), the
bench, the scan region (given points, or the command line's radius, step and z planes, checked
inside the map), the coupled Monte Carlo with its positioning-only / probe-only split, and the
files ``summary.json``, ``points.csv``, ``report.html`` (`cfm_fem.io.compare_out`).

`reference_model`, `bench_for` and `check_trials` serve ``cfm-fem compare`` too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CfmInputError, check_seed
from ..models.field import FieldMap
from ..models.field_model import FieldModel
from .inputs import bench_provenance, choose_bench, refuse_reader_options
from .results import CoupledTable

__all__ = ["CoupledRun", "run_coupled", "reference_model", "bench_for", "check_trials",
           "scan_region", "MAX_REGION_POINTS", "BUDGET_TRIALS"]  # fmt: skip

#: Most scan points of --radius/--step: each point is a full Monte Carlo of --trials (default
#: 1e5) probe positions, so 100,000 points are already hours; --step 0.002 (metres typed as mm)
#: would ask for 78.5 million points and a 1.2 GB array before the run.
MAX_REGION_POINTS = 100_000
#: Largest trial count of the positioning-only / probe-only split (two extra runs).
BUDGET_TRIALS = 20_000
#: The paper's five planes along the magnet axis, mm, for a multipole reference.
DEFAULT_Z_MM = (-100.0, -50.0, 0.0, 50.0, 100.0)


@dataclass
class CoupledRun(CoupledTable):
    """Everything ``cfm-fem coupled`` writes: a `CoupledTable` with its ``summary.json``.

    Attributes
    ----------
    summary : dict
        ``summary.json`` (Table V beside the paper, budgets, provenance).
    command_line : str or None
        Shown in the report.
    """

    summary: dict = None
    command_line: str | None = None

    def files(self) -> dict:
        """File name -> contents (dict, text or PNG bytes) of the run."""
        from ..io.compare_out import coupled_points_csv
        from ..report.runs import coupled_report  # matplotlib: loaded only when used

        rep = coupled_report(self.result, self.summary, self.command_line)
        files = {"summary.json": self.summary, "points.csv": coupled_points_csv(self.result)}
        files.update(rep.images)
        files["report.html"] = rep.render()
        return files

    def write(self, out_dir) -> list[Path]:
        """Write the run's files into ``out_dir`` (`cfm_fem.io.run_files.write_run`)."""
        from ..io.run_files import write_run

        return write_run(out_dir, self.files())


def check_trials(trials: int, seed: int) -> None:
    """Refuse fewer than 20 trials and a seed the kernels cannot take."""
    if trials < 20:
        raise CfmInputError(f"--trials must be >= 20; got {trials}")
    check_seed(seed)


def bench_for(bench=None, centre_magnet: bool = False):
    """``(bench, note)``: the bench (`choose_bench`), moved so that the magnet origin sits at
    mid-travel of X and Y with ``centre_magnet``; ``note`` says so (else None)."""
    from .coupled import centred_on_travel

    model, _ = choose_bench(bench)
    if centre_magnet:
        return centred_on_travel(model), "magnet moved to mid-travel of X and Y (--centre-magnet)"
    return model, None


def reference_model(field=None, *, b_ref_T=None, r_ref_mm=None, field_model: str = "linear",
                    reader=None, default: str = "QFDp4"):  # fmt: skip
    """``(FieldModel, path or None)`` of a reference field and the file it came from.

    Parameters
    ----------
    field : path-like, FieldMap, FieldModel or None
        A harmonics file or field map; None: the paper's QFDp4 harmonics (bundled).
    b_ref_T : float, optional, T
        B_ref of a field map (default max |B|).
    r_ref_mm : float, optional, mm
        R_ref of a harmonics file that does not state it.
    field_model : {"linear", "harmonic"}
        A field map between its nodes.
    reader : dict, optional
        Keyword arguments of `cfm_fem.io.read_field` for a field map file.
    default : str
        What None stands for, in the refusals.
    """
    if isinstance(field, FieldModel):
        return field, None
    if isinstance(field, FieldMap):
        refuse_reader_options(reader, "the field map is already read")
        return FieldModel.from_map(field, b_ref_T, field_model), None
    if field is None:
        from ..io.harmonics import qfdp4_path, read_qfdp4

        why = f"without --field the bundled {default} harmonics are used"
        refuse_reader_options(reader, why)
        if field_model != "linear":
            raise CfmInputError(f"--field-model applies to a field map given with --field; {why}")
        return FieldModel.from_multipole(read_qfdp4()), qfdp4_path()
    from ..io.reference_field import read_reference

    model = read_reference(field, b_ref_T=b_ref_T, r_ref_mm=r_ref_mm, field_model=field_model,
                           **(reader or {}))  # fmt: skip
    return model, field


def scan_region(fm: FieldModel, radius_mm=None, step_mm: float = 2.0, z_mm=None):
    """``(points (n, 3) mm, description)`` of the default scan region: a transverse grid of
    ``step_mm`` inside r <= ``radius_mm`` (default R_ref, or 0.8 x a map's transverse extent)
    on the planes ``z_mm`` (default the paper's five, or five over the middle half of a map)."""
    from .coupled import default_region

    z = None if z_mm is None else [float(v) for v in z_mm]
    if z is not None and (not z or not all(np.isfinite(z))):
        raise CfmInputError(f"--z must be comma-separated finite numbers in mm; got {z_mm!r}")
    if fm.multipole is not None:
        r = fm.multipole.r_ref if radius_mm is None else radius_mm
        z = list(DEFAULT_Z_MM) if z is None else z
        what = f"R_ref = {fm.multipole.r_ref:g} mm" if radius_mm is None else "--radius"
    else:
        pts = fm.fieldmap.points
        half = min(np.abs(pts[:, 0]).max(), np.abs(pts[:, 1]).max())
        r = 0.8 * half if radius_mm is None else radius_mm
        if z is None:
            z0, z1 = pts[:, 2].min(), pts[:, 2].max()
            z = list(np.linspace(0.75 * z0 + 0.25 * z1, 0.25 * z0 + 0.75 * z1, 5))
        what = "0.8 x the map's transverse extent" if radius_mm is None else "--radius"
    if not (r > 0 and step_mm > 0):
        raise CfmInputError("--radius and --step must be > 0 mm")
    n_est = np.pi * (r / step_mm) ** 2 * len(z)  # grid points inside the circle, all planes
    if not n_est <= MAX_REGION_POINTS:
        raise CfmInputError(
            f"--step {step_mm:g} mm inside r <= {r:g} mm ({what}) on {len(z)} plane(s) asks "
            "for about "
            f"{n_est:.3g} scan points; expected at most {MAX_REGION_POINTS:,} (the step is in mm: "
            f"{r * np.sqrt(np.pi * len(z) / MAX_REGION_POINTS):.2g} mm or more here)"
        )
    pts = default_region(r, step_mm, z)
    desc = (
        f"transverse grid step {step_mm:g} mm inside r <= {r:g} mm ({what}), "
        f"z planes {', '.join(f'{v:g}' for v in z)} mm (magnet frame); {len(pts)} points"
    )
    return pts, desc


def _check_inside(fm, points, field_path, default_radius: bool) -> None:
    """Name the map and the options when the scan region leaves a field map (the default region
    is centred on the z axis, which a map need not be)."""
    if fm.multipole is not None:
        return
    _, inside = fm.field(points)
    if inside.all():
        return
    i = int(np.argmax(~inside))
    pts = fm.fieldmap.points
    span = ", ".join(
        f"{a} {lo:g}..{hi:g}" for a, lo, hi in zip("xyz", pts.min(0), pts.max(0), strict=True)
    )
    why = "the default region is centred on the z axis: " if default_radius else ""
    raise CfmInputError(
        f"scan point {points[i].tolist()} mm is outside the field map, which spans {span} mm; "
        f"{why}set --radius and --z to a region inside the map",
        file=field_path,
    )


def run_coupled(field=None, bench=None, points=None, *, radius_mm=None, step_mm: float = 2.0,
                z_mm=None, trials: int = 100_000, seed: int = 0, probe="paper",
                align: str = "placement", centre_magnet: bool = False, b_ref_T=None,
                r_ref_mm=None, field_model: str = "linear", reader=None, budget: bool = True,
                command_line=None, progress=None, on_start=None) -> CoupledRun:  # fmt: skip
    """Coupled Monte Carlo of the field error at scan points (``cfm-fem coupled``, Table V).

    Parameters
    ----------
    field : path-like, FieldMap or None
        Harmonics file or field map (`reference_model`); None: the paper's QFDp4.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    points : ndarray, shape (n, 3), mm, optional
        Scan points (magnet frame); default the region of ``radius_mm``, ``step_mm``, ``z_mm``
        (`scan_region`).
    trials, seed : int
    probe : {"paper", "table1"} or HallProbe
    align : {"placement", "probe"}
    centre_magnet : bool
        Move the magnet origin to mid-travel of X and Y.
    b_ref_T, r_ref_mm, field_model, reader
        Of the reference (`reference_model`).
    budget : bool
        Also the positioning-only / probe-only split (two runs of at most `BUDGET_TRIALS`).
    command_line : str, optional
        For the provenance and the report.
    progress : callable(int), optional
        Called with the points finished.
    on_start : callable(str, int), optional
        Called once the inputs are checked: a line naming the run, and the number of points.

    Returns
    -------
    CoupledRun
    """
    from ..io.compare_out import coupled_summary
    from ..io.provenance import provenance
    from ..models.kinematics.budget import uncertainty_budget
    from ..models.probe import HallProbe
    from .coupled import field_budget
    from .coupled import run_coupled as run

    check_trials(trials, seed)
    model, bench_note = bench_for(bench, centre_magnet)
    fm, field_path = reference_model(field, b_ref_T=b_ref_T, r_ref_mm=r_ref_mm,
                                     field_model=field_model, reader=reader)  # fmt: skip
    if points is None:
        points, region = scan_region(fm, radius_mm, step_mm, z_mm)
    else:
        points = np.asarray(points, dtype=np.float64)
        region = f"{len(points)} points given"
    _check_inside(fm, points, field_path, radius_mm is None)
    hp = probe if isinstance(probe, HallProbe) else HallProbe(model=probe)
    if on_start is not None:
        on_start(f"{fm.describe()}; {region}; {trials} trials, seed {seed}, align {align}",
                 len(points))  # fmt: skip
    res = run(fm, model, points, probe=hp, trials=trials, seed=seed, align=align, region=region,
              progress=progress)  # fmt: skip
    fb = None
    if budget:
        fb = field_budget(fm, model, points, probe=hp, trials=min(trials, BUDGET_TRIALS),
                          seed=seed, align=align)  # fmt: skip
    if bench_note:
        res.notes.append(bench_note)
    prov = provenance({"bench": bench_provenance(bench), "field": field_path}, command_line)
    summary = coupled_summary(res, model, field_budget=fb,
                              bench_budget=uncertainty_budget(model, res.q_cmd),
                              extra={"provenance": prov})  # fmt: skip
    return CoupledRun(res, model, summary, command_line)
