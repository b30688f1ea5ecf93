"""ISO 230-2:2014 evaluation of the positioning of one linear axis from bidirectional runs.

Notation of the standard: targets P_i (i = 1..m), runs j = 1..n in each direction, deviations
x_ij = P_ij - P_i (actual minus target position), "up" (arrow up, positive approach) and "down"
(arrow down, negative approach). Lengths are in whatever unit the deviations are given in (mm in
cfm_fem) and come back in that unit.

Definitions (ISO 230-2:2014, clause 3). The 1997 edition numbers the same terms 2.10-2.24 in
clause 2; the 2014 numbers below are those plus one for the term "functional point" (3.3) that the
later edition inserts before "target position" (3.4). We had no copy of the 2014 text to check
every number against; the formulas themselves are the same in both editions.

* 3.11 mean unidirectional positioning deviation at a position
  x̄_i↑ = (1/n) sum_j x_ij↑,  x̄_i↓ likewise
* 3.12 mean bidirectional positioning deviation at a position   x̄_i = (x̄_i↑ + x̄_i↓) / 2
* 3.13 reversal value at a position                            B_i = x̄_i↑ - x̄_i↓
* 3.14 reversal value of an axis                               B = max_i |B_i|
* 3.15 mean reversal value of an axis                          B̄ = (1/m) sum_i B_i  (signed)
* 3.16 estimator for the unidirectional standard uncertainty of positioning at a position
  s_i↑ = sqrt( 1/(n-1) sum_j (x_ij↑ - x̄_i↑)^2 ),  s_i↓ likewise
* 3.17 unidirectional repeatability of positioning at a position   R_i↑ = 4 s_i↑,  R_i↓ = 4 s_i↓
* 3.18 bidirectional repeatability of positioning at a position
  R_i = max( 2 s_i↑ + 2 s_i↓ + |B_i| ; R_i↑ ; R_i↓ )
* 3.19 unidirectional repeatability of positioning of an axis   R↑ = max_i R_i↑,  R↓ = max_i R_i↓
* 3.20 bidirectional repeatability of positioning of an axis    R = max_i R_i
* 3.21 unidirectional systematic positioning error of an axis
  E↑ = max_i x̄_i↑ - min_i x̄_i↑,  E↓ likewise
* 3.22 bidirectional systematic positioning error of an axis
  E = max(x̄_i↑ ; x̄_i↓) - min(x̄_i↑ ; x̄_i↓)
* 3.23 mean bidirectional positioning error of an axis         M = max_i x̄_i - min_i x̄_i
* 3.24 unidirectional accuracy of positioning of an axis
  A↑ = max_i (x̄_i↑ + 2 s_i↑) - min_i (x̄_i↑ - 2 s_i↑),  A↓ likewise
* 3.25 bidirectional accuracy of positioning of an axis
  A = max(x̄_i↑ + 2 s_i↑ ; x̄_i↓ + 2 s_i↓) - min(x̄_i↑ - 2 s_i↑ ; x̄_i↓ - 2 s_i↓)

The standard test cycle uses n = 5 runs per direction and at least 5 targets per metre; these
functions accept any n >= 2 (s needs two runs) and any m >= 1, and a run missing at a target
(NaN) is left out of that target's statistics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..errors import CfmInputError

__all__ = ["Iso230Result", "evaluate_bidirectional", "evaluate_records"]

_UP_WORDS = {"up", "+", "+1", "1", "pos", "positive"}
_DOWN_WORDS = {"down", "-", "-1", "neg", "negative"}


@dataclass(frozen=True, eq=False)
class Iso230Result:
    """Per-target and axis values of an ISO 230-2 bidirectional test (see the module docstring).

    Per target, ndarray shape (m,), in the unit of the deviations unless stated:
    ``targets`` (P_i), ``n_up``, ``n_down`` (runs used, int), ``mean_up`` (x̄_i↑), ``mean_down``
    (x̄_i↓), ``mean_bidirectional`` (x̄_i), ``s_up``, ``s_down`` (s_i↑, s_i↓), ``reversal`` (B_i),
    ``repeatability_up``, ``repeatability_down`` (R_i↑, R_i↓), ``repeatability`` (R_i).

    Axis values, float: ``A``, ``A_up``, ``A_down`` (accuracy), ``E``, ``E_up``, ``E_down``
    (systematic positioning error), ``M`` (mean bidirectional positioning error), ``R``,
    ``R_up``, ``R_down`` (repeatability), ``B`` (reversal value, max |B_i|), ``B_mean``
    (mean reversal value B̄, signed).
    """

    targets: np.ndarray
    n_up: np.ndarray
    n_down: np.ndarray
    mean_up: np.ndarray
    mean_down: np.ndarray
    mean_bidirectional: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    reversal: np.ndarray
    repeatability_up: np.ndarray
    repeatability_down: np.ndarray
    repeatability: np.ndarray
    A: float
    A_up: float
    A_down: float
    E: float
    E_up: float
    E_down: float
    M: float
    R: float
    R_up: float
    R_down: float
    B: float
    B_mean: float

    def axis_values(self) -> dict[str, float]:
        """The axis values only: {"A": .., "A_up": .., ..., "B_mean": ..}."""
        names = ("A", "A_up", "A_down", "E", "E_up", "E_down", "M", "R", "R_up", "R_down")
        return {k: float(getattr(self, k)) for k in names + ("B", "B_mean")}

    def as_dict(self) -> dict:
        """Everything as plain lists and floats (JSON-ready)."""
        return {
            k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()
        }


def _runs(name: str, values, m: int) -> np.ndarray:
    x = np.asarray(values, dtype=np.float64)
    if x.ndim == 1 and m == 1:
        x = x[None, :]
    if x.ndim != 2 or x.shape[0] != m:
        raise CfmInputError(
            f"{name} deviations must have shape (m, n) = ({m}, runs), one row per target; "
            f"instead received {x.shape}"
        )
    if np.isinf(x).any():
        raise CfmInputError(f"{name} deviations must be finite numbers (NaN marks a missing run)")
    return x


def _mean_and_std(x: np.ndarray, name: str, targets: np.ndarray):
    """Mean and sample standard deviation (ddof = 1) per row, NaN = missing run."""
    n = np.sum(~np.isnan(x), axis=1)
    short = np.flatnonzero(n < 2)
    if short.size:
        i = int(short[0])
        raise CfmInputError(
            f"target {i + 1} (P = {targets[i]:g}) has {int(n[i])} {name} run(s); expected at least "
            "2 to estimate the repeatability"
        )
    mean = np.nanmean(x, axis=1)
    std = np.sqrt(np.nansum((x - mean[:, None]) ** 2, axis=1) / (n - 1))
    return n, mean, std


def evaluate_bidirectional(targets, up, down) -> Iso230Result:
    """Evaluate a bidirectional positioning test of one axis (ISO 230-2:2014).

    Parameters
    ----------
    targets : array_like, shape (m,)
        Target positions P_i.
    up, down : array_like, shape (m, n_up) and (m, n_down)
        Deviations x_ij = P_ij - P_i of the runs approaching each target in the positive (up) and
        negative (down) direction; row i belongs to ``targets[i]``, NaN marks a missing run.

    Returns
    -------
    Iso230Result
    """
    p = np.atleast_1d(np.asarray(targets, dtype=np.float64))
    if p.ndim != 1 or p.size == 0 or not np.isfinite(p).all():
        raise CfmInputError(f"targets must be a non-empty 1-D array of finite positions; got {p!r}")
    m = p.size
    x_up = _runs("up", up, m)
    x_down = _runs("down", down, m)
    n_up, mean_up, s_up = _mean_and_std(x_up, "up", p)
    n_down, mean_down, s_down = _mean_and_std(x_down, "down", p)

    mean_bi = 0.5 * (mean_up + mean_down)  # 3.12
    reversal = mean_up - mean_down  # 3.13
    r_up, r_down = 4.0 * s_up, 4.0 * s_down  # 3.17
    r_bi = np.maximum.reduce([2.0 * s_up + 2.0 * s_down + np.abs(reversal), r_up, r_down])  # 3.18

    hi_up, lo_up = mean_up + 2.0 * s_up, mean_up - 2.0 * s_up
    hi_down, lo_down = mean_down + 2.0 * s_down, mean_down - 2.0 * s_down
    both = np.concatenate([mean_up, mean_down])
    return Iso230Result(
        targets=p,
        n_up=n_up,
        n_down=n_down,
        mean_up=mean_up,
        mean_down=mean_down,
        mean_bidirectional=mean_bi,
        s_up=s_up,
        s_down=s_down,
        reversal=reversal,
        repeatability_up=r_up,
        repeatability_down=r_down,
        repeatability=r_bi,
        A=float(max(hi_up.max(), hi_down.max()) - min(lo_up.min(), lo_down.min())),  # 3.25
        A_up=float(hi_up.max() - lo_up.min()),  # 3.24
        A_down=float(hi_down.max() - lo_down.min()),
        E=float(both.max() - both.min()),  # 3.22
        E_up=float(mean_up.max() - mean_up.min()),  # 3.21
        E_down=float(mean_down.max() - mean_down.min()),
        M=float(mean_bi.max() - mean_bi.min()),  # 3.23
        R=float(r_bi.max()),  # 3.20
        R_up=float(r_up.max()),  # 3.19
        R_down=float(r_down.max()),
        B=float(np.abs(reversal).max()),  # 3.14
        B_mean=float(reversal.mean()),  # 3.15
    )


def _direction_signs(directions) -> np.ndarray:
    d = np.asarray(directions)
    if d.dtype.kind in "US":
        words = np.char.lower(np.char.strip(d.astype(str)))
        sign = np.where(
            np.isin(words, list(_UP_WORDS)), 1, np.where(np.isin(words, list(_DOWN_WORDS)), -1, 0)
        )
    else:
        sign = np.where(d > 0, 1, np.where(d < 0, -1, 0)).astype(int)
    return sign


def evaluate_records(positions, deviations, directions, *, tol: float = 1e-9) -> Iso230Result:
    """Evaluate a bidirectional test given as one record per approach.

    Parameters
    ----------
    positions : array_like, shape (k,)
        Target position P_i of each record; records whose targets differ by at most ``tol`` belong
        to the same target.
    deviations : array_like, shape (k,)
        x_ij = P_ij - P_i of each record.
    directions : array_like, shape (k,)
        Approach direction: +1 / "up" (positive) or -1 / "down" (negative). 0 (no move) is an
        error: such a record has no approach direction.
    tol : float
        Largest difference between target values that are the same target (unit of positions).

    Returns
    -------
    Iso230Result
        Targets in increasing order; each holds as many runs as it has records per direction.
    """
    p = np.asarray(positions, dtype=np.float64).ravel()
    x = np.asarray(deviations, dtype=np.float64).ravel()
    sign = _direction_signs(directions).ravel()
    if not p.size == x.size == sign.size:
        raise CfmInputError(
            f"positions, deviations and directions must have the same length; instead received "
            f"{p.size}, {x.size} and {sign.size}"
        )
    for name, arr in (("position", p), ("deviation", x)):
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise CfmInputError(
                f"record {int(bad[0]) + 1}: {name} must be a finite number; found {arr[bad[0]]}"
            )
    bad = np.flatnonzero(sign == 0)
    if bad.size:
        k = int(bad[0])
        raise CfmInputError(
            f"record {k + 1}: direction must be +1/'up' or -1/'down'; "
            f"found {np.asarray(directions).ravel()[k]!r}"
        )
    order = np.argsort(p, kind="stable")
    new_target = np.concatenate([[True], np.diff(p[order]) > tol])
    group_sorted = np.cumsum(new_target) - 1
    group = np.empty_like(group_sorted)
    group[order] = group_sorted
    targets = p[order][new_target]
    m = targets.size

    def table(s: int) -> np.ndarray:
        sel = sign == s
        counts = np.bincount(group[sel], minlength=m)
        out = np.full((m, max(int(counts.max(initial=0)), 1)), np.nan)
        g = group[sel]
        # column of each record = how many earlier records of the same target and direction
        col = np.zeros(g.size, dtype=np.int64)
        seen = np.zeros(m, dtype=np.int64)
        for r, gi in enumerate(g):
            col[r] = seen[gi]
            seen[gi] += 1
        out[g, col] = x[sel]
        return out

    return evaluate_bidirectional(targets, table(1), table(-1))
