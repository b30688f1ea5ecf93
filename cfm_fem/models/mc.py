"""GUM Supplement 1 (JCGM 101:2008) machinery shared by every workflow.

Coverage intervals from Monte Carlo samples (section 7.7), the numerical tolerance of a standard
uncertainty (section 7.9.2) and the validation of the GUM uncertainty framework against Monte Carlo
(section 8); PDFs of the input quantities (6.4), plain Monte Carlo propagation for vectorised
numpy models, the adaptive procedure (7.9.4), the GUM uncertainty framework (first order, with
Welch-Satterthwaite effective degrees of freedom, JCGM 100 G.4) and linearised variance budgets.
The paper-scale bench Monte Carlo with its numba kernels is in :mod:`cfm_fem.models.kinematics`; it
uses the rank and tolerance helpers here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError

__all__ = [
    "coverage_count",
    "symmetric_interval",
    "symmetric_ranks",
    "shortest_interval",
    "numerical_tolerance",
    "gum_validation",
    "Pdf",
    "KERNEL_PDF_CODES",
    "PDF_PARAMETERS",
    "ppf_numpy",
    "McSummary",
    "summarize",
    "draw_inputs",
    "monte_carlo",
    "AdaptiveResult",
    "adaptive_monte_carlo",
    "sensitivities_fd",
    "GumResult",
    "gum_linear",
    "validate_gum",
    "variance_shares",
]


def coverage_count(m: int, p: float = 0.95) -> int:
    """Number of sample intervals q spanned by a coverage interval (JCGM 101, 7.7.1).

    q = p*M if that is an integer, else int(p*M + 1/2).
    """
    pm = p * m
    q = round(pm) if abs(pm - round(pm)) < 1e-9 else int(pm + 0.5)
    return int(min(max(q, 1), m - 1))


def symmetric_interval(samples, p: float = 0.95, axis: int = -1, presorted: bool = False):
    """Probabilistically symmetric coverage interval (JCGM 101, 7.7.2).

    Parameters
    ----------
    samples : ndarray, shape (..., M)
        Monte Carlo values along ``axis``.
    p : float
        Coverage probability.

    Returns
    -------
    low, high : ndarray, shape (...)
        The (M-q)/2-th and ((M-q)/2 + q)-th order statistics (1-based; rounded as in 7.7.2).
    """
    y = np.moveaxis(np.asarray(samples, dtype=np.float64), axis, -1)
    if not presorted:
        y = np.sort(y, axis=-1)
    r_low, r_high = symmetric_ranks(y.shape[-1], p)
    return y[..., r_low - 1], y[..., r_high - 1]


def symmetric_ranks(m: int, p: float = 0.95) -> tuple[int, int]:
    """1-based ranks of the ends of the probabilistically symmetric interval (JCGM 101, 7.7.2).

    The low end is order statistic r = (M - q)/2 (rounded up when M - q is odd), the high end
    r + q, with q from :func:`coverage_count`. Streaming code uses these ranks directly.
    """
    q = coverage_count(m, p)
    r = (m - q) // 2 if (m - q) % 2 == 0 else (m - q + 1) // 2
    r = max(r, 1)
    return int(r), int(r + q)


def shortest_interval(samples, p: float = 0.95, axis: int = -1, presorted: bool = False):
    """Shortest coverage interval (JCGM 101, 7.7.4).

    Returns
    -------
    low, high : ndarray, shape (...)
        y_(r*) and y_(r*+q), r* minimising y_(r+q) - y_(r) over r = 1..M-q.
    """
    y = np.moveaxis(np.asarray(samples, dtype=np.float64), axis, -1)
    if not presorted:
        y = np.sort(y, axis=-1)
    m = y.shape[-1]
    q = coverage_count(m, p)
    widths = y[..., q:] - y[..., : m - q]
    r = np.argmin(widths, axis=-1)[..., None]
    return np.take_along_axis(y, r, -1)[..., 0], np.take_along_axis(y, r + q, -1)[..., 0]


def numerical_tolerance(u, ndig: int = 2):
    """Numerical tolerance delta of a standard uncertainty (JCGM 101, 7.9.2).

    ``u`` is written as c x 10**l with c an ``ndig``-digit integer; delta = 10**l / 2.
    Zero gives zero. c is u rounded to ``ndig`` significant digits, so a u that rounds up into
    the next decade takes that decade's l (0.0996 with two digits is 10 x 10**-2, delta 0.005).
    """
    u = np.abs(np.asarray(u, dtype=np.float64))
    safe = np.where(u > 0, u, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        l_exp = np.floor(np.log10(safe)) - (ndig - 1)
        c = np.floor(safe / 10.0**l_exp + 0.5)
    l_exp = np.where(c >= 10**ndig, l_exp + 1, l_exp)
    delta = 0.5 * 10.0**l_exp
    return np.where(u > 0, delta, 0.0)


def gum_validation(y, expanded_u, low, high, delta):
    """Compare the GUM interval y +- U with a Monte Carlo interval [low, high] (JCGM 101, 8.2).

    Returns
    -------
    d_low, d_high : ndarray
        |y - U - low| and |y + U - high|.
    valid : ndarray of bool
        True where both are at most ``delta``.
    """
    y, expanded_u, low, high = (np.asarray(a, dtype=np.float64) for a in (y, expanded_u, low, high))
    d_low = np.abs(y - expanded_u - low)
    d_high = np.abs(y + expanded_u - high)
    return d_low, d_high, (d_low <= delta) & (d_high <= delta)


# ---------------------------------------------------------------------------------------------
# Probability density functions assigned to input quantities (JCGM 101, 6.4)
# ---------------------------------------------------------------------------------------------

#: Integer codes of the PDFs the numba kernels sample by inverse CDF (see ``Pdf.kernel_code``).
KERNEL_PDF_CODES = {
    "constant": 0,
    "uniform": 1,
    "normal": 2,
    "triangular": 3,
    "arcsine": 4,
    "trapezoidal": 5,
}

#: Parameters of each PDF, in order, as written in bench files and ``Pdf.params``.
PDF_PARAMETERS = {
    "constant": ("value",),
    "uniform": ("low", "high"),
    "normal": ("mean", "std"),
    "triangular": ("low", "mode", "high"),
    "arcsine": ("low", "high"),
    "trapezoidal": ("low", "high", "beta"),
    "student_t": ("loc", "scale", "dof"),
    "curvilinear_trapezoidal": ("low", "high", "d"),
}


@dataclass(frozen=True)
class Pdf:
    """A PDF assigned to one input quantity (JCGM 101, 6.4), in the quantity's own unit.

    Build it with the class methods (``Pdf.uniform(-1.5, 1.5)``) or ``Pdf.from_params``; both check
    the parameters and raise :class:`~cfm_fem.errors.CfmInputError` naming what was expected.

    Conventions
    -----------
    - ``normal(mean, std)``: N(mean, std**2); the second number is a standard deviation.
    - ``trapezoidal(low, high, beta)``: symmetric trapezoid on [low, high] whose top has width
      ``beta * (high - low)`` (JCGM 101, 6.4.4); beta = 0 is triangular, beta = 1 uniform.
    - ``arcsine(low, high)``: U-shaped (JCGM 101, 6.4.6), std = (high - low) / (2 sqrt 2).
    - ``student_t(loc, scale, dof)``: scaled and shifted t_nu(loc, scale**2) of JCGM 101 6.4.9:
      X = loc + scale * T_nu. ``scale`` is the GUM standard uncertainty s/sqrt(n) of a mean, not the
      standard deviation of X, which is scale * sqrt(nu / (nu - 2)).
    - ``curvilinear_trapezoidal(low, high, d)``: rectangular with inexactly known limits, the
      half-width known to +- d (JCGM 101, 6.4.3); needs two uniforms per draw.
    """

    kind: str
    params: tuple

    # -- constructors ------------------------------------------------------------------------
    @classmethod
    def from_params(cls, kind: str, **params) -> Pdf:
        """Build from a kind name and its named parameters (see ``PDF_PARAMETERS``)."""
        if kind not in PDF_PARAMETERS:
            raise CfmInputError(
                f"unknown pdf '{kind}'; expected one of {', '.join(PDF_PARAMETERS)}"
            )
        names = PDF_PARAMETERS[kind]
        missing = [n for n in names if n not in params]
        extra = [n for n in params if n not in names]
        if missing or extra:
            raise CfmInputError(
                f"pdf '{kind}' takes parameters {', '.join(names)}"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(extra)}" if extra else "")
            )
        values = []
        for n in names:
            v = params[n]
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise CfmInputError(f"pdf '{kind}' parameter '{n}' must be a number; found {v!r}")
            if not np.isfinite(v):
                raise CfmInputError(f"pdf '{kind}' parameter '{n}' must be finite; found {v!r}")
            values.append(float(v))
        pdf = cls(kind, tuple(values))
        pdf._check()
        return pdf

    @classmethod
    def constant(cls, value):
        return cls.from_params("constant", value=value)

    @classmethod
    def uniform(cls, low, high):
        return cls.from_params("uniform", low=low, high=high)

    @classmethod
    def normal(cls, mean, std):
        return cls.from_params("normal", mean=mean, std=std)

    @classmethod
    def triangular(cls, low, mode, high):
        return cls.from_params("triangular", low=low, mode=mode, high=high)

    @classmethod
    def arcsine(cls, low, high):
        return cls.from_params("arcsine", low=low, high=high)

    @classmethod
    def trapezoidal(cls, low, high, beta):
        return cls.from_params("trapezoidal", low=low, high=high, beta=beta)

    @classmethod
    def student_t(cls, loc, scale, dof):
        return cls.from_params("student_t", loc=loc, scale=scale, dof=dof)

    @classmethod
    def curvilinear_trapezoidal(cls, low, high, d):
        return cls.from_params("curvilinear_trapezoidal", low=low, high=high, d=d)

    def _check(self):
        k, p = self.kind, self.params
        if (
            k in ("uniform", "arcsine", "trapezoidal", "curvilinear_trapezoidal")
            and not p[0] < p[1]
        ):
            raise CfmInputError(f"pdf '{k}' needs low < high; found low={p[0]}, high={p[1]}")
        if k == "normal" and p[1] < 0:
            raise CfmInputError(f"pdf 'normal' needs std >= 0; found std={p[1]}")
        if k == "triangular" and not (p[0] <= p[1] <= p[2] and p[0] < p[2]):
            raise CfmInputError(
                f"pdf 'triangular' needs low <= mode <= high and low < high; found {p}"
            )
        if k == "trapezoidal" and not 0.0 <= p[2] <= 1.0:
            raise CfmInputError(f"pdf 'trapezoidal' needs 0 <= beta <= 1; found beta={p[2]}")
        if k == "student_t" and (p[1] < 0 or p[2] <= 2):
            raise CfmInputError(
                f"pdf 'student_t' needs scale >= 0 and dof > 2 (finite variance); found {p}"
            )
        if k == "curvilinear_trapezoidal" and not 0 <= p[2] <= (p[1] - p[0]) / 2:
            raise CfmInputError(
                f"pdf 'curvilinear_trapezoidal' needs 0 <= d <= (high - low)/2; found d={p[2]}"
            )

    # -- moments -----------------------------------------------------------------------------
    @property
    def mean(self) -> float:
        k, p = self.kind, self.params
        if k == "constant":
            return p[0]
        if k in ("normal", "student_t"):
            return p[0]
        if k == "triangular":
            return (p[0] + p[1] + p[2]) / 3.0
        return 0.5 * (p[0] + p[1])

    @property
    def std(self) -> float:
        k, p = self.kind, self.params
        if k == "constant":
            return 0.0
        if k == "normal":
            return p[1]
        if k == "student_t":
            return p[1] * np.sqrt(p[2] / (p[2] - 2.0))
        if k == "uniform":
            return (p[1] - p[0]) / np.sqrt(12.0)
        if k == "arcsine":
            return (p[1] - p[0]) / (2.0 * np.sqrt(2.0))
        if k == "triangular":
            a, c, b = p
            return np.sqrt((a * a + b * b + c * c - a * b - a * c - b * c) / 18.0)
        if k == "trapezoidal":
            a, b, beta = p
            return (b - a) / 2.0 * np.sqrt((1.0 + beta * beta) / 6.0)  # JCGM 101 (6.4.4.3)
        a, b, d = p  # curvilinear trapezoidal, JCGM 101 (6.4.3.3)
        return np.sqrt(((b - a) / 2.0) ** 2 / 3.0 + d * d / 9.0)

    @property
    def n_uniforms(self) -> int:
        """Uniform numbers consumed per draw by :meth:`from_uniforms`."""
        return 2 if self.kind == "curvilinear_trapezoidal" else 1

    def scaled(self, factor: float) -> Pdf:
        """The PDF of ``factor * X`` (used for unit conversion and for tolerance scaling)."""
        f = float(factor)
        k, p = self.kind, self.params
        if k == "normal":
            return Pdf(k, (p[0] * f, abs(f) * p[1]))
        if k == "student_t":
            return Pdf(k, (p[0] * f, abs(f) * p[1], p[2]))
        if k == "trapezoidal":
            lo, hi = sorted((p[0] * f, p[1] * f))
            return Pdf(k, (lo, hi, p[2])) if lo < hi else Pdf("constant", (0.0,))
        if k == "curvilinear_trapezoidal":
            lo, hi = sorted((p[0] * f, p[1] * f))
            return Pdf(k, (lo, hi, abs(f) * p[2])) if lo < hi else Pdf("constant", (0.0,))
        if k == "triangular":
            a, c, b = (v * f for v in p)
            if f < 0:
                a, b = b, a
            return Pdf(k, (a, c, b)) if a < b else Pdf("constant", (0.0,))
        if k in ("uniform", "arcsine"):
            lo, hi = sorted((p[0] * f, p[1] * f))
            return Pdf(k, (lo, hi)) if lo < hi else Pdf("constant", (0.0,))
        return Pdf(k, (p[0] * f,))

    def named_params(self) -> dict:
        return dict(zip(PDF_PARAMETERS[self.kind], self.params, strict=True))

    def describe(self, unit: str = "") -> str:
        """Short text such as ``U(-1.5, 1.5) um`` or ``N(5.5, 7.8^2) um``."""
        p = ", ".join(f"{v:g}" for v in self.params)
        short = {
            "constant": "const",
            "uniform": "U",
            "normal": "N",
            "triangular": "Tri",
            "arcsine": "Arcsine",
            "trapezoidal": "Trap",
            "student_t": "t",
            "curvilinear_trapezoidal": "CTrap",
        }[self.kind]
        if self.kind == "normal":
            p = f"{self.params[0]:g}, {self.params[1]:g}^2"
        return f"{short}({p})" + (f" {unit}" if unit else "")

    def kernel_code(self) -> tuple[int, np.ndarray]:
        """(code, params padded to 4) for the numba samplers; only the kernel PDFs have one."""
        if self.kind not in KERNEL_PDF_CODES:
            raise CfmInputError(
                f"pdf '{self.kind}' is not available in the bench kernels; use one of "
                f"{', '.join(KERNEL_PDF_CODES)}"
            )
        par = np.zeros(4)
        par[: len(self.params)] = self.params
        return KERNEL_PDF_CODES[self.kind], par

    # -- sampling ----------------------------------------------------------------------------
    def from_uniforms(self, u):
        """Transform uniforms in (0, 1) to values of this PDF.

        Parameters
        ----------
        u : ndarray, shape (...,) or (..., 2) for the curvilinear trapezoid
            Independent U(0, 1) numbers, 0 and 1 excluded.

        Returns
        -------
        ndarray, shape (...)
            Inverse-CDF transform (the same formulas as the numba kernels), except the
            curvilinear trapezoid (JCGM 101 6.4.3.4, two uniforms).
        """
        from scipy import special

        u = np.asarray(u, dtype=np.float64)
        k, p = self.kind, self.params
        if k == "curvilinear_trapezoidal":
            a, b, d = p
            a_s = (a - d) + 2.0 * d * u[..., 0]
            b_s = (a + b) - a_s
            return a_s + (b_s - a_s) * u[..., 1]
        if k == "student_t":
            return p[0] + p[1] * special.stdtrit(p[2], u)
        return ppf_numpy(KERNEL_PDF_CODES[k], np.asarray(self.kernel_code()[1]), u)

    def sample(self, rng: np.random.Generator, size) -> np.ndarray:
        """``size`` draws with numpy's ``rng`` (tests and small models; kernels draw their own)."""
        size = (size,) if np.isscalar(size) else tuple(size)
        if self.kind == "normal":
            return self.params[0] + self.params[1] * rng.standard_normal(size)
        if self.kind == "student_t":
            return self.params[0] + self.params[1] * rng.standard_t(self.params[2], size)
        shape = size + ((2,) if self.n_uniforms == 2 else ())
        u = rng.random(shape)
        u = np.where(u == 0.0, 0.5 * 2.0**-53, u)  # open interval, as the kernels
        return self.from_uniforms(u)


# ---------------------------------------------------------------------------------------------
# Monte Carlo propagation, adaptive stopping, GUM comparison, budgets (JCGM 101 sections 7-8)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class McSummary:
    """Summary of the Monte Carlo values of one or more output quantities (JCGM 101, 7.6-7.7).

    Arrays have the shape of one model output (scalar outputs give 0-d arrays).

    Attributes
    ----------
    y : ndarray
        Estimate: the mean of the M values.
    u : ndarray
        Standard uncertainty: their standard deviation (1/(M-1)).
    low, high : ndarray
        Probabilistically symmetric coverage interval (7.7.2).
    short_low, short_high : ndarray
        Shortest coverage interval (7.7.4).
    p : float
    trials : int
    """

    y: np.ndarray
    u: np.ndarray
    low: np.ndarray
    high: np.ndarray
    short_low: np.ndarray
    short_high: np.ndarray
    p: float
    trials: int


def summarize(values, p: float = 0.95) -> McSummary:
    """Summarise Monte Carlo values, shape (M,) or (M, k) (trials first)."""
    v = np.asarray(values, dtype=np.float64)
    srt = np.sort(v, axis=0)
    srt_last = np.moveaxis(srt, 0, -1)
    lo, hi = symmetric_interval(srt_last, p, presorted=True)
    slo, shi = shortest_interval(srt_last, p, presorted=True)
    return McSummary(
        y=v.mean(axis=0),
        u=v.std(axis=0, ddof=1),
        low=lo,
        high=hi,
        short_low=slo,
        short_high=shi,
        p=p,
        trials=v.shape[0],
    )


def draw_inputs(pdfs, m: int, rng: np.random.Generator) -> np.ndarray:
    """``m`` independent draws of each input, shape (m, len(pdfs))."""
    return np.stack([pdf.sample(rng, m) for pdf in pdfs], axis=-1)


def monte_carlo(model, pdfs, trials: int = 10**6, seed: int = 0, batch: int = 10**6) -> np.ndarray:
    """Propagate the input PDFs through ``model`` (JCGM 101, 7.2-7.5).

    Parameters
    ----------
    model : callable
        ``model(x)`` with x of shape (m, n_inputs) returns the outputs, shape (m,) or (m, k);
        it must be vectorised over the first axis.
    pdfs : sequence of Pdf
        Independent input PDFs.
    trials : int
    seed : int
        Batch b draws from ``SeedSequence(seed).spawn`` child b, so the values depend on the
        seed and ``batch`` only.
    batch : int
        Trials per model call (memory bound).

    Returns
    -------
    ndarray, shape (trials,) or (trials, k)
    """
    children = np.random.SeedSequence(seed).spawn((trials + batch - 1) // batch)
    out = []
    for b, child in enumerate(children):
        m = min(batch, trials - b * batch)
        out.append(np.asarray(model(draw_inputs(pdfs, m, np.random.default_rng(child)))))
    return np.concatenate(out, axis=0)


@dataclass(frozen=True)
class AdaptiveResult:
    """Result of :func:`adaptive_monte_carlo` (JCGM 101, 7.9.4)."""

    summary: McSummary
    batches: int
    batch_trials: int
    converged: bool
    delta: np.ndarray
    two_s: np.ndarray  # 2 x standard deviation of the batch (y, u, low, high), shape (4, ...)


def adaptive_monte_carlo(
    model,
    pdfs,
    *,
    ndig: int = 2,
    p: float = 0.95,
    batch_trials: int | None = None,
    max_trials: int = 10**7,
    seed: int = 0,
) -> AdaptiveResult:
    """Adaptive Monte Carlo procedure of JCGM 101 7.9.4.

    Batches of M = max(J, 10**4) trials (J = 100 / (1 - p), 7.9.4 a) are run until twice the
    standard deviation of the batch estimates of y, u(y), y_low and y_high are all within the
    numerical tolerance delta of u(y) for ``ndig`` significant digits (7.9.2). The final results
    use all h x M values.

    Parameters
    ----------
    model, pdfs, seed
        As :func:`monte_carlo`; batch h draws from child h of ``SeedSequence(seed)``.
    ndig : int
        Significant digits required of u(y).
    p : float
    batch_trials : int, optional
        M; default max(100 / (1 - p), 10**4).
    max_trials : int
        Stop (with ``converged=False``) before exceeding this.

    Returns
    -------
    AdaptiveResult
    """
    m = int(batch_trials or max(int(np.ceil(100 / (1 - p))), 10**4))
    ss = np.random.SeedSequence(seed)
    values, stats = [], []
    while True:
        (child,) = ss.spawn(1)
        v = np.asarray(model(draw_inputs(pdfs, m, np.random.default_rng(child))))
        values.append(v)
        s = summarize(v, p)
        stats.append(np.stack([s.y, s.u, s.low, s.high]))
        h = len(values)
        if h < 2:
            continue
        st = np.array(stats)  # (h, 4, ...)
        two_s = 2.0 * st.std(axis=0, ddof=1) / np.sqrt(h)
        summary = summarize(np.concatenate(values, axis=0), p)
        delta = numerical_tolerance(summary.u, ndig)
        converged = bool(np.all(two_s <= delta))
        if converged or (h + 1) * m > max_trials:
            return AdaptiveResult(summary, h, m, converged, delta, two_s)


def sensitivities_fd(model, x0, steps) -> np.ndarray:
    """Sensitivity coefficients by central differences at ``x0``.

    Parameters
    ----------
    model : callable, vectorised as in :func:`monte_carlo`
    x0 : ndarray, shape (n,)
    steps : ndarray, shape (n,)
        Step per input (a small fraction of its standard uncertainty; zero gives 0).

    Returns
    -------
    ndarray, shape (n,) or (k, n)
    """
    x0 = np.asarray(x0, dtype=np.float64)
    h = np.asarray(steps, dtype=np.float64)
    safe = np.where(h > 0, h, 1.0)
    x = np.vstack([x0 + np.diag(safe), x0 - np.diag(safe)])
    y = np.asarray(model(x))
    n = len(x0)
    c = (y[:n] - y[n:]) / (2.0 * safe.reshape((n,) + (1,) * (y.ndim - 1)))
    c = np.where(np.reshape(h > 0, (n,) + (1,) * (y.ndim - 1)), c, 0.0)
    return np.moveaxis(c, 0, -1)


@dataclass(frozen=True)
class GumResult:
    """The GUM uncertainty framework, first order (GUM 5.1.2, G.4; JCGM 101, 5.6).

    Attributes
    ----------
    y : ndarray
        Estimate: the model at the input estimates.
    u : ndarray
        Combined standard uncertainty u_c(y) = sqrt(sum_i (c_i u_i)**2) (GUM eq. 10).
    sensitivities : ndarray, shape (..., n)
        c_i = df/dx_i at the input estimates.
    contributions : ndarray, shape (..., n)
        (c_i u_i)**2 / u_c**2, summing to 1 (0 where u_c = 0).
    dof : ndarray or float
        Effective degrees of freedom nu_eff of u_c by the Welch-Satterthwaite formula
        (GUM G.4.1, eq. G.2b); ``inf`` when every contributing input has infinite degrees of
        freedom or u_c = 0.
    """

    y: np.ndarray
    u: np.ndarray
    sensitivities: np.ndarray  # (..., n)
    contributions: np.ndarray  # (..., n): (c_i u_i)**2 / u**2, sums to 1
    dof: np.ndarray | float = np.inf

    def coverage_factor(self, p: float = 0.95, dof=None):
        """Coverage factor k_p = t_p(nu) of GUM G.3 and G.4.1.

        Parameters
        ----------
        p : float
            Coverage probability (level of confidence).
        dof : float or ndarray, optional
            Degrees of freedom used as given (``inf``: the normal quantile). By default the
            effective degrees of freedom ``self.dof`` truncated to the next lower integer, as
            the note to GUM G.4.1 says (values below 1 are used unchanged).

        Returns
        -------
        ndarray or float
            The two-sided Student-t quantile t_{(1+p)/2}(nu), or the normal one for nu = inf.
        """
        from scipy import special

        if dof is None:
            nu = np.asarray(self.dof, dtype=np.float64)
            nu = np.where(nu >= 1.0, np.floor(nu), nu)
        else:
            nu = np.asarray(dof, dtype=np.float64)
        q = 0.5 + p / 2
        finite = np.isfinite(nu)
        k = np.where(finite, special.stdtrit(np.where(finite, nu, 1.0), q), special.ndtri(q))
        return k[()] if k.ndim == 0 else k

    def interval(self, p: float = 0.95, dof=None):
        """Coverage interval y -+ k_p u_c (GUM 6.2.1, G.4.1).

        k_p is :meth:`coverage_factor`: by default t_p(floor(nu_eff)), the normal quantile when
        nu_eff is infinite; an explicit ``dof`` is used as given.
        """
        k = self.coverage_factor(p, dof)
        return self.y - k * self.u, self.y + k * self.u


def _input_dof(pdfs, dof) -> np.ndarray:
    """Degrees of freedom of each input's standard uncertainty (see :func:`gum_linear`)."""
    nu = np.array([p.params[2] if p.kind == "student_t" else np.inf for p in pdfs])
    if dof is None:
        return nu
    if isinstance(dof, str) or not hasattr(dof, "__len__") or len(dof) != len(pdfs):
        raise CfmInputError(
            f"gum_linear 'dof' must be a sequence with one entry per input ({len(pdfs)}); "
            f"found {dof!r}"
        )
    for i, (pdf, v) in enumerate(zip(pdfs, dof, strict=True)):
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise CfmInputError(
                f"gum_linear 'dof' of input {i} must be a number or None; found {v!r}"
            )
        if not v > 0:  # also rejects nan
            raise CfmInputError(
                f"gum_linear 'dof' of input {i} must be positive (or inf); found {v!r}"
            )
        if pdf.kind == "student_t" and float(v) != nu[i]:
            raise CfmInputError(
                f"gum_linear 'dof' of input {i} is a Student-t whose degrees of freedom are its "
                f"own dof={nu[i]:g}; found {v!r} (pass None)"
            )
        nu[i] = float(v)
    return nu


def gum_linear(model, pdfs, rel_step: float = 1e-4, dof=None) -> GumResult:
    """The GUM uncertainty framework at the input estimates (first order, no correlations).

    Each input contributes an estimate x_i, a standard uncertainty u_i and degrees of freedom
    nu_i (GUM 4.2, 4.3, G.4.2); u_c is the law of propagation of uncertainty (GUM eq. 10),
    nu_eff the Welch-Satterthwaite formula (GUM G.4.1, eq. G.2b),
    nu_eff = u_c**4 / sum_i (c_i u_i)**4 / nu_i, and ``GumResult.interval`` the coverage factor
    t_p(nu_eff) (GUM G.3, G.4.1).

    Parameters
    ----------
    model : callable, vectorised as in :func:`monte_carlo`
    pdfs : sequence of Pdf
        x_i is ``Pdf.mean``. For ``Pdf.student_t(loc, scale, dof)`` the GUM convention holds:
        u_i = ``scale`` (s/sqrt(n) of a Type A mean) with nu_i = ``dof`` (GUM G.4; JCGM 101 6.4.9
        and 9.5 build their Student-t inputs from these), *not* the standard deviation
        scale * sqrt(nu / (nu - 2)) that the Monte Carlo propagates. Every other PDF gives
        u_i = ``Pdf.std`` and nu_i = inf unless ``dof`` states otherwise.
    rel_step : float
        Central-difference step as a fraction of each standard uncertainty.
    dof : sequence of (float or None), optional
        One entry per input: the degrees of freedom of its standard uncertainty, for Type B
        evaluations whose reliability is stated (GUM G.4.2, nu ~ (1/2) (Delta u / u)**-2;
        JCGM 100 H.1 gives 50 and 2). Positive numbers or ``inf``; None keeps the default
        above. A Student-t input accepts only None or its own dof.

    Returns
    -------
    GumResult
        ``dof`` holds nu_eff (inf when every input with a non-zero contribution has nu_i = inf,
        or u_c = 0).

    Raises
    ------
    CfmInputError
        ``dof`` has the wrong length or an entry that is not positive.
    """
    nu = _input_dof(pdfs, dof)
    x0 = np.array([p.mean for p in pdfs])
    ux = np.array([p.params[1] if p.kind == "student_t" else p.std for p in pdfs])
    y = np.asarray(model(x0[None, :]))[0]
    c = sensitivities_fd(model, x0, rel_step * ux)
    var = (c * ux) ** 2
    tot = var.sum(axis=-1)
    u = np.sqrt(tot)
    share = np.divide(var, tot[..., None], out=np.zeros_like(var), where=tot[..., None] > 0)
    # Welch-Satterthwaite: terms with nu_i = inf or a zero contribution add nothing
    terms = np.divide(var**2, nu, out=np.zeros_like(var), where=(var > 0) & np.isfinite(nu))
    den = terms.sum(axis=-1)
    num = np.asarray(tot**2, dtype=np.float64)
    nu_eff = np.divide(num, den, out=np.full_like(num, np.inf), where=den > 0)
    return GumResult(
        y=y,
        u=u,
        sensitivities=c,
        contributions=share,
        dof=nu_eff[()] if nu_eff.ndim == 0 else nu_eff,
    )


def validate_gum(gum_low, gum_high, mc: McSummary, ndig: int = 2) -> dict:
    """JCGM 101 section 8: does the GUM interval agree with the Monte Carlo one?

    delta is the numerical tolerance of the Monte Carlo u for ``ndig`` significant digits.

    Returns
    -------
    dict
        ``d_low``, ``d_high`` = |gum_low - mc.low|, |gum_high - mc.high|; ``delta``; ``valid``.
    """
    delta = numerical_tolerance(mc.u, ndig)
    y = 0.5 * (np.asarray(gum_low) + np.asarray(gum_high))
    half = 0.5 * (np.asarray(gum_high) - np.asarray(gum_low))
    d_low, d_high, ok = gum_validation(y, half, mc.low, mc.high, delta)
    return {"d_low": d_low, "d_high": d_high, "delta": delta, "valid": ok}


def variance_shares(sens, stds) -> np.ndarray:
    """Linearised variance budget: (c_k u_k)**2 / sum_j (c_j u_j)**2 along the last axis."""
    v = (np.asarray(sens) * np.asarray(stds)) ** 2
    tot = v.sum(axis=-1, keepdims=True)
    return np.divide(v, tot, out=np.zeros_like(v), where=tot > 0)


def ppf_numpy(code: int, par, u):
    """Inverse CDF of the kernel PDFs (plain-numpy twin of ``_kernels.pdf_ppf``).

    Parameters
    ----------
    code : int
        One of ``KERNEL_PDF_CODES``.
    par : ndarray, shape (4,)
        Parameters as in ``PDF_PARAMETERS``, zero padded.
    u : ndarray
        Uniforms in (0, 1).
    """
    from scipy import special

    u = np.asarray(u, dtype=np.float64)
    p0, p1, p2 = float(par[0]), float(par[1]), float(par[2])
    if code == 0:
        return np.full_like(u, p0)
    if code == 1:
        return p0 + (p1 - p0) * u
    if code == 2:
        return p0 + p1 * special.ndtri(u)
    if code == 3:
        a, c, b = p0, p1, p2
        fc = (c - a) / (b - a)
        left = a + np.sqrt(u * (b - a) * (c - a))
        right = b - np.sqrt((1.0 - u) * (b - a) * (b - c))
        return np.where(u < fc, left, right)
    if code == 4:
        s = np.sin(0.5 * np.pi * u)
        return p0 + (p1 - p0) * s * s
    if code == 5:
        a, b, beta = p0, p1, p2
        ramp = 0.5 * (b - a) * (1.0 - beta)  # length of each sloping side
        h = 1.0 / (b - a - ramp)  # height of the top
        f1 = 0.5 * h * ramp  # probability under one ramp
        with np.errstate(divide="ignore", invalid="ignore"):
            lo = a + np.sqrt(2.0 * ramp * u / h)
            hi = b - np.sqrt(2.0 * ramp * (1.0 - u) / h)
        mid = a + ramp + (u - f1) / h
        return np.where(u < f1, lo, np.where(u > 1.0 - f1, hi, mid))
    raise ValueError(f"unknown pdf code {code}")
