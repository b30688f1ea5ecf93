"""``cfm-fem tolerance`` as one function, `run_tolerance`, behind the command line: the bench,
the tolerance design for a target U_p per axis (`cfm_fem.models.kinematics.budget.
design_tolerances`), the bench of its plan, the optional Monte Carlo check of the plan, and the
files ``tolerance.json``, ``bench_plan.toml`` and ``report.html``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CfmInputError, check_seed
from .inputs import choose_bench

__all__ = ["ToleranceRun", "run_tolerance", "check_options", "MAX_TARGET_UM"]

#: Largest target (um): 1 m, far beyond any bench stroke; larger values only overflow U_p^2.
MAX_TARGET_UM = 1e6


@dataclass
class ToleranceRun:
    """Everything ``cfm-fem tolerance`` writes.

    Attributes
    ----------
    design : dict
        The design (`design_tolerances`), with ``plan_check_mc`` after a check.
    bench, plan_bench : Bench
        The bench, and the bench with the plan's factors applied.
    """

    design: dict
    bench: object
    plan_bench: object

    def document(self) -> dict:
        """``tolerance.json``: the design with the bench described; an infinite factor (an
        error that does not matter) written as ``"inf"``."""
        from ..io.kinematics_out import bench_description

        return _inf_as_text({**self.design, "bench": bench_description(self.bench)})

    def write(self, out_dir, command_line: str | None = None) -> list[Path]:
        """Write ``tolerance.json``, ``bench_plan.toml``, ``report.html`` and its figures into
        ``out_dir``: all or, if any fails, none."""
        from ..io._atomic import atomic_paths, json_text, write_text
        from ..io.bench_toml import write_bench
        from ..models.kinematics.budget import UP_SHARE_MEANING
        from ..report.tolerance import tolerance_report  # matplotlib: loaded only when used

        doc = self.document()
        rep = tolerance_report(doc, UP_SHARE_MEANING, command_line)
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = [out / n for n in ("tolerance.json", "bench_plan.toml", "report.html",
                                   *rep.images)]  # fmt: skip
        with atomic_paths(paths) as (tj, tb, th, *images):
            write_text(tj, json_text(doc))
            write_bench(tb, self.plan_bench)
            write_text(th, rep.render())
            for path, png in zip(images, rep.images.values(), strict=True):
                path.write_bytes(png)
        return paths


def check_options(target_um, check_trials: int = 0, seed: int = 0) -> None:
    """Refuse a target not in (0, `MAX_TARGET_UM`] per axis, a check of 1 or fewer than 0
    trials, and a seed the kernels cannot take."""
    check_seed(seed)
    if len(target_um) != 3 or any(not x > 0 for x in target_um):
        raise CfmInputError(f"--target must be one or three positive numbers in um; got "
                            f"{','.join(f'{x:g}' for x in target_um)}")  # fmt: skip
    if any(not x <= MAX_TARGET_UM for x in target_um):
        shown = ",".join(f"{x:g}" for x in target_um)
        raise CfmInputError(
            f"--target must be at most {MAX_TARGET_UM:g} um (1 m) per axis; got {shown} "
            "(larger values only overflow U_p^2)"
        )
    if check_trials < 0 or check_trials == 1:
        raise CfmInputError(f"--check must be 0 or >= 2 trials; got {check_trials}")


def run_tolerance(target_um, bench=None, *, check_trials: int = 0, seed: int = 0,
                  progress=None) -> ToleranceRun:  # fmt: skip
    """How far each of the 21 tolerances of a bench may go for a target U_p per axis.

    Parameters
    ----------
    target_um : sequence of 3 float, um
        Target U_p of X, Y, Z.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    check_trials : int
        Verify the plan with a Monte Carlo of this many trials (0: no check).
    seed : int
        Of the check.
    progress : callable(int), optional
        Called with the trials of the check finished.

    Returns
    -------
    ToleranceRun
    """
    from ..models.kinematics.budget import design_tolerances
    from ..models.kinematics.monte_carlo import run_kinematics

    target = [float(x) for x in target_um]
    check_options(target, check_trials, seed)
    model, _ = choose_bench(bench)
    d = design_tolerances(model, np.asarray(target) * 1e-3)
    plan_bench = model.scaled_errors(_plan_factors(model, d["plan"]))
    if check_trials:  # exact=False: one pass over the trials
        res = run_kinematics(plan_bench, trials=check_trials, seed=seed, exact=False,
                             progress=progress, option="tolerance --check")  # fmt: skip
        d["plan_check_mc"] = {a: res.pooled[a] for a in "xyz"}
        d["plan_check_mc"]["trials"] = res.trials
    return ToleranceRun(d, model, plan_bench)


def _inf_as_text(obj):
    """``obj`` with every infinite float as the string ``"inf"`` (JSON has no infinity): a factor
    is infinite when its error does not matter, which a bench without errors makes of all."""
    if isinstance(obj, dict):
        return {k: _inf_as_text(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_inf_as_text(v) for v in obj]
    if isinstance(obj, float | np.floating) and np.isinf(obj):
        return "inf" if obj > 0 else "-inf"
    return obj


def _plan_factors(bench, plan):
    f = np.ones(len(bench.errors))
    names = [e.name for e in bench.errors]
    for step in plan:
        f[names.index(step["name"])] = step["factor"]
    return f
