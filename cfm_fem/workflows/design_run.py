"""``cfm-fem design`` as one function, `run_design`, behind both the command line and
`cfm_fem.api.run_design`: a Gaussian sweep over U_p (`cfm_fem.workflows.sweep.run`), the
coverage percentile of U_f over the nodes of a region, and the largest U_p that keeps it at or
below the target (`cfm_fem.workflows.design.admissible_up`), written as the sweep's outputs,
``design.json`` and the report with the answer on top. `design_answer` answers the question
for a sweep already run.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import CfmInputError, check_seed
from .design import DesignAnswer, admissible_up, region_mask

__all__ = ["DesignRun", "run_design", "design_answer", "check_question", "DEFINITION"]

DEFINITION = (
    "largest U_p whose coverage quantile of U_f over the region's nodes with a U_f figure is "
    "<= uf_max (cfm_fem.workflows.design); u_up_max_um: standard deviation of a bootstrap that "
    "redraws both interval ends of every node within their Monte Carlo standard errors. At "
    "finite trials U_f is biased slightly high (the larger of two noisy ends), so the answer "
    "errs low, on the safe side"
)


@dataclass
class DesignRun:
    """Everything ``cfm-fem design`` writes.

    Attributes
    ----------
    answer : DesignAnswer
        Its attributes are reachable on the run too (``run.up_max_um``, ``run.sentence()``).
    maps : cfm_fem.workflows.results.SweepMaps
        The sweep behind the answer.
    document : dict
        ``design.json``.
    provenance : dict
        Of the sweep's outputs.
    """

    answer: DesignAnswer
    maps: object
    document: dict
    provenance: dict

    def __getattr__(self, name):
        if name == "answer":  # not yet set (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.answer, name)

    def write(self, out_dir, report: bool = True) -> list[Path]:
        """Write the sweep's maps, ``sweep.pvd``, ``summary.json``, ``design.json`` and (with
        ``report``) ``report.html`` with the answer on top; return the files written."""
        from ..io.run_files import write_run
        from ..io.sweep_out import write_sweep

        write_sweep(out_dir, self.maps.result, self.provenance, remove_stale=True)
        written = write_run(out_dir, {"design.json": self.document})
        if report:
            from ..report.sweep import write_sweep_report

            written += list(write_sweep_report(out_dir, design=self.document) or [])
        return written


def check_question(up_um, uf_max: float, coverage: float) -> None:
    """Refuse U_p values that do not increase, a target <= 0 and a coverage outside (0, 1]."""
    if any(b <= a for a, b in zip(up_um, up_um[1:], strict=False)):
        raise CfmInputError(f"--up values must increase; got {', '.join(f'{u:g}' for u in up_um)}")
    if not uf_max > 0:
        raise CfmInputError(f"--uf-max must be > 0 units; got {uf_max}")
    if not 0 < coverage <= 1:
        raise CfmInputError(f"--coverage must be in (0, 1]; got {coverage}")


def design_answer(maps, uf_max: float, *, coverage: float = 0.95, region=None,
                  seed: int = 0) -> DesignAnswer:  # fmt: skip
    """Largest U_p that keeps U_f <= ``uf_max`` units over ``coverage`` of the nodes (of
    ``region``) of a mode-gauss sweep ``maps`` (`cfm_fem.workflows.results.SweepMaps`)."""
    from ..models.region import parse_region

    box = parse_region(region) if isinstance(region, str) else region
    res = maps.result
    inside = region_mask(maps.points, box)
    ends = res.to_units(res.stats[inside][:, :, 3, 2:4])  # |B|: symmetric 95 % interval
    return admissible_up(maps.up_um, ends[..., 0], ends[..., 1], res.complete()[inside], uf_max,
                         coverage=coverage, rel_mc_std=maps.summary["uf_relative_mc_std"],
                         seed=seed)  # fmt: skip


def run_design(field, uf_max: float, *, up_um=(0, 10, 20, 30, 40, 50), coverage: float = 0.95,
               region=None, trials: int = 10_000, seed: int = 0, b_ref_T=None,
               outside: str = "exclude", field_model: str = "auto", reader=None,
               command_line=None, progress=None, on_start=None) -> DesignRun:  # fmt: skip
    """Largest U_p that keeps U_f <= ``uf_max`` over ``coverage`` of the nodes of a map (or
    of ``region``), from a sweep over ``up_um`` (``cfm-fem design``).

    Parameters
    ----------
    field : path-like or FieldMap
    uf_max : float
        Target U_f, units of 1e-4 B_ref.
    up_um : sequence of float, um
        Increasing U_p values of the sweep.
    coverage : float
        Share of the nodes that must meet the target, in (0, 1].
    region : Region or str, optional
        Only the nodes inside it (box or cylinder, `cfm_fem.models.region.parse_region`).
    trials, seed, b_ref_T, outside, field_model, reader
        Of the sweep (`cfm_fem.workflows.sweep.run.run_sweep`).
    command_line : str, optional
        For the provenance.
    progress : callable(int), optional
        Called with the nodes finished.
    on_start : callable(str, int, str), optional
        Called once the map is read: a line naming the run, the nodes and ``"nodes"``.

    Returns
    -------
    DesignRun
    """
    from ..io.provenance import provenance
    from ..models.region import parse_region
    from .inputs import field_map
    from .sweep.problem import check_options
    from .sweep.run import run_sweep

    up = [float(u) for u in up_um]
    check_question(up, uf_max, coverage)
    check_seed(seed)
    check_options(trials, (1.0, 1.0, 1.0), b_ref_T, len(up))
    box = parse_region(region) if isinstance(region, str) else region
    fm = field_map(field, reader)
    inside = region_mask(fm.points, box)
    if not inside.any():
        raise CfmInputError(f"--region holds none of the {fm.n_nodes} nodes of {fm.source}")
    if on_start is not None:
        on_start(f"{fm.n_nodes} nodes from {fm.source} ({int(inside.sum())} in the region); "
                 f"U_p = {', '.join(f'{u:g}' for u in up)} um; {trials} trials per node",
                 fm.n_nodes, "nodes")  # fmt: skip
    maps = run_sweep(fm, up, trials=trials, seed=seed, b_ref_T=b_ref_T, outside=outside,
                     field_model=field_model, region=box, progress=progress)  # fmt: skip
    prov = provenance({"field": None if hasattr(field, "points") else field}, command_line)
    prov.update(seed=int(seed), trials=int(trials))
    ans = design_answer(maps, uf_max, coverage=coverage, region=box, seed=seed)
    doc = {
        "answer": ans.sentence(),
        **ans.to_dict(),
        "region_mm": None if box is None else box.to_json(),
        "region_nodes": int(inside.sum()),
        "b_ref_T": maps.summary["b_ref_T"],
        "field_model": maps.summary["field_model"],
        "trials": int(trials),
        "seed": int(seed),
        "definition": DEFINITION,
        "provenance": prov,
    }
    return DesignRun(ans, maps, doc, prov)
