"""Labelled views of the results for Python users: per component and U_p by name, not by the
axes of 4-D arrays (`cfm_fem.api` returns them).

Components are ``"Bx"``, ``"By"``, ``"Bz"``, ``"absB"`` (field) and ``"x"``, ``"y"``, ``"z"``,
``"norm"`` (probe position); a sweep's columns are picked by ``up_um=`` (mode gauss) or
``column=`` (``"up20um"``, ``"htm_geometric"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError

__all__ = ["SweepMaps", "KinematicsTable", "CoupledTable", "FIELD_COMPONENTS", "AXES"]

FIELD_COMPONENTS = ("Bx", "By", "Bz", "absB")
AXES = ("x", "y", "z", "norm")
#: Statistics of the error per node (the last axis of `SweepResult.stats`).
SWEEP_STATS = ("systematic", "u", "sym95_low", "sym95_high", "short95_low", "short95_high")


def _index(name, names, what) -> int:
    key = "absB" if name == "|B|" else name
    if key not in names:
        raise CfmInputError(f"{what} {name!r} unknown; expected one of {', '.join(names)}")
    return names.index(key)


@dataclass
class SweepMaps:
    """U_f maps of a sweep (`cfm_fem.run_sweep`).

    Attributes
    ----------
    result : cfm_fem.models.sweep.SweepResult
        Everything, as arrays.
    summary : dict
        The ``summary.json`` document (percentiles over the nodes with a U_f figure).
    """

    result: object
    summary: dict

    @property
    def points(self) -> np.ndarray:
        """Node positions, shape (n, 3), mm."""
        return self.result.fieldmap.points

    @property
    def up_um(self) -> list:
        """U_p of each column, um."""
        return self.result.column_up_um()

    @property
    def columns(self) -> list:
        """Column names: ``up20um`` (gauss) or ``htm_total``, ``htm_geometric``, ... (htm)."""
        return self.result.labels

    def column(self, up_um=None, column=None) -> int:
        """Index of the column with U_p = ``up_um`` (um) or named ``column``; either may be
        left out when the sweep has one column."""
        if column is not None:
            return _index(column, self.columns, "column")
        if up_um is not None:
            ups = np.asarray(self.up_um)
            k = int(np.argmin(np.abs(ups - float(up_um))))
            if not np.isclose(ups[k], float(up_um), rtol=1e-9, atol=1e-12):
                raise CfmInputError(f"U_p = {up_um} um is not in this sweep; it has "
                                    f"{', '.join(f'{u:g}' for u in ups)} um")  # fmt: skip
            return k
        if len(self.columns) == 1:
            return 0
        raise CfmInputError(f"give up_um= or column=; this sweep has {', '.join(self.columns)}")

    def complete(self, up_um=None, column=None) -> np.ndarray:
        """Nodes with a U_f figure (every trial has a value), shape (n,), bool."""
        return self.result.complete()[:, self.column(up_um, column)]

    def uf(self, component: str = "absB", up_um=None, column=None) -> np.ndarray:
        """Symmetric 95 % expanded uncertainty of ``component`` per node, shape (n,), units of
        1e-4 B_ref; NaN at nodes without a figure. ``component="absB"`` is U_f."""
        c = _index(component, FIELD_COMPONENTS, "component")
        k = self.column(up_um, column)
        st = self.result.stats[:, k, c]
        u95 = self.result.to_units(np.maximum(np.abs(st[:, 2]), np.abs(st[:, 3])))
        return np.where(self.result.complete()[:, k], u95, np.nan)

    def stat(self, name: str, component: str = "absB", up_um=None, column=None) -> np.ndarray:
        """One statistic of the error B_meas - B_nom per node, shape (n,), units; ``name`` one
        of `SWEEP_STATS`; NaN at nodes without a figure."""
        s = _index(name, SWEEP_STATS, "statistic")
        c = _index(component, FIELD_COMPONENTS, "component")
        k = self.column(up_um, column)
        values = self.result.to_units(self.result.stats[:, k, c, s])
        return np.where(self.result.complete()[:, k], values, np.nan)

    def percentile(self, q: float, up_um=None, column=None, per_node: bool = False) -> float:
        """The ``q`` % percentile of U_f over the nodes with a figure (of the region of
        interest, if the sweep has one), units, as ``summary.json``'s ``uf_units``: each node
        weighted by the volume it stands for (`cfm_fem.models.node_weights`); ``per_node``
        counts every node once instead (``uf_units_per_node``)."""
        from ..models.node_weights import weighted_percentiles
        from ..models.region import region_mask

        res = self.result
        v = self.uf("absB", up_um, column)
        keep = np.isfinite(v) & region_mask(res.fieldmap.points, res.config.region)
        if not keep.any():
            return float("nan")
        if per_node:
            return float(np.percentile(v[keep], q))
        return float(weighted_percentiles(v[keep], res.node_volumes()[keep], [q])[0])

    def write(self, out_dir, provenance: dict | None = None, report: bool = True) -> list:
        """Write the maps, ``sweep.pvd``, ``open_in_paraview.py``, ``summary.json`` and (with
        ``report``) ``report.html`` into ``out_dir``; return what was written."""
        from pathlib import Path

        from ..io.sweep_out import write_sweep

        write_sweep(out_dir, self.result, provenance)
        out = Path(out_dir)
        names = ["sweep.pvd", "open_in_paraview.py", "summary.json"]
        written = sorted(out.glob("uf_*.vtu")) + [out / n for n in names]
        if report:
            from ..report.sweep import write_sweep_report

            written += write_sweep_report(out_dir)
        return written


@dataclass
class KinematicsTable:
    """Probe positioning error of a bench (`cfm_fem.run_kinematics`, paper Table IV).

    Attributes
    ----------
    result : cfm_fem.models.kinematics.monte_carlo.KinematicsResult
    bench : cfm_fem.models.bench.Bench
    """

    result: object
    bench: object

    def axis(self, axis: str) -> dict:
        """Table IV row of ``axis`` ("x", "y", "z", "norm"): ``systematic_um``, ``std_um``,
        ``U_p_um`` (pooled over the points) and other poolings, um."""
        _index(axis, AXES, "axis")
        return dict(self.result.pooled[axis])

    def per_point(self, stat: str = "U_p", axis: str = "x") -> np.ndarray:
        """Per point, shape (n,), um: ``stat`` one of systematic, std, low, high, U_p, U95."""
        a = _index(axis, AXES, "axis")
        r = self.result
        table = {"systematic": r.mean, "std": r.std, "low": r.low, "high": r.high,
                 "U_p": r.up, "U95": r.u95}  # fmt: skip
        if stat not in table:
            raise CfmInputError(f"stat {stat!r} unknown; expected one of {', '.join(table)}")
        return 1e3 * table[stat][:, a]

    def write(self, out_dir, provenance: dict | None = None) -> dict:
        """Write ``summary.json``, ``points.csv`` and ``points.vtu`` (as ``cfm-fem
        kinematics``); return their paths."""
        from ..io.kinematics_out import kinematics_summary, write_kinematics

        extra = {"provenance": provenance} if provenance else None
        summary = kinematics_summary(self.result, self.bench, extra=extra)
        return write_kinematics(out_dir, self.result, self.bench, summary)


@dataclass
class CoupledTable:
    """Field error of the coupled model at scan points (`cfm_fem.run_coupled`, Table V).

    Attributes
    ----------
    result : cfm_fem.workflows.coupled.CoupledResult
    bench : cfm_fem.models.bench.Bench
    """

    result: object
    bench: object

    def table_v(self) -> dict:
        """Pooled systematic, std and U_f per component and over the model's components
        ("all"), units, with their numerical uncertainty."""
        return self.result.pooled()

    def per_point(self, stat: str = "U95", component: str = "absB") -> np.ndarray:
        """Per scan point, shape (n,), units: ``stat`` one of systematic, std, low, high, U95."""
        c = _index(component, FIELD_COMPONENTS, "component")
        r = self.result
        table = {"systematic": r.mean, "std": r.std, "low": r.low, "high": r.high, "U95": r.u95}
        if stat not in table:
            raise CfmInputError(f"stat {stat!r} unknown; expected one of {', '.join(table)}")
        return table[stat][:, c]

    def write(self, out_dir, provenance: dict | None = None) -> list:
        """Write ``summary.json``, ``points.csv`` and ``report.html`` (as ``cfm-fem
        coupled``); return their paths."""
        from ..io.compare_out import coupled_points_csv, coupled_summary
        from ..io.run_files import write_run
        from ..report.runs import coupled_report

        extra = {"provenance": provenance} if provenance else None
        summary = coupled_summary(self.result, self.bench, extra=extra)
        rep = coupled_report(self.result, summary)
        files = {"summary.json": summary, "points.csv": coupled_points_csv(self.result)}
        return write_run(out_dir, {**files, **rep.images, "report.html": rep.render()})
