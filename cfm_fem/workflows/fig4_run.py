"""``cfm-fem fig4`` as one function, `run_fig4`, behind the command line: the field map, the
Gaussian sweep of `cfm_fem.workflows.fig4`, its summary over the magnet body, and the files
``fig4.json``, ``fig4.csv`` and ``report.html`` with its figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..errors import check_seed

__all__ = ["Fig4Run", "run_fig4"]

#: Columns of ``fig4.csv`` and the summary table's keys.
CSV_COLUMNS = ("U_p_um", "nodes", "p50_units", "p95_units", "max_units", "analytic_units",
               "paper_units")  # fmt: skip
_KEYS = ("up_um", "nodes", "p50", "p95", "max", "analytic", "paper")


@dataclass
class Fig4Run:
    """Everything ``cfm-fem fig4`` writes.

    Attributes
    ----------
    result : cfm_fem.models.sweep.SweepResult
    summary : dict
        ``fig4.json``.
    command_line : str or None
        Shown in the report.
    """

    result: object
    summary: dict
    command_line: str | None = None

    def csv(self) -> str:
        """``fig4.csv``: one row per U_p."""
        rows = [",".join(CSV_COLUMNS)]
        for r in self.summary["table"]:
            rows.append(",".join("" if r[k] is None else f"{r[k]:.6g}" for k in _KEYS))
        return "\n".join(rows) + "\n"

    def write(self, out_dir) -> list[Path]:
        """Write ``fig4.json``, ``fig4.csv``, the figures and ``report.html``."""
        from ..io.run_files import write_run
        from ..report.runs import fig4_report  # matplotlib: loaded only when used
        from .fig4 import plane_nodes

        pts, uf = plane_nodes(self.result)
        rep = fig4_report(self.summary, pts, uf, self.command_line)
        files = {"fig4.json": self.summary, "fig4.csv": self.csv()}
        files.update(rep.images)
        files["report.html"] = rep.render()
        return write_run(out_dir, files)


def run_fig4(field, up_um=(0, 10, 20, 30, 40, 50), *, trials: int = 2000, seed: int = 0,
             b_ref_T=None, field_model: str = "linear", reader=None, command_line=None,
             progress=None, on_start=None) -> Fig4Run:  # fmt: skip
    """U_f (95 %) against U_p on a field map, as the paper's Fig. 4 (``cfm-fem fig4``).

    Parameters
    ----------
    field : path-like or FieldMap
    up_um : sequence of float, um
    trials, seed : int
    b_ref_T : float, optional, T
        B_ref (default max |B| of the map).
    field_model : {"linear", "harmonic"}
    reader : dict, optional
        Keyword arguments of `cfm_fem.io.read_field`.
    command_line : str, optional
        For the provenance and the report.
    progress : callable(int), optional
        Called with the nodes finished.
    on_start : callable(str, int, str), optional
        Called once the map is read: a line naming the run, the nodes and ``"nodes"``.

    Returns
    -------
    Fig4Run
    """
    from ..io.provenance import provenance
    from .fig4 import fig4_summary
    from .fig4 import run_fig4 as run
    from .inputs import field_map
    from .sweep.problem import check_options
    from .sweep.run import check_up_values

    up = [float(u) for u in up_um]
    check_up_values(up)
    check_seed(seed)
    check_options(trials, (1.0, 1.0, 1.0), b_ref_T, len(up))
    fm = field_map(field, reader)
    if on_start is not None:
        on_start(f"{fm.n_nodes} nodes from {fm.source}; U_p = {', '.join(f'{u:g}' for u in up)} "
                 f"um; {trials} trials", fm.n_nodes, "nodes")  # fmt: skip
    res = run(fm, up, trials=trials, seed=seed, b_ref_T=b_ref_T, field_model=field_model,
              progress=progress)  # fmt: skip
    summary = fig4_summary(res)
    field_path = None if hasattr(field, "points") else field
    summary["provenance"] = provenance({"field": field_path}, command_line)
    return Fig4Run(res, summary, command_line)
