"""The paper's design question: which U_p keeps U_f at or below a target over a share of the
nodes (or of a region)?

Given U_f per node for a sweep of U_p values (Gaussian perturbation, paper eq. 16), the
coverage percentile P(U_p) of U_f over the nodes with a U_f figure grows ~linearly with U_p
(exactly while every trial stays in the cells around its node). The largest admissible U_p is
where P crosses the target, found by linear interpolation between the two bracketing sweep
values (or, beyond the largest, by the proportional law P ~ U_p through the largest one, and
said so).

Monte Carlo uncertainty: U_f of a node is max(|low|, |high|) of the estimated 2.5 % and 97.5 %
quantiles of its error, each with relative standard error r = 1.363 / sqrt(N) (normal theory,
`cfm_fem.models.sweep.summarize`'s ``uf_relative_mc_std``). A parametric bootstrap redraws
both ends of every node as end (1 + r z), z ~ N(0, 1) per node and end, the same z for every
U_p (the sweep uses common random numbers, so a node's errors at different U_p move together),
and repeats the percentile and the interpolation; the standard deviation of the replicates is
the answer's standard uncertainty. The larger of two noisy ends is biased upward (by ~0.56 r U_f
where the ends are equal), so at finite N the U_f figures are slightly high and the answer
slightly low: on the safe side, by a fraction that shrinks as 1 / sqrt(N).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError
from ..models.region import parse_region, region_mask  # the region syntax of every command

__all__ = ["DesignAnswer", "admissible_up", "region_mask", "parse_region"]

#: Bootstrap replicates of the uncertainty.
N_BOOT = 400


@dataclass
class DesignAnswer:
    """Largest U_p that keeps U_f <= ``uf_max`` over ``coverage`` of the nodes.

    Attributes
    ----------
    up_max_um : float or None
        The answer, um; None when the sweep bounds no U_p: method "unbounded" (U_f is 0 at
        every U_p of the sweep: the field does not vary over the perturbation, so no U_p
        exceeds the target) or "undetermined" (no node has a U_f figure).
    u_up_max_um : float or None
        Its Monte Carlo standard uncertainty, um.
    low_bias_bound_um : float or None
        The finite trial count biases the answer low (the safe side) by up to this, um:
        r ``up_max_um``, r the relative standard error of one interval end.
    uf_max_units, coverage : float
        The question.
    method : str
        "interpolated" between two sweep values, or "extrapolated" by the proportional law.
    up_um : list of float
        The sweep's U_p values, um.
    percentile_units : list of float or None
        P(U_p): the ``coverage`` quantile of U_f over the nodes with a U_f figure, units.
    u_percentile_units : list of float or None
        Bootstrap standard uncertainty of each P, units.
    nodes : list of int
        Nodes with a U_f figure in the region, per U_p.
    """

    up_max_um: float | None
    u_up_max_um: float | None
    low_bias_bound_um: float | None
    uf_max_units: float
    coverage: float
    method: str
    up_um: list
    percentile_units: list
    u_percentile_units: list
    nodes: list

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def sentence(self) -> str:
        """``U_p <= 23.4 +- 0.3 um keeps U_f <= 10 units over 95 % of the nodes``."""
        share = f"over {100 * self.coverage:g} % of the nodes"
        if self.method == "unbounded":
            return (
                f"no largest U_p: U_f stays 0 units {share} at every U_p of the sweep (up to "
                f"{max(self.up_um):g} um), below the target {self.uf_max_units:g} units: the "
                "field does not vary over the perturbed positions (uniform field?)"
            )
        if self.method == "undetermined":
            return (
                f"no U_p determined for U_f <= {self.uf_max_units:g} units {share}: no node of "
                "the region has a U_f figure at a U_p > 0 of the sweep"
            )
        return (
            f"U_p <= {self.up_max_um:.4g} +- {self.u_up_max_um:.2g} um keeps U_f <= "
            f"{self.uf_max_units:g} units over {100 * self.coverage:g} % of the nodes "
            f"({self.method}; +- is the Monte Carlo standard uncertainty; the finite trial count "
            f"biases the answer low by up to {self.low_bias_bound_um:.2g} um)"
        )


def _percentiles(uf, complete, coverage):
    """(n_up,) coverage quantile of U_f over each column's complete nodes (NaN if none)."""
    out = np.full(uf.shape[1], np.nan)
    for k in range(uf.shape[1]):
        v = uf[complete[:, k], k]
        if v.size:
            out[k] = np.quantile(v, coverage)
    return out


def _crossing(up, p, target):
    """(U_p where the piecewise-linear P(U_p) first reaches ``target``, method); P(0) = 0."""
    if up[0] > 0:  # no error without a perturbation: the curve starts at the origin
        up, p = np.r_[0.0, up], np.r_[0.0, p]
    for k in range(1, len(up)):
        if p[k] >= target and np.isfinite(p[k - 1]):
            lo, hi = p[k - 1], p[k]
            t = (target - lo) / (hi - lo) if hi > lo else 1.0
            return up[k - 1] + t * (up[k] - up[k - 1]), "interpolated"
    k = int(np.nanargmax(np.where(up > 0, up, np.nan))) if (up > 0).any() else -1
    if k < 0 or not np.isfinite(p[k]):
        return float("nan"), "undetermined"
    if not p[k] > 0:  # U_f is 0 at the largest U_p: the field does not vary there
        return float("nan"), "unbounded"
    return up[k] * target / p[k], "extrapolated"


def admissible_up(
    up_um, low, high, complete, uf_max: float, *, coverage: float = 0.95, rel_mc_std: float,
    seed: int = 0, n_boot: int = N_BOOT,
) -> DesignAnswer:  # fmt: skip
    """The largest U_p with the ``coverage`` quantile of U_f at or below ``uf_max``.

    Parameters
    ----------
    up_um : sequence of float, shape (n_up,)
        U_p of the sweep, increasing, um.
    low, high : ndarray, shape (n, n_up), units
        Ends of the probabilistically symmetric 95 % interval of the |B| error per node (the
        nodes of the region); U_f = max(|low|, |high|).
    complete : ndarray, shape (n, n_up), bool
        Nodes with a U_f figure.
    uf_max : float
        Target, units.
    coverage : float
        Share of the nodes, in (0, 1].
    rel_mc_std : float
        Relative Monte Carlo standard error of one node's U_f.
    seed : int
        Seed of the bootstrap.
    n_boot : int

    Returns
    -------
    DesignAnswer
    """
    up = np.asarray(up_um, dtype=np.float64)
    if len(up) < 1 or np.any(np.diff(up) <= 0):
        raise CfmInputError("the U_p values of a design sweep must be increasing")
    if not uf_max > 0:
        raise CfmInputError(f"--uf-max must be > 0 units; got {uf_max}")
    if not 0 < coverage <= 1:
        raise CfmInputError(f"--coverage must be in (0, 1]; got {coverage}")
    low = np.abs(np.asarray(low, dtype=np.float64))
    high = np.abs(np.asarray(high, dtype=np.float64))
    uf = np.maximum(low, high)
    complete = np.asarray(complete, dtype=bool) & np.isfinite(uf)
    p = _percentiles(uf, complete, coverage)
    answer, method = _crossing(up, p, uf_max)
    if n_boot < 2:
        raise CfmInputError(f"n_boot must be >= 2; got {n_boot}")
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0x44455347,)))
    boot_p = np.empty((n_boot, len(up)))
    boot_a = np.empty(n_boot)
    for b in range(n_boot):
        z = rng.standard_normal((2, uf.shape[0], 1))
        ufb = np.maximum(low * (1.0 + rel_mc_std * z[0]), high * (1.0 + rel_mc_std * z[1]))
        boot_p[b] = _percentiles(ufb, complete, coverage)
        boot_a[b] = _crossing(up, boot_p[b], uf_max)[0]
    u_p = _std(boot_p)
    found = bool(np.isfinite(answer))
    return DesignAnswer(
        up_max_um=float(answer) if found else None,
        u_up_max_um=float(_std(boot_a[:, None])[0]) if found else None,
        low_bias_bound_um=float(rel_mc_std * answer) if found else None,
        uf_max_units=float(uf_max),
        coverage=float(coverage),
        method=method,
        up_um=up.tolist(),
        percentile_units=[None if not np.isfinite(v) else float(v) for v in p],
        u_percentile_units=[None if not np.isfinite(v) else float(v) for v in u_p],
        nodes=[int(complete[:, k].sum()) for k in range(len(up))],
    )


def _std(replicates) -> np.ndarray:
    """Standard deviation over the bootstrap replicates (axis 0) of each column, NaN where
    fewer than two are finite (no warning)."""
    ok = np.isfinite(replicates)
    out = np.full(replicates.shape[1], np.nan)
    enough = ok.sum(axis=0) >= 2
    if enough.any():
        out[enough] = np.nanstd(replicates[:, enough], axis=0, ddof=1)
    return out
