"""Effects made of several error functions (:attr:`Columns.families`): the ways such an
effect can be present (each function alone, pairs of them), their screening from the current
fit, their posterior weights, and the effect's parameters averaged over the functions the
data cannot tell apart. :mod:`~cfm_fem.workflows.diagnose.select` tests them.
"""

from __future__ import annotations

import itertools

import numpy as np

from .calibrate import Columns, fit_map, stack

__all__ = [
    "PAIR_MAX_FUNCTIONS",
    "ALT_MIN_WEIGHT",
    "screen_gram",
    "screened_drop",
    "model_basis",
    "function_options",
    "pair_members",
    "family_weights",
    "model_average",
    "other_functions",
    "unspanned",
]


def screen_gram(sigma, model, current, J):
    """Screening of columns ``J`` (n, 3, k) joining ``model`` (vague priors on them), from the
    current fit alone: the drop of the MAP objective when a subset S of them joins is
    g_S' M_SS^-1 g_S, with W the whitened columns, Q an orthonormal basis of the whitened,
    prior-augmented model, M = W'W - W'QQ'W and g = W' r (the current whitened residual r is
    orthogonal to Q). Returns ``(M, g)``, shapes (k, k) and (k,)."""
    W = (J / sigma[..., None]).reshape(-1, J.shape[-1])
    r = (current.resid / sigma).reshape(-1)
    ok = np.isfinite(r)
    W, r = W[ok], r[ok]
    QW = current.q_data[ok].T @ W if current.q_data is not None else np.zeros((0, W.shape[1]))
    return W.T @ W - QW.T @ QW, W.T @ r


def screened_drop(M, g, idx) -> float:
    """Drop of the objective when the columns ``idx`` join (:func:`screen_gram`)."""
    Ms, gs = M[np.ix_(idx, idx)], g[idx]
    try:
        return float(gs @ np.linalg.lstsq(Ms, gs, rcond=1e-10)[0])
    except np.linalg.LinAlgError:
        return 0.0


#: Most functions an effect may have for its functions to be tested in pairs as well
#: (:func:`function_options`).
PAIR_MAX_FUNCTIONS = 8


def function_options(families, pairs=None) -> list:
    """The ways an effect made of several error functions can be present: each function alone,
    then each pair of functions (an effect spread over two of them: a tilt about two axes, an
    offset along two), without a pair that one function already is (a quadratic profile with
    its own linear term). An effect of more than :data:`PAIR_MAX_FUNCTIONS` functions (the 18
    position-dependent errors at two orders, the drifts of each axis) is tested function by
    function: its pairs would outnumber its functions many times over, and a pair of two
    such functions can take the place of another effect (a bench's straightness and pitch
    along one stroke against a reversal's backlash). An effect that lists its pairs
    (:attr:`~cfm_fem.workflows.diagnose.calibrate.Columns.pairs`) is tested with those.

    Parameters
    ----------
    families : list of (str, list of int)
    pairs : list of (str, str, str), optional
        Group and labels of the pairs to test; of one group the first whose two functions are
        both in ``families``.

    Returns
    -------
    list of (labels, idx, stage)
        ``labels`` the functions' labels (one or two), ``idx`` their columns, ``stage`` 1 for
        single functions and 2 for pairs.
    """
    out = [([label], list(idx), 1) for label, idx in families]
    if pairs is not None:
        cols = dict(families)
        groups = set()
        for group, la, lb in pairs:
            if group in groups or la not in cols or lb not in cols:
                continue
            groups.add(group)
            out.append(([la, lb], sorted(set(cols[la]) | set(cols[lb])), 2))
        return out
    if len(families) > PAIR_MAX_FUNCTIONS:
        return out
    seen = {frozenset(idx) for _, idx in families}
    for (la, ia), (lb, ib) in itertools.combinations(families, 2):
        idx = sorted(set(ia) | set(ib))
        key = frozenset(idx)
        if key in seen:
            continue
        seen.add(key)
        out.append(([la, lb], idx, 2))
    return out


def pair_members(options, pair) -> list:
    """Indices of the single functions of a pair among ``options`` (:func:`function_options`)."""
    return [i for i, o in enumerate(options) if o[2] == 1 and set(o[1]) <= set(options[pair][1])]


#: Functions of an effect whose posterior weight (:func:`family_weights`) is at least this are
#: averaged into the reported parameters (:func:`model_average`); the others are negligible.
ALT_MIN_WEIGHT = 0.01


def family_weights(score) -> np.ndarray:
    """Posterior weights of an effect's alternative functions from their BIC scores (drop of the
    objective less k ln n: the weight of each is exp(score / 2), normalised)."""
    s = np.asarray(score, dtype=float)
    w = np.exp(0.5 * (s - s.max()))
    return w / w.sum()


def model_average(prob, sigma, model: Columns, c, log_n=None) -> dict | None:
    """The parameters of an effect found as one of several functions, averaged over the
    functions the data cannot tell apart.

    Two error functions may have nearly the same signature on a scan (a straightness along x
    and a pitch seen through the probe's lever; a quadratic profile and a linear one over a
    short stroke). The function chosen is then a coin toss, and its parameter's std, conditional
    on that choice, says nothing of it. Each alternative of non-negligible posterior weight
    (``c.alternatives``: other functions, not another order of the chosen one's) whose
    parameters the data determine (posterior std below half the
    prior's) is fitted in place of the chosen one in the final ``model``; each
    parameter is reported with the mixture's mean and std over the alternatives (zero where a
    function lacks it): std^2 = sum_f w_f (var_f + theta_f^2) - mean^2.

    An effect that states physical parameters (:attr:`Columns.physical`: ``sensor_offset``'s
    offsets from the elements' centroid) is averaged in those, the chosen function's only.
    An effect whose nuisance is free in the final model (:attr:`Columns.nuisance`) has its
    functions weighed again there (:func:`_weighed_free`, ``log_n`` the BIC's ln n).

    Returns
    -------
    dict or None
        ``params`` {name: (mean, std, std of the chosen function's own fit or None)},
        ``units`` {name: unit},
        ``alternatives`` [(label, weight, names)]; None when one function carries the weight.
    """
    if not c.has_new or c.family_block is None:
        return None
    own = list(c.cols.names)
    rest = model.subset([i for i, n in enumerate(model.names) if n not in own])
    alternatives = c.alternatives
    if c.cols.nuisance is not None and log_n is not None:
        alternatives = _weighed_free(prob, sigma, rest, c, log_n)
    if len(alternatives) < 2:
        return None
    runs, units = [], {}
    for label, idx, w in alternatives:
        sub = c.family_block.subset(idx)
        sub.families = None
        if set(sub.names) & set(rest.names):
            continue  # the function is in the model already (found in another round)
        f = fit_map(prob.y, sigma, stack([rest, sub]))
        if np.any(f.std[rest.p :] > 0.5 * sub.prior_std):
            continue  # the data do not determine the function's parameters: no estimate
        th, cov = f.theta[rest.p :], f.cov[rest.p :, rest.p :]
        if sub.physical is not None:  # averaged as the effect reports them
            phys = sub.physical(sub.names, th, cov)
            params = {n: v[:2] for n, v in phys.items()}
            units |= {n: v[2] for n, v in phys.items()}
        else:
            params = dict(zip(sub.names, zip(th, f.std[rest.p :], strict=True), strict=True))
            units |= dict(zip(sub.names, sub.units, strict=True))
        runs.append((label, w, params))
    tot = sum(w for _, w, _ in runs)
    if len(runs) < 2 or tot <= 0:
        return None
    chosen = next((p for lb, _, p in runs if lb == c.family), {})
    names = list(dict.fromkeys(n for _, _, p in runs for n in p))
    if c.cols.physical is not None and chosen:
        # offsets along the directions the chosen function fits: an alternative's along
        # another direction would read as zero within a std the data never gave
        names = list(chosen)
    out = {}
    for nm in names:
        m1 = sum(w * p[nm][0] for _, w, p in runs if nm in p) / tot
        m2 = sum(w * (p[nm][0] ** 2 + p[nm][1] ** 2) for _, w, p in runs if nm in p) / tot
        out[nm] = (m1, float(np.sqrt(max(m2 - m1**2, 0.0))), chosen.get(nm, (0, None))[1])
    return {
        "params": out,
        "units": {nm: units[nm] for nm in out},
        "alternatives": [(lb, w / tot, list(p)) for lb, w, p in runs],
    }


def _weighed_free(prob, sigma, rest: Columns, c, log_n: float) -> list:
    """The functions of an accepted effect weighed as the selection weighs them, but against
    ``rest`` (the final model less the effect's chosen function), where the effect's
    nuisance is free (``sensor_offset``: the elements' common shift, the magnet's offsets
    released). In the selection that shift is held by the survey, which prefers the element
    whose displacement carries the least common shift; with it free, two elements along a
    direction only one of the others sees (the x and the z element of a quadrupole's body,
    along x) read alike, and their offsets from the centroid are averaged over both. A pair
    that holds the chosen function is another placement of the elements too, not another
    order of one error: one element displaced from two that sit together, or two displaced
    from the third (the offsets from the centroid differ by the second's share), and is
    averaged over like any other.

    Returns
    -------
    list of (label, idx, weight)
        As ``Candidate.alternatives``, of weight at least :data:`ALT_MIN_WEIGHT`.
    """
    blk = c.family_block
    current = fit_map(prob.y, sigma, rest)
    current.q_data = model_basis(sigma, rest)
    M, g = screen_gram(sigma, rest, current, blk.J)
    options = function_options(blk.families, blk.pairs)
    stages = {st: sum(1 for o in options if o[2] == st) for st in (1, 2)}
    score = np.array([
        screened_drop(M, g, idx) - len(idx) * log_n - 2.0 * np.log(stages[st])
        for _, idx, st in options
    ])  # fmt: skip
    w = family_weights(score)
    return [
        ("+".join(lb), ix, float(w[j]))
        for j in np.argsort(-w, kind="stable")
        for lb, ix, _ in [options[j]]
        if w[j] >= ALT_MIN_WEIGHT
    ]


def model_basis(sigma, model):
    """Data rows of an orthonormal basis of the whitened, prior-augmented model columns."""
    A = (model.J / sigma[..., None]).reshape(-1, model.p)
    ok = np.isfinite(A).all(1)
    has = np.isfinite(model.prior_std) & (model.prior_std > 0)
    P = np.diag(1.0 / np.where(has, model.prior_std, 1.0))[has]
    sc = np.sqrt(
        (A[ok] ** 2).sum(0) + np.where(has, 1.0 / np.where(has, model.prior_std, 1), 0) ** 2
    )
    sc[sc == 0] = 1.0
    Aa = np.vstack([np.where(ok[:, None], A, 0.0), P]) / sc
    u, s, _ = np.linalg.svd(Aa, full_matrices=False)
    u = u[:, s > 1e-10 * s[0]]
    return u[: A.shape[0]]


def other_functions(sigma, model: Columns, accepted, blk: Columns):
    """The functions of an accepted effect that stay candidates (``blk`` less the functions
    accepted and those ``model`` spans), or None when none is left."""
    if accepted.family is None:
        return None
    used = set(accepted.functions)
    rest = sorted({k for lb, idx in blk.families if lb not in used for k in idx})
    if not rest:
        return None
    out = blk.subset(rest)
    out.families = [f for f in out.families if f[0] not in used]
    if out.pairs is not None:
        out.pairs = [pr for pr in out.pairs if not {pr[1], pr[2]} & used]
    out = unspanned(sigma, model, out)
    return out if out.p else None


#: A column whose whitened norm the model leaves below this fraction is one the model spans.
SPANNED = 1e-8


def unspanned(sigma, model: Columns, blk: Columns) -> Columns:
    """``blk`` (an effect of several functions) without the functions all of whose columns
    ``model`` spans (``sensor_offset``: the third element along a direction two elements are
    fitted along, whose offset the other two give)."""
    W = (model.J / sigma[..., None]).reshape(-1, model.p)
    V = (blk.J / sigma[..., None]).reshape(-1, blk.p)
    ok = np.all(np.isfinite(W), axis=1) & np.all(np.isfinite(V), axis=1)
    Q = np.linalg.qr(W[ok])[0] if model.p else np.zeros((ok.sum(), 0))
    V = V[ok]
    left = np.sum((V - Q @ (Q.T @ V)) ** 2, axis=0)
    spanned = left <= SPANNED * np.maximum(np.sum(V**2, axis=0), 1e-300)
    fams = [f for f in blk.families if not all(spanned[k] for k in f[1])]
    if len(fams) == len(blk.families):
        return blk
    return blk.subset(sorted({k for _, idx in fams for k in idx}))
