"""``step_event``: an abrupt shift from one moment on (a slip, a knock, a re-homing).

The residual of an axis (tracker) or of a field component (Hall map: a jump of the element's
offset, or a jump of the probe position seen through the gradient) changes by a constant from a
change point on. Change points are searched between repetitions in time order (or, with one
repetition, at quantiles of the acquisition time); for each axis or component the change point
that explains most of the calibrated baseline's residual is kept (the step is then linear in its
size), and the evidence is corrected for the number of change points searched (``multiplicity``).
Each axis or component is its own function of the effect (``families``).
"""

from __future__ import annotations

import numpy as np

from .calibrate import Columns, fit_map, stack
from .priors import bounds_for
from .problem import UM, model_sigma

__all__ = ["step_event", "change_points"]

#: Change points searched when there is one repetition: this many time quantiles.
_N_TIME_BREAKS = 40


def change_points(prob):
    """Candidate change points: (label, row mask of the rows after it, info dict) per point.

    Between repetitions in time order when there are three or more, else at quantiles of the
    acquisition time (``t_s``), else none.
    """
    out = []
    reps = np.unique(prob.rep)
    if reps.size >= 3:
        if prob.t_h is not None:
            t0 = np.array([prob.t_h[prob.rep == r].min() for r in reps])
            reps = reps[np.argsort(t0, kind="stable")]
        rank = np.empty(prob.n, dtype=np.int64)
        for k, r in enumerate(reps):
            rank[prob.rep == r] = k
        for k in range(1, reps.size):
            after = rank >= k
            info = {"from_repetition": int(reps[k])}
            if prob.t_h is not None:
                info["t_h"] = round(float(prob.t_h[after].min()), 4)
            out.append((f"from repetition {reps[k]}", after, info))
        return out
    if prob.t_h is not None and np.ptp(prob.t_h) > 0:
        tq = np.unique(np.quantile(prob.t_h, np.linspace(0, 1, _N_TIME_BREAKS + 2)[1:-1]))
        for t in tq:
            after = prob.t_h >= t
            if 0 < after.sum() < prob.n:
                out.append((f"from t = {t:.3f} h", after, {"t_h": round(float(t), 4)}))
    return out


def _kinds(prob):
    """(name, unit, column function(after mask) -> (n, 3)) of the steps the data can show."""
    kinds = []
    if prob.kind == "tracker":
        for a in range(3):

            def col(after, a=a):
                c = np.zeros((prob.n, 3))
                c[after, a] = UM
                return c

            kinds.append((f"step_{'xyz'[a]}", "um", col))
        return kinds
    G = prob.ctx.G
    for i in range(3):

        def off(after, i=i):
            c = np.zeros((prob.n, 3))
            c[after, i] = 1e-6
            return c

        kinds.append((f"offset_step_{'xyz'[i]}", "uT", off))
    for a in range(3):

        def pos(after, a=a):
            c = np.zeros((prob.n, 3))
            c[after] = -G[after, :, a] * UM  # the probe moved by +s: B(p + s), magnet frame
            return c

        if np.any(G[:, :, a]):
            kinds.append((f"step_{'xyz'[a]}", "um", pos))
    return kinds


def step_event(prob):
    """Block of ``step_event`` (module docstring), or why the recording cannot show one."""
    breaks = change_points(prob)
    if not breaks:
        return (
            "fewer than three repetitions and no acquisition time (t_s): a change point "
            "cannot be placed"
        )
    base = stack(prob.baseline)
    sigma = model_sigma(prob, base)
    fit = fit_map(prob.y, sigma, base)
    # whitened baseline design with its priors; steps are judged beyond it
    A = (base.J / sigma[..., None]).reshape(-1, base.p)
    has = np.isfinite(base.prior_std) & (base.prior_std > 0)
    q, _ = np.linalg.qr(np.vstack([A, np.diag(1.0 / np.where(has, base.prior_std, 1.0))[has]]))
    q = q[: A.shape[0]]
    r = (fit.resid / sigma).reshape(-1)
    cols, names, units, info = [], [], [], {}
    for name, unit, colfn in _kinds(prob):
        best = (-1.0, None, None)
        for _, after, inf in breaks:
            w = (colfn(after) / sigma).reshape(-1)
            w = w - q @ (q.T @ w)
            nw = float(w @ w)
            if nw <= 0:
                continue
            gain = float(w @ r) ** 2 / nw
            if gain > best[0]:
                best = (gain, after, inf)
        if best[1] is None:
            continue
        cols.append(colfn(best[1]))
        names.append(name)
        units.append(unit)
        info[name] = best[2]
    if not cols:
        return "no change point leaves a signature beyond the calibrated model"

    J = np.stack(cols, axis=-1)
    p = J.shape[-1]
    blk = Columns(
        J,
        names,
        units,
        np.zeros(p),
        np.full(p, 1e6),
        "step_event",
        bounds=bounds_for("step_event", names)[0],
    )
    blk.families = [(nm, [k]) for k, nm in enumerate(names)]
    blk.multiplicity = float(len(breaks))
    blk.info = info
    return blk
