"""Locate the mismatch: standardised residuals and where they are significant.

Per point and component, the mean residual over the repetitions is standardised by its predicted
standard deviation (sigma / sqrt(R)) and tested two-sided; per-group means (repetition, time block,
approach direction, speed, region of the volume) likewise. All p-values of one analysis form one
family. Whether the recording departs from the model anywhere is decided family-wise: the
smallest p-value against ``alpha / m`` (Bonferroni over the m tests, a max-statistic test whose
false-alarm rate on a clean recording is at most ``alpha`` whatever the number of readings).
Only then are the locations named, by Benjamini-Hochberg at level ``q`` over the same family. A
global lack-of-fit F test compares the scatter of the point means with the pure error of the
repetitions.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .problem import Problem

__all__ = [
    "standardised",
    "locate",
    "benjamini_hochberg",
    "gated_discoveries",
    "planes",
    "isolated_planes",
]

COMP = "xyz"


def benjamini_hochberg(p, q: float) -> np.ndarray:
    """Boolean mask of the discoveries of the BH step-up procedure at FDR ``q``."""
    p = np.asarray(p, dtype=np.float64)
    m = p.size
    if m == 0:
        return np.zeros(0, dtype=bool)
    order = np.argsort(p)
    thresh = q * np.arange(1, m + 1) / m
    below = p[order] <= thresh
    out = np.zeros(m, dtype=bool)
    if below.any():
        kmax = np.flatnonzero(below).max()
        out[order[: kmax + 1]] = True
    return out


def gated_discoveries(p, q: float, alpha: float | None) -> np.ndarray:
    """Discoveries of Benjamini-Hochberg at ``q``, kept only when the family as a whole is
    significant at the family-wise level ``alpha``: min p <= alpha / m (Bonferroni on the
    smallest p-value). ``alpha`` None: BH alone (its family-wise rate on a clean family is q)."""
    p = np.asarray(p, dtype=np.float64)
    if p.size == 0 or (alpha is not None and not p.min() * p.size <= alpha):
        return np.zeros(p.size, dtype=bool)
    return benjamini_hochberg(p, q)


def standardised(prob: Problem, resid, sigma):
    """Per-row z (n, 3) and per-point z of the mean over repetitions (m, 3)."""
    z_row = resid / sigma
    cnt = np.bincount(prob.point, minlength=prob.n_points).astype(float)
    zp = np.zeros((prob.n_points, 3))
    for c in range(3):
        s = np.bincount(prob.point, z_row[:, c], prob.n_points)
        zp[:, c] = s / np.sqrt(np.maximum(cnt, 1))
    return z_row, zp


def _region_words(pos, sel, frame):
    lo, hi = pos[sel].min(0), pos[sel].max(0)
    span = pos.max(0) - pos.min(0)
    parts = []
    for a in range(3):
        if span[a] > 0 and (hi[a] - lo[a]) < 0.6 * span[a]:
            parts.append(f"{COMP[a]} in [{lo[a]:.0f}, {hi[a]:.0f}] mm")
    return (", ".join(parts) or "spread over the whole volume") + f" ({frame})"


def _groups(prob: Problem):
    """(label, row mask) groupings whose means may deviate: reps, time, direction, speed, region."""
    out = []
    reps = np.unique(prob.rep)
    if reps.size > 1:
        for r in reps:
            out.append((f"repetition {r}", prob.rep == r))
    if prob.t_h is not None and np.ptp(prob.t_h) > 0:
        edges = np.quantile(prob.t_h, np.linspace(0, 1, 6))
        b = np.clip(np.searchsorted(edges, prob.t_h, side="right") - 1, 0, 4)
        for k in range(5):
            if np.any(b == k):  # tied times leave a block empty (0/0 in its mean)
                out.append(
                    (f"time block {k + 1}/5 (t {edges[k]:.2f}-{edges[k + 1]:.2f} h)", b == k)
                )
    if prob.dir is not None:
        for a in range(3):
            for s in (-1, 1):
                m = prob.dir[:, a] == s
                if 0 < m.sum() < prob.n:
                    out.append((f"approach {'+' if s > 0 else '-'}{COMP[a]}", m))
    if prob.speed is not None:
        sp = np.unique(prob.speed)
        if sp.size > 1:
            for s in sp:
                out.append((f"speed {s:g} mm/s", prob.speed == s))
    for a, _, vals, inv in planes(prob.pos):
        for k, v in enumerate(vals):
            out.append((f"plane {COMP[a]} = {v:.6g} mm", inv == k))
    return out


#: Planes are tested as groups along an axis with this many distinct positions at most.
MAX_PLANES = 400


def planes(pos):
    """Planes of the scan: (axis, label, distinct positions (k,), row -> plane index (n,)).

    Only axes with 3 to :data:`MAX_PLANES` distinct positions, each plane holding at least two
    rows (a grid, not a scatter)."""
    out = []
    for a in range(3):
        vals, inv = np.unique(np.round(pos[:, a], 6), return_inverse=True)
        inv = inv.reshape(-1)
        if 3 <= vals.size <= MAX_PLANES and np.bincount(inv).min() >= 2:
            out.append((a, COMP[a], vals, inv))
    return out


def isolated_planes(prob, z_row, q: float = 0.01, alpha: float | None = None) -> list:
    """Planes whose mean residual departs from what their neighbours predict: a bad plane
    (a settling artefact at the start of every line, a glitch), not a smooth effect.

    Per axis and component, the standardised plane means m_k are compared with the line
    through their neighbours (interior planes: (m_{k-1} + m_{k+1}) / 2, variance 3/2; end
    planes: 2 m_1 - m_2 extrapolated, variance 6); the p-values of all planes form one family
    (Benjamini-Hochberg at ``q``) and a plane must also be significant on its own mean. With
    ``alpha``, a plane is called bad only when both its departure from its neighbours and its
    own mean also pass Bonferroni over the planes tested (family-wise rate <= ``alpha`` on a
    clean recording, :func:`gated_discoveries`).

    Returns
    -------
    list of dict
        ``axis``, ``position_mm``, ``component``, ``z_isolated``, ``z_mean``, ``rows`` (bool
        (n,)), strongest first.
    """
    cand = []
    for a, _, vals, inv in planes(prob.pos):
        cnt = np.bincount(inv).astype(float)
        for c in range(3):
            m = np.bincount(inv, z_row[:, c]) / np.sqrt(cnt)
            k = vals.size
            d = np.empty(k)
            d[1:-1] = (m[1:-1] - 0.5 * (m[:-2] + m[2:])) / np.sqrt(1.5)
            d[0] = (m[0] - 2 * m[1] + m[2]) / np.sqrt(6.0)
            d[-1] = (m[-1] - 2 * m[-2] + m[-3]) / np.sqrt(6.0)
            for j in range(k):
                cand.append((a, float(vals[j]), c, float(d[j]), float(m[j]), inv == j))
    if not cand:
        return []
    p_iso = np.array([2 * stats.norm.sf(abs(t[3])) for t in cand])
    p_mean = np.array([2 * stats.norm.sf(abs(t[4])) for t in cand])
    hit = benjamini_hochberg(p_iso, q) & benjamini_hochberg(p_mean, q)
    if alpha is not None:
        hit &= (p_iso * p_iso.size <= alpha) & (p_mean * p_mean.size <= alpha)
    out = [
        {
            "axis": COMP[t[0]],
            "position_mm": t[1],
            "component": COMP[t[2]],
            "z_isolated": round(t[3], 2),
            "z_mean": round(t[4], 2),
            "rows": t[5],
        }
        for t, h in zip(cand, hit, strict=True)
        if h
    ]
    return sorted(out, key=lambda d: -abs(d["z_isolated"]))


def locate(
    prob: Problem,
    resid,
    sigma,
    q: float = 0.01,
    frame: str = "",
    edf: float = 0.0,
    alpha: float | None = None,
) -> dict:
    """Where the residuals are significant.

    ``q``: the Benjamini-Hochberg level naming the locations; ``alpha``: the family-wise level
    of the decision that anything is located (module docstring), None: BH alone.

    Returns
    -------
    dict
        ``located``: list of 4.3 entries (component, where, n_points, max_abs_z), strongest first;
        ``z_point`` (m, 3), ``z_row`` (n, 3), ``significant_point`` (m, 3) bool, ``lack_of_fit``
        (F, p per component), ``groups`` (label, component, z, significant).
    """
    z_row, zp = standardised(prob, resid, sigma)
    p_pt = 2 * stats.norm.sf(np.abs(zp))
    group_list = _groups(prob)
    gz = []
    for label, m in group_list:
        for c in range(3):
            # group mean of within-point deviations: removes the point means, keeps rep structure
            gz.append((label, c, float(z_row[m, c].sum() / np.sqrt(m.sum()))))
    # within-point centred z for group tests (point means are tested separately)
    cnt = np.bincount(prob.point, minlength=prob.n_points).astype(float)
    if prob.n_reps >= 2 and group_list:
        gz = []
        zc = np.empty_like(z_row)
        for c in range(3):
            mean = np.bincount(prob.point, z_row[:, c], prob.n_points) / np.maximum(cnt, 1)
            zc[:, c] = z_row[:, c] - mean[prob.point]
        for label, m in group_list:
            for c in range(3):
                # variance of a sum of centred z over the rows: sum (1 - 1/R_i) for disjoint reps
                v = np.sum(1 - 1 / cnt[prob.point[m]])
                gz.append((label, c, float(zc[m, c].sum() / np.sqrt(max(v, 1e-12)))))
    p_g = np.array([2 * stats.norm.sf(abs(z)) for _, _, z in gz])
    allp = np.concatenate([p_pt.reshape(-1), p_g])
    disc = gated_discoveries(allp, q, alpha)
    sig_pt = disc[: p_pt.size].reshape(p_pt.shape)
    sig_g = disc[p_pt.size :]
    located = []
    upos = np.zeros((prob.n_points, 3))
    np.add.at(upos, prob.point, prob.pos)
    upos /= np.maximum(cnt, 1)[:, None]
    for c in range(3):
        sel = sig_pt[:, c]
        if sel.any():
            located.append(
                {
                    "component": COMP[c],
                    "where": _region_words(upos, sel, frame),
                    "n_points": int(sel.sum()),
                    "max_abs_z": round(float(np.abs(zp[sel, c]).max()), 2),
                    "mean_z": round(float(zp[sel, c].mean()), 2),
                }
            )
    for (label, c, z), s in zip(gz, sig_g, strict=True):
        if s:
            located.append(
                {
                    "component": COMP[c],
                    "where": label,
                    "n_points": int(len(np.unique(prob.point[dict(group_list)[label]]))),
                    "max_abs_z": round(abs(z), 2),
                    "mean_z": round(z, 2),
                }
            )
    located.sort(key=lambda d: -d["max_abs_z"])
    lof = []
    if prob.n_reps >= 2:
        for c in range(3):
            ss_lof = float((zp[:, c] ** 2).sum())
            dof1 = max(prob.n_points - edf / 3.0, 1.0)
            F = ss_lof / dof1
            # pure-error z are unit variance by construction of sigma; F ~ chi2(m)/m
            p = float(stats.chi2.sf(ss_lof, dof1))
            lof.append({"component": COMP[c], "F": round(F, 4), "p": p})
    return {
        "located": located,
        "z_point": zp,
        "z_row": z_row,
        "significant_point": sig_pt,
        "lack_of_fit": lof,
        "groups": [(lb, COMP[c], z, bool(s)) for (lb, c, z), s in zip(gz, sig_g, strict=True)],
        "point_pos": upos,
    }
