"""``cfm-fem kinematics`` as one function, `run_kinematics`, behind both the command line and
`cfm_fem.api.run_kinematics`: the bench, the Monte Carlo of the probe position error over its
scan grid (in this process, adaptive, or on Dask workers), the budget and the GUM check, and the
files ``summary.json``, ``points.csv``, ``points.vtu`` and ``report.html``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import CfmInputError, check_seed
from .inputs import bench_provenance, choose_bench
from .results import KinematicsTable
from .sweep.distributed import backend_description

__all__ = ["KinematicsRun", "run_kinematics", "check_options"]


@dataclass
class KinematicsRun(KinematicsTable):
    """Everything ``cfm-fem kinematics`` writes: a `KinematicsTable` with its ``summary.json``.

    Attributes
    ----------
    summary : dict
        ``summary.json`` (Table IV pooling, budget, GUM check, assumptions, provenance).
    bench_sentence : str
        The bench the run assumed (`cfm_fem.io.bench_toml.resolve_bench`).
    """

    summary: dict = None
    bench_sentence: str = ""

    def write(self, out_dir, report: bool = True) -> dict:
        """Write ``summary.json``, ``points.csv``, ``points.vtu`` and (``report``)
        ``report.html`` with its figures into ``out_dir``; return the paths by role
        (``summary``, ``csv``, ``vtu``, ``report``)."""
        from ..io.kinematics_out import write_kinematics

        paths = write_kinematics(out_dir, self.result, self.bench, self.summary)
        if report:
            from ..io.run_files import write_run
            from ..report.kinematics import kinematics_report  # matplotlib: when used

            rep = kinematics_report(self.result, self.summary)
            paths["report"] = write_run(out_dir, {**rep.images, "report.html": rep.render()})[-1]
        return paths


def check_options(trials: int, seed: int, adaptive_digits=None, scheduler=None,
                  workers=None) -> None:  # fmt: skip
    """Every check of the options that needs no file read, run before the bench is read.

    Raises
    ------
    CfmInputError
        ``trials`` < 2 (not adaptive), ``adaptive_digits`` not 1..4, a seed the kernels cannot
        take, ``workers`` < 1 or Dask missing, adaptive with ``scheduler`` / ``workers``.
    """
    from .sweep.distributed import check_scale_out

    if adaptive_digits is None and trials < 2:
        raise CfmInputError(f"--trials must be >= 2; got {trials}")
    if adaptive_digits is not None and not 1 <= adaptive_digits <= 4:
        raise CfmInputError(f"--adaptive must be 1..4 significant digits; got {adaptive_digits}")
    check_seed(seed)
    # the conflict first: installing Dask, as the next check would say, would not help
    if adaptive_digits is not None and (scheduler is not None or workers is not None):
        raise CfmInputError(
            "--adaptive stops on the pooled result of all points and cannot be split over Dask "
            "workers; drop --scheduler/--workers or --adaptive"
        )
    check_scale_out(scheduler, workers)


def run_kinematics(bench=None, *, trials: int = 1_000_000, seed: int = 0, adaptive_digits=None,
                   fast_intervals: bool = False, scheduler=None, workers=None, q_cmd=None,
                   command_line=None, progress=None, on_start=None) -> KinematicsRun:  # fmt: skip
    """Probe positioning error over the bench's scan grid (``cfm-fem kinematics``, Table IV).

    Parameters
    ----------
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    trials, seed : int
    adaptive_digits : int, optional
        Adaptive Monte Carlo (JCGM 101 7.9) to this many significant digits (``trials`` is
        then ignored).
    fast_intervals : bool
        Skip the second pass of runs too long for the one exact pass.
    scheduler, workers
        Run on a Dask cluster (``tcp://HOST:PORT``) or a local one of ``workers`` processes.
    q_cmd : ndarray, shape (n, 3), mm, optional
        Commanded positions; default the bench's grid (in this process only).
    command_line : str, optional
        For the provenance.
    progress : callable(int), optional
        Called with the trials finished (the points finished on Dask).
    on_start : callable(str, int or None, str), optional
        Called once the bench is read: a line naming the run, the work to come and its unit.

    Returns
    -------
    KinematicsRun
    """
    from ..io.kinematics_out import kinematics_summary
    from ..io.provenance import provenance
    from ..models.kinematics.budget import gum_check, uncertainty_budget
    from ..models.kinematics.monte_carlo import run_kinematics as run
    from .sweep.distributed import dask_client, run_kinematics_dask

    check_options(trials, seed, adaptive_digits, scheduler, workers)
    model, sentence = choose_bench(bench)
    on_dask = scheduler is not None or workers is not None
    if on_dask and q_cmd is not None:
        raise CfmInputError("q_cmd applies in this process only, not on Dask workers")
    npts = len(model.grid_points()) if q_cmd is None else len(q_cmd)
    if on_start is not None:
        what = f"adaptive to {adaptive_digits} digits" if adaptive_digits else f"{trials} trials"
        total = npts if on_dask else (None if adaptive_digits else trials)
        on_start(f"{model.name} ({model.source}); {npts} points; {what}, seed {seed}", total,
                 "points" if on_dask else "trials")  # fmt: skip
    if on_dask:
        with dask_client(scheduler, workers) as client:
            res = run_kinematics_dask(client, model, trials, seed, exact=not fast_intervals,
                                      progress=progress)  # fmt: skip
    else:
        passes = 1 if (fast_intervals or adaptive_digits) else 2
        extra = {} if q_cmd is None else {"q_cmd": q_cmd}
        res = run(model, trials=trials, seed=seed, exact=not fast_intervals,
                  adaptive_digits=adaptive_digits, progress=_per_pass(progress, passes),
                  **extra)  # fmt: skip
    budget = uncertainty_budget(model, res.q_cmd)
    gum = gum_check(model, res)
    prov = provenance({"bench": bench_provenance(bench)}, command_line)  # packaged or given
    prov.update(bench_name=model.name, seed=int(seed), trials=int(res.trials),
                backend=backend_description(scheduler, workers))  # fmt: skip
    summary = kinematics_summary(res, model, budget=budget, gum=gum, extra={"provenance": prov})
    return KinematicsRun(res, model, summary, sentence)


def _per_pass(update, passes: int):
    """A progress callback for work that runs every trial ``passes`` times (the exact
    intervals take a second pass): it advances ``update`` in trials, so that the bar of a
    20,000-trial run ends at 20,000 trials."""
    if update is None:
        return None
    state = {"draws": 0, "shown": 0}

    def step(n: int = 1) -> None:
        state["draws"] += n
        now = state["draws"] // passes
        if now > state["shown"]:
            update(now - state["shown"])
            state["shown"] = now

    return step
