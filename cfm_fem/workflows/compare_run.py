"""``cfm-fem compare`` as one function, `run_compare`, behind both the command line and
`cfm_fem.api.run_compare`: a tracker recording against the kinematic Monte Carlo (Table IV,
Fig. 12, ISO 230-2), or a Hall map against its reference field and the coupled Monte Carlo
(Table V, Fig. 13), with the files ``compare.json``, ``points.csv`` and ``report.html``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import CfmInputError
from .coupled_run import BUDGET_TRIALS, bench_for, check_trials, reference_model
from .inputs import bench_provenance, recording, refuse_reader_options

__all__ = ["CompareRun", "run_compare", "check_options"]


@dataclass
class CompareRun:
    """Everything ``cfm-fem compare`` writes.

    Attributes
    ----------
    comparison : TrackerComparison or HallComparison
        `cfm_fem.workflows.compare`; its attributes are reachable on the run too
        (``run.pooled_exp``).
    summary : dict
        ``compare.json``.
    command_line : str or None
        Shown in the report.
    """

    comparison: object
    summary: dict
    command_line: str | None = None

    def __getattr__(self, name):
        if name == "comparison":  # not yet set (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.comparison, name)

    @property
    def kind(self) -> str:
        """``"tracker"`` or ``"hall"``."""
        from .compare import TrackerComparison

        return "tracker" if isinstance(self.comparison, TrackerComparison) else "hall"

    def files(self) -> dict:
        """File name -> contents (dict, text or PNG bytes) of the run."""
        from ..io.compare_out import hall_points_csv, tracker_points_csv
        from ..report.runs import hall_report, tracker_report  # matplotlib: when used

        tracker = self.kind == "tracker"
        report = (tracker_report if tracker else hall_report)(
            self.comparison, self.summary, self.command_line
        )
        points = (tracker_points_csv if tracker else hall_points_csv)(self.comparison)
        files = {"compare.json": self.summary, "points.csv": points}
        files.update(report.images)
        files["report.html"] = report.render()
        return files

    def write(self, out_dir) -> list[Path]:
        """Write the run's files into ``out_dir`` (`cfm_fem.io.run_files.write_run`)."""
        from ..io.run_files import write_run

        return write_run(out_dir, self.files())


def check_options(kind: str, reference=None, tracker_u_um: float = 0.0, reader=None) -> None:
    """The checks that need no file read: a tracker recording takes no reference and no reader
    option; ``tracker_u_um`` >= 0. ``kind``: "tracker" or "hall"."""
    if kind == "tracker":
        if reference is not None:
            raise CfmInputError("--reference applies to --hall-map only")
        refuse_reader_options(reader, "--tracker reads no field map (--hall-map --reference does)")
    if not tracker_u_um >= 0:
        raise CfmInputError(f"--tracker-u-um must be >= 0; got {tracker_u_um}")


def run_compare(rec, reference=None, bench=None, *, trials: int = 100_000, seed: int = 0,
                tracker_u_um: float = 0.0, probe="paper", align: str = "placement",
                centre_magnet: bool = False, b_ref_T=None, r_ref_mm=None,
                field_model: str = "linear", reader=None, budget: bool = True,
                command_line=None, progress=None, on_start=None) -> CompareRun:  # fmt: skip
    """A recording against the simulation (``cfm-fem compare``).

    Parameters
    ----------
    rec : Recording or path-like
        A tracker recording or a Hall map (mm, T).
    reference : path-like, FieldMap or None
        Hall maps: a harmonics file or field map (`reference_model`); None: QFDp4.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    trials, seed : int
    tracker_u_um : float, um
        Tracker: its standard uncertainty, added to the simulated std in the residuals.
    probe, align, centre_magnet, b_ref_T, r_ref_mm, field_model, reader
        As `cfm_fem.workflows.coupled_run.run_coupled`.
    budget : bool
        Hall maps: also the positioning-only / probe-only split.
    command_line : str, optional
    progress : callable(int), optional
        Called with the trials (tracker) or points (Hall map) finished.
    on_start : callable(str, int or None, str), optional
        Called once the inputs are checked: a line naming the run, the work to come and its
        unit.

    Returns
    -------
    CompareRun
    """
    from ..io.compare_out import hall_summary, tracker_summary
    from ..io.provenance import provenance

    rec = recording(rec)
    check_trials(trials, seed)
    check_options(rec.kind, reference, tracker_u_um, reader)
    model, bench_note = bench_for(bench, centre_magnet)
    if rec.kind == "tracker":
        comp, extra = _tracker(rec, model, trials, seed, tracker_u_um, progress, on_start)
        inputs = {"bench": bench_provenance(bench), "tracker": _source(rec)}
        build = tracker_summary
    else:
        fm, ref_path = reference_model(reference, b_ref_T=b_ref_T, r_ref_mm=r_ref_mm,
                                       field_model=field_model, reader=reader)  # fmt: skip
        comp, extra = _hall(rec, fm, model, trials=trials, seed=seed, probe=probe, align=align,
                            budget=budget, progress=progress, on_start=on_start)  # fmt: skip
        inputs = {"bench": bench_provenance(bench), "hall_map": _source(rec),
                  "reference": None if ref_path is None else str(ref_path)}  # fmt: skip
        build = hall_summary
    if bench_note:
        comp.notes.append(bench_note)
    prov = provenance(inputs, command_line)
    summary = build(comp, model, **extra, extra={"provenance": prov})
    return CompareRun(comp, summary, command_line)


def _source(rec):
    return str(rec.source) if Path(str(rec.source)).is_file() else None


def _tracker(rec, bench, trials, seed, tracker_u_um, progress, on_start):
    """The comparison of a tracker recording and the summary's extra arguments."""
    from ..models.kinematics.budget import uncertainty_budget
    from .compare import compare_tracker

    if on_start is not None:
        on_start(f"{rec.source}: {len(rec)} readings; {trials} trials", None, "trials")
    comp = compare_tracker(rec, bench, trials=trials, seed=seed, tracker_u_um=tracker_u_um,
                           progress=progress)  # fmt: skip
    return comp, {"budget": uncertainty_budget(bench, comp.cmd)}


def _hall(rec, fm, bench, *, trials, seed, probe, align, budget, progress, on_start):
    """The comparison of a Hall map and the summary's extra arguments."""
    from ..models.probe import HallProbe
    from .compare import compare_hall
    from .coupled import field_budget

    hp = probe if isinstance(probe, HallProbe) else HallProbe(model=probe)
    _, pts = rec.point_cmd()
    if on_start is not None:
        on_start(f"{rec.source}: {len(rec)} readings at {len(pts)} points; {trials} trials",
                 len(pts), "points")  # fmt: skip
    comp = compare_hall(rec, fm, bench, probe=hp, trials=trials, seed=seed, align=align,
                        progress=progress)  # fmt: skip
    fb = None
    if budget:
        fb = field_budget(fm, bench, pts, probe=hp, trials=min(trials, BUDGET_TRIALS),
                          seed=seed, align=align)  # fmt: skip
    return comp, {"field_budget": fb}
