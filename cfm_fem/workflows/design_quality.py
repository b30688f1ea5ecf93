"""The design question for one field-quality figure: the largest U_p that keeps its U95 within a
limit (``cfm-fem design FIELD --quantity b3 --max 1 --r-ref MM``).

U95(U_p) of a quantity comes from the Monte Carlo of ``cfm-fem quality`` in mode gauss (scan
points moved by N(0, U_p^2) per axis and point, `cfm_fem.models.quality.run_quality_mc`) with
the same seed at every U_p: the trials then use the same standard normal numbers scaled by U_p,
so U95 is a smooth, increasing function of U_p (proportional to it while the field is linear
over the displacements) and the bisection converges on it. Steps:

1. U95 at ``start_um``; the proportional law gives a first guess U_p = start max / U95.
2. Bracket: widen by factors of `BRACKET` (1.05) from the guess until U95 <= max at the lower
   end and > max at the upper one.
3. Bisect until the bracket is within ``rel_tol`` of its upper end; the answer is the lower end
   (its U95 is within the limit).

Monte Carlo uncertainty: while U95 is proportional to U_p, a relative error r of U95 is the
relative error of the answer; r is the spread of U95 over the run's batches
(`McQuality.u95_spread`, twice the standard deviation of the batch values over
sqrt(batches)) over U95 at the answer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import CfmInputError
from ..models.probe import HallProbe
from ..models.quality import (
    LocalField,
    Sources,
    analyse,
    fit_planes,
    main_order_of,
    run_quality_mc,
)

__all__ = ["QUANTITIES", "QualityDesign", "quality_up_max"]

#: Quantities of the design: name -> (column of `VECTOR_NAMES`, factor from the vector's unit
#: to the quantity's unit, unit); the names of the tolerance table of ``cfm-fem quality``.
QUANTITIES = {
    **{f"{c}{n}": (f"{c}{n}", 1.0, "units") for c in "ba" for n in range(1, 16)},
    "centre_x_um": ("centre_x", 1e3, "um"),
    "centre_y_um": ("centre_y", 1e3, "um"),
    "roll_mrad": ("roll", 1.0, "mrad"),
    "magnetic_length_mm": ("length", 1.0, "mm"),
}
#: Bracket steps and bisections at most.
MAX_STEPS = 60
#: Factor between the ends of a bracket step.
BRACKET = 1.05


@dataclass
class QualityDesign:
    """Largest U_p with U95 of ``quantity`` <= ``max_value``.

    Attributes
    ----------
    quantity, unit : str
    max_value : float
        The limit, in ``unit``.
    up_max_um : float or None
        The answer, um (None: ``method`` says why).
    u_up_max_um : float or None
        Its Monte Carlo uncertainty (module docstring), um.
    u95_at_answer : float or None
        U95 of the quantity at the answer, in ``unit``.
    method : {"bisection", "unbounded", "undetermined"}
        "unbounded": U95 at the start value is 0 (below 1e-9 of the limit: the quantity does
        not depend on the scan points' places); "undetermined": the map's value of the
        quantity is undefined, or no bracket within `MAX_STEPS` steps of the guess.
    evaluations : list of (float, float)
        (U_p um, U95) of every Monte Carlo run, in order.
    trials, seed : int
    probe : str
    main_order : int
    r_ref_mm : float, mm
        Reference radius of the harmonics.
    """

    quantity: str
    unit: str
    max_value: float
    up_max_um: float | None
    u_up_max_um: float | None
    u95_at_answer: float | None
    method: str
    evaluations: list = field(default_factory=list)
    trials: int = 0
    seed: int = 0
    probe: str = "paper"
    main_order: int = 0
    r_ref_mm: float = 0.0

    def sentence(self) -> str:
        """``U_p <= 12.3 +- 0.4 um keeps U95(b3) <= 1 units``."""
        what = f"U95({self.quantity}) <= {self.max_value:g} {self.unit}"
        if self.method == "unbounded":
            return f"no largest U_p: {what} at every U_p (the quantity does not move with them)"
        if self.method == "undetermined":
            return f"no U_p determined for {what}: see the evaluations"
        return (
            f"U_p <= {self.up_max_um:.4g} +- {self.u_up_max_um:.2g} um keeps {what} (quality "
            f"Monte Carlo in mode gauss, {self.trials} trials per U_p, seed {self.seed}; +- is "
            "the Monte Carlo uncertainty at 95 %)"
        )

    def to_dict(self) -> dict:
        out = dict(self.__dict__)
        out["evaluations"] = [{"up_um": u, "U95": v} for u, v in self.evaluations]
        return out

    def summary(self, provenance: dict | None = None) -> dict:
        """The content of ``design.json``."""
        return {
            "answer": self.sentence(), **self.to_dict(),
            "definition": "largest U_p (um, N(0, U_p^2) per axis and scan point) whose U95 of "
            "the quantity, from the Monte Carlo of cfm-fem quality in mode gauss with the same "
            "seed at every U_p, is <= max (cfm_fem.workflows.design_quality); u_up_max_um: U_p "
            "times the relative spread of U95 over the run's batches",
            "provenance": provenance or {},
        }  # fmt: skip

    def write(self, out_dir, provenance: dict | None = None) -> list:
        """Write ``out_dir/design.json``; returns the paths written."""
        from ..io.run_files import write_run

        return write_run(out_dir, {"design.json": self.summary(provenance)})


def quality_up_max(fieldmap, r_ref_mm: float, quantity: str, max_value: float, *,
                   trials: int = 2000, seed: int = 0, probe: str = "paper",
                   start_um: float = 10.0, rel_tol: float = 0.01, main_order: int | None = None,
                   field_model: str = "harmonic", sampling: str = "auto",
                   radius_mm: float | None = None, dz_mm: float | None = None,
                   n_angles: int = 64, reader: dict | None = None,
                   progress=None) -> QualityDesign:  # fmt: skip
    """Largest U_p that keeps U95 of a field-quality figure within ``max_value``.

    Parameters
    ----------
    fieldmap : path-like or FieldMap
    r_ref_mm : float, mm
    quantity : str
        A key of `QUANTITIES`.
    max_value : float
        Limit of its U95, in the quantity's unit.
    trials : int
        Trials of each Monte Carlo run.
    seed : int
    probe : {"exact", "paper", "table1"}
    start_um : float, um
        First U_p.
    rel_tol : float
        Relative width of the final bracket.
    main_order, field_model, sampling, radius_mm, dz_mm, n_angles, reader
        As `cfm_fem.workflows.quality.run_quality`.
    progress : callable(int), optional
        Called with the trials finished.

    Returns
    -------
    QualityDesign
    """
    from ..io import read_field
    from .quality import PROBES, SAMPLINGS, _field_model, scan_plan

    if quantity not in QUANTITIES:
        raise CfmInputError(
            "--quantity must be one of b1..b15, a1..a15, centre_x_um, centre_y_um, roll_mrad, "
            f"magnetic_length_mm; got {quantity!r}"
        )
    if not (np.isfinite(max_value) and max_value > 0):
        raise CfmInputError(f"--max must be a positive number; got {max_value}")
    if not (np.isfinite(r_ref_mm) and r_ref_mm > 0):
        raise CfmInputError(f"--r-ref must be a positive radius in mm; got {r_ref_mm}")
    if probe not in PROBES or sampling not in SAMPLINGS:
        raise CfmInputError(f"probe must be one of {PROBES}, sampling one of {SAMPLINGS}")
    if not (start_um > 0 and 0 < rel_tol < 1):
        raise CfmInputError("start_um must be > 0 and rel_tol in (0, 1)")
    fm = fieldmap if hasattr(fieldmap, "points") else read_field(fieldmap, **(reader or {}))
    notes: list = []
    plan, b_nodes = scan_plan(fm, sampling, float(r_ref_mm), radius_mm, dz_mm, int(n_angles),
                              notes)  # fmt: skip
    model, _ = _field_model(fm, field_model)
    local = LocalField(model, plan.points, b_nodes)
    planes = fit_planes(plan, local.B_nominal)
    n_main = main_order_of(np.einsum("pn,p->n", planes, plan.weights_mm))
    n_main = n_main if main_order is None else int(main_order)
    z_len = 0.0 if plan.z[0] <= 0.0 <= plan.z[-1] else float(plan.z[np.argmax(
        np.abs(planes[:, n_main - 1]))])  # fmt: skip
    vec = analyse(plan, local.B_nominal, n_main, z_len).vector()
    from ..models.quality import VECTOR_NAMES

    col, factor, unit = QUANTITIES[quantity]
    j = VECTOR_NAMES.index(col)
    hp = HallProbe.exact() if probe == "exact" else HallProbe(model=probe)
    evaluations, cache = [], {}

    def u95(up_um):
        src = Sources("gauss", up_mm=up_um * 1e-3, probe=hp)
        mc = run_quality_mc(plan, local, src, vec, n_main, z_len, seed=seed, trials=trials,
                            progress=progress)  # fmt: skip
        value, spread = float(mc.u95[j] * factor), float(mc.u95_spread[j] * factor)
        evaluations.append((float(up_um), value))
        cache[float(up_um)] = (value, spread)
        return value

    base = dict(quantity=quantity, unit=unit, max_value=float(max_value), trials=int(trials),
                seed=int(seed), probe=probe, main_order=n_main,
                r_ref_mm=float(r_ref_mm))  # fmt: skip
    if not np.isfinite(vec[j]):
        return QualityDesign(up_max_um=None, u_up_max_um=None, u95_at_answer=None,
                             method="undetermined", evaluations=evaluations, **base)  # fmt: skip
    u0 = u95(start_um)
    if not u0 > 1e-9 * max_value:  # rounding only: the figure does not move with U_p
        return QualityDesign(up_max_um=None, u_up_max_um=None, u95_at_answer=None,
                             method="unbounded", evaluations=evaluations, **base)  # fmt: skip

    def below(up_um):
        return (cache[up_um][0] if up_um in cache else u95(up_um)) <= max_value

    undetermined = QualityDesign(up_max_um=None, u_up_max_um=None, u95_at_answer=None,
                                 method="undetermined", evaluations=evaluations,
                                 **base)  # fmt: skip
    lo = hi = start_um * max_value / u0  # the proportional law
    if below(lo):
        hi = lo * BRACKET
        for _ in range(MAX_STEPS):
            if not below(hi):
                break
            lo, hi = hi, hi * BRACKET
        else:
            return undetermined
    else:
        lo = hi / BRACKET
        for _ in range(MAX_STEPS):
            if below(lo):
                break
            lo, hi = lo / BRACKET, lo
        else:
            return undetermined
    for _ in range(MAX_STEPS):  # bisect
        if hi - lo <= rel_tol * hi:
            break
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if u95(mid) <= max_value else (lo, mid)
    value, spread = cache[lo]
    return QualityDesign(up_max_um=float(lo), u_up_max_um=float(lo * spread / value),
                         u95_at_answer=value, method="bisection", evaluations=evaluations,
                         **base)  # fmt: skip
