"""Linear-Gaussian MAP calibration: the engine under every fit of the diagnosis.

The data are residuals ``y`` of shape (n, 3) (tracker: measured minus nominal probe position, mm;
Hall map: measured minus reference field, T) with a standard deviation ``sigma`` of the same
shape. A model is a set of columns ``J`` of shape (n, 3, p): the change of ``y`` per unit of
each parameter, parameters in display units (um, urad, ppm, ...). Parameters may carry a Gaussian
prior (mean, std; std = inf for none). The MAP estimate minimises

    chi2(theta) = sum ((y - J theta) / sigma)**2 + sum ((theta - m0) / s0)**2

solved as one augmented least-squares problem by SVD (rank-deficient combinations are
regularised by the priors, or reported as non-identifiable when no prior holds them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Columns", "Fit", "fit_map", "identifiability", "released_in", "stack"]


@dataclass
class Columns:
    """A block of model columns with names, units and priors.

    Attributes
    ----------
    J : ndarray, shape (n, 3, p)
        Change of the residual per unit of each parameter (mm or T per display unit).
    names : list of str, length p
    units : list of str, length p
    prior_mean : ndarray, shape (p,)
    prior_std : ndarray, shape (p,)
        ``inf`` for no prior.
    group : str
        Which block it is (``'bench'``, ``'registration'``, an effect name).
    bounds : ndarray, shape (p, 2), optional
        Physically plausible range [low, high] of each parameter (display units); an effect
        whose fitted value lies beyond it by more than 3 standard uncertainties is reported as
        an implausible fit, never as found. None: no bounds.
    release : tuple of str
        Names of baseline parameters whose priors this effect releases (``parameter_bias``,
        ``magnet_misalignment``, the gains of ``hall_offset_gain``): their change is a
        prior-data conflict, not a new signature.
    release_bounds : ndarray, shape (len(release), 2), optional
        Plausible range of the released parameters (display units).
    physical : callable, optional
        ``physical(names, theta, cov) -> {name: (value, std, unit)}``: the physical parameters
        of a linearised non-linear effect (``fringe_field_3d``) from its fitted linear ones
        (``names``: those still in the block), uncertainty propagated; None: the parameters
        are physical already.
    replaces : dict, optional
        ``{baseline parameter name: column (n, 3)}``: how the effect changes the signature of
        parameters already in the model (``fringe_field_3d``: the bench errors, the magnet
        registration and the Hall gains act on the 3-D field, not on the 2-D reference).
        :func:`stack` puts these columns in place of the same-named columns of the blocks
        before this one, so the parameters keep their priors and are fitted jointly with the
        effect. None: the effect only adds columns.
    var_known : ndarray, shape (n, 3), optional
        Variance of the observations known from the bench model (vibration through the
        gradient) when this effect is in the model, in place of the problem's (``fringe_field_3d``:
        through the 3-D gradient); :func:`stack` keeps the last one given. None: the problem's.
    families : list of (str, list of int), optional
        Error functions within the effect, each a label and its column indices
        (``position_dependent_geometric``: one per axis error, ``eps_z(z)`` with its linear
        and quadratic profile). The selection tests each function on its own, with the
        multiplicity of the choice accounted for, and may take several in turn. None: the
        block is one function.
    pairs : list of (str, str, str), optional
        The pairs of ``families`` tested together, each a group and two labels; of the pairs
        of one group only the first whose functions are both present is tested (pairs that
        span the same columns: ``sensor_offset``'s two elements of three along one
        direction). None: every pair, where the effect has at most
        :data:`~cfm_fem.workflows.diagnose.functions.PAIR_MAX_FUNCTIONS` functions.
    multiplicity : float
        Number of alternatives searched to build the columns (``step_event``: candidate change
        points); the evidence is corrected for it (Bonferroni). 1: none.
    info : dict, optional
        Per-parameter facts reported with the estimate (``step_event``: where the step is).
    bounds_why : list of str, optional
        Reason of each bound in place of the catalogue's (``fringe_field_3d``: an edge must lie
        in the z range the data cover); '' keeps the catalogue's.
    model_rows : ndarray of bool, shape (n,), optional
        Rows where an approximate model of a non-linear effect (``fringe_field_3d``: the soft
        ends) carries the signal: the reported std of its physical parameters is scaled by the
        square root of the reduced chi2 of the fitted model there when above 1 (its lack of
        fit). None: the model is taken as exact.
    element : tuple of int, optional
        For an effect on the field a Hall element senses (``probe_misalignment``,
        ``planar_hall``): the element (0, 1, 2 for x, y, z) whose reading each parameter's
        column changes. The element's gain scales that change as it scales the field, so the
        columns fit the parameter times (1 + gain); the reported value is divided by it.
        None: no such conversion.
    model_dependent : tuple of str, optional
        Physical parameters that belong to an assumed shape (``fringe_field_3d``: the edges
        and fringe length of a Fermi profile) rather than to the data alone; reported as
        model-dependent. None: every physical parameter when the block has ``model_rows``.
    lower_order : dict, optional
        ``{lower-order term: its higher-order term}`` of functions fitted at the order the
        selection chooses (``position_dependent_geometric``: ``eps_z(z)_u1`` alone, or with
        ``eps_z(z)_u2``). A lower-order term reported without its higher-order term is the
        coefficient of that chosen order (the slope of the straight line through a curved error
        over the scanned part of the stroke), not the function's own coefficient: it is
        reported as model-dependent. None: no such terms.
    ref_error : tuple (ndarray (m, 3), ndarray (n,)), optional
        For an effect with the shape of the reference's own error between its nodes
        (``sensor_volume_averaging``: a curvature term): the stated std (T) of that error at
        each distinct point, and each row's point. The selection credits the effect only with
        what an error of that size cannot explain
        (:func:`~cfm_fem.workflows.diagnose.select.reference_explains`). None: no such term.
    nuisance : Columns, optional
        Parameters the effect's reported estimates are marginalised over, which its evidence
        is not tested with (``sensor_offset``: the shift common to the three Hall elements,
        free of any prior: it moves the readings as the magnet's offset does, but the magnet's
        survey says nothing about where the elements sit in the probe). The selection tests
        the effect's own columns; the accepted effect's parameters and their covariance come
        from the final model with these columns added. Its ``release`` names the baseline
        parameters whose priors the data cannot check while it is free (the magnet's offsets:
        a conflict of theirs is not stated once the effect is accepted). None: no such
        parameters.
    """

    J: np.ndarray
    names: list
    units: list
    prior_mean: np.ndarray
    prior_std: np.ndarray
    group: str
    bounds: np.ndarray | None = None
    release: tuple = ()
    release_bounds: np.ndarray | None = None
    physical: object = None
    replaces: dict | None = None
    var_known: np.ndarray | None = None
    families: list | None = None
    pairs: list | None = None
    multiplicity: float = 1.0
    info: dict | None = None
    bounds_why: list | None = None
    model_rows: np.ndarray | None = None
    element: tuple | None = None
    model_dependent: tuple | None = None
    lower_order: dict | None = None
    ref_error: tuple | None = None
    nuisance: Columns | None = None

    @property
    def p(self) -> int:
        return self.J.shape[-1]

    def subset(self, keep) -> Columns:
        """The block restricted to the columns ``keep`` (indices; release kept, families
        renumbered and emptied ones dropped, with the pairs of a dropped one)."""
        keep = list(keep)
        rb = self.release_bounds
        fams = None
        if self.families is not None:
            where = {k: i for i, k in enumerate(keep)}
            fams = [
                (label, [where[k] for k in idx if k in where])
                for label, idx in self.families
                if any(k in where for k in idx)
            ]
        pairs = self.pairs
        if pairs is not None and fams is not None:
            labels = {label for label, _ in fams}
            pairs = [pr for pr in pairs if pr[1] in labels and pr[2] in labels]
        return Columns(
            self.J[..., keep],
            [self.names[k] for k in keep],
            [self.units[k] for k in keep],
            self.prior_mean[keep],
            self.prior_std[keep],
            self.group,
            None if self.bounds is None else self.bounds[keep],
            self.release,
            rb,
            self.physical,
            self.replaces,
            self.var_known,
            fams,
            pairs,
            self.multiplicity,
            self.info,
            None if self.bounds_why is None else [self.bounds_why[k] for k in keep],
            self.model_rows,
            None if self.element is None else tuple(self.element[k] for k in keep),
            self.model_dependent,
            self.lower_order,
            self.ref_error,
            self.nuisance,
        )

    def released(self, group: str) -> Columns:
        """The same columns without priors (a 'prior release' effect)."""
        return Columns(
            self.J,
            list(self.names),
            list(self.units),
            np.zeros(self.p),
            np.full(self.p, np.inf),
            group,
        )


def released_in(model: Columns, names) -> Columns:
    """``model`` with the priors of the parameters ``names`` removed (a copy)."""
    std = model.prior_std.copy()
    for nm in names:
        std[model.names.index(nm)] = np.inf
    return Columns(
        model.J,
        list(model.names),
        list(model.units),
        model.prior_mean,
        std,
        model.group,
        var_known=model.var_known,
    )


def stack(blocks) -> Columns:
    """Concatenate column blocks (group of the result: ``'+'``-joined; bounds dropped).

    A block with ``replaces`` substitutes its columns for the same-named columns of the blocks
    before it (the parameters stay where they are, with their priors); the last ``var_known``
    given is kept."""
    blocks = list(blocks)
    J = np.concatenate([b.J for b in blocks], axis=-1)
    names = [n for b in blocks for n in b.names]
    k0 = 0
    for b in blocks:
        for nm, col in (b.replaces or {}).items():
            if nm in names[:k0]:
                J[..., names.index(nm)] = col  # J is a new array (concatenate)
        k0 += b.p
    vk = [b.var_known for b in blocks if b.var_known is not None]
    return Columns(
        J,
        names,
        [u for b in blocks for u in b.units],
        np.concatenate([b.prior_mean for b in blocks]),
        np.concatenate([b.prior_std for b in blocks]),
        "+".join(b.group for b in blocks),
        var_known=vk[-1] if vk else None,
    )


@dataclass
class Fit:
    """Result of :func:`fit_map`.

    Attributes
    ----------
    theta : ndarray, shape (p,)
        MAP estimate, display units.
    cov : ndarray, shape (p, p)
        Posterior covariance (inverse of the augmented normal matrix, pseudo-inverse when
        singular).
    resid : ndarray, shape (n, 3)
        y - J theta on all rows (held-out rows too).
    chi2_data : float
        Sum of squared standardised residuals over the fitted rows.
    chi2_prior : float
    n_obs : int
        Number of fitted scalar observations.
    edf : float
        Effective number of fitted parameters, trace of the hat matrix (p minus prior shrinkage).
    rank : int
    singular_values : ndarray
        Of the whitened augmented system.
    """

    theta: np.ndarray
    cov: np.ndarray
    resid: np.ndarray
    chi2_data: float
    chi2_prior: float
    n_obs: int
    edf: float
    rank: int
    singular_values: np.ndarray
    vt: np.ndarray
    scale: np.ndarray
    q_data: np.ndarray | None = None  # cache of the selection's screening (functions.screen_gram)

    @property
    def objective(self) -> float:
        return self.chi2_data + self.chi2_prior

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))


def fit_map(y, sigma, cols: Columns, mask=None, rcond: float = 1e-10) -> Fit:
    """MAP estimate of the parameters of ``cols`` from the rows in ``mask``.

    Parameters
    ----------
    y : ndarray, shape (n, 3)
    sigma : ndarray, shape (n, 3)
        Standard deviation of each observation (same unit as ``y``); inf drops it.
    cols : Columns
    mask : ndarray of bool, shape (n,), optional
        Rows used for fitting (default all); residuals are returned for every row.
    rcond : float
        Relative cut-off of singular values (directions below it are left at the prior mean).

    Returns
    -------
    Fit
    """
    y = np.asarray(y, dtype=np.float64)
    n = y.shape[0]
    mask = np.ones(n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    J = cols.J
    w = 1.0 / np.asarray(sigma, dtype=np.float64)
    A = (J[mask] * w[mask][..., None]).reshape(-1, cols.p)
    b = (y[mask] * w[mask]).reshape(-1)
    keep = np.isfinite(b)
    A, b = A[keep], b[keep]
    has_prior = np.isfinite(cols.prior_std) & (cols.prior_std > 0)
    P = np.zeros(cols.p)
    P[has_prior] = 1.0 / cols.prior_std[has_prior]
    # column scaling for conditioning
    scale = np.sqrt((A**2).sum(0) + P**2)
    scale[scale == 0] = 1.0
    prow = np.diag(P)[has_prior]
    Aa = np.vstack([A, prow]) / scale
    ba = np.concatenate([b, (cols.prior_mean * P)[has_prior]])
    u, s, vt = np.linalg.svd(Aa, full_matrices=False)
    good = s > rcond * s[0]
    sinv = np.where(good, 1.0 / np.where(good, s, 1.0), 0.0)
    z = vt.T @ (sinv * (u.T @ ba))
    theta = z / scale
    cov = (vt.T * sinv**2) @ vt / np.outer(scale, scale)
    resid = y - np.einsum("nkp,p->nk", J, theta)
    r = (resid[mask] * w[mask]).reshape(-1)[keep]
    chi2_data = float(r @ r)
    chi2_prior = float((((theta - cols.prior_mean) * P)[has_prior] ** 2).sum())
    # effective dof: p - trace(cov * P^2)
    edf = float(good.sum() - np.sum(np.diag(cov) * P**2))
    return Fit(
        theta=theta,
        cov=cov,
        resid=resid,
        chi2_data=chi2_data,
        chi2_prior=chi2_prior,
        n_obs=int(keep.sum()),
        edf=edf,
        rank=int(good.sum()),
        singular_values=s,
        vt=vt,
        scale=scale,
    )


def identifiability(y_sigma, cols: Columns, n_show: int = 5, tol: float = 1e-6) -> dict:
    """What the data alone (no priors) can tell apart.

    Parameters
    ----------
    y_sigma : ndarray, shape (n, 3)
        Standard deviations of the observations.
    cols : Columns
    n_show : int
        Number of null-space combinations and correlated pairs to report.
    tol : float
        Relative singular value below which a combination is called not identifiable.

    Returns
    -------
    dict
        ``condition_number`` (of the column-scaled data Jacobian, identifiable part),
        ``rank``, ``n_params``, ``not_identifiable`` (list of combinations, each a dict of the
        largest coefficients), ``correlated_pairs`` (largest |correlation| of the posterior).
    """
    w = 1.0 / y_sigma
    A = (cols.J * w[..., None]).reshape(-1, cols.p)
    A = A[np.isfinite(A).all(1)]
    sc = np.sqrt((A**2).sum(0))
    zero = sc == 0
    sc[zero] = 1.0
    _, s, vt = np.linalg.svd(A / sc, full_matrices=False)
    good = s > tol * s[0]
    rank = int(good.sum())
    cond = float(s[0] / s[good][-1]) if rank else float("inf")
    null = []
    for v in vt[~good][:n_show]:
        order = np.argsort(-np.abs(v))[:4]
        null.append({cols.names[k]: round(float(v[k]), 3) for k in order if abs(v[k]) > 0.05})
    null.extend({cols.names[k]: 1.0} for k in np.flatnonzero(zero)[:n_show])
    return {
        "condition_number": cond,
        "rank": rank,
        "n_params": cols.p,
        "n_not_identifiable": int(cols.p - rank),
        "not_identifiable": null[:n_show],
    }


def correlated_pairs(fit: Fit, names, n_show: int = 5, threshold: float = 0.9) -> list:
    """Parameter pairs with the largest posterior |correlation| above ``threshold``."""
    sd = fit.std
    ok = sd > 0
    c = fit.cov / np.outer(np.where(ok, sd, 1), np.where(ok, sd, 1))
    iu = np.triu_indices(len(sd), 1)
    vals = np.abs(c[iu])
    order = np.argsort(-vals)
    out = []
    for k in order[:n_show]:
        if vals[k] < threshold:
            break
        i, j = iu[0][k], iu[1][k]
        out.append({"a": names[i], "b": names[j], "correlation": round(float(c[i, j]), 4)})
    return out
