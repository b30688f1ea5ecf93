"""The catalogue of physical effects: each a small parametric model, linear in its parameters.

Every builder takes a :class:`~cfm_fem.workflows.diagnose.problem.Problem` and returns
either a :class:`~cfm_fem.workflows.diagnose.calibrate.Columns` block (change of the residual
per unit of each physical parameter) or a string saying why the recording cannot test it
(which is then turned into advice). The names are those of ``effects[].name`` in
``diagnosis.json``: keep their spelling.

Positioning (tracker), displacement of the probe in the bench frame:

* ``thermal_drift``: screw/frame expansion growing with time (or temperature when logged):
  E_a += tau (d_a + s_a q_a), d in um/h (um/K), s in ppm/h (ppm/K); each axis's offset drift,
  scale drift, or both, is a function of its own.
* ``reversal``: backlash, E_a += b_a dir_a / 2 (b = full hysteresis width, um).
* ``reading_delay``: position read late in on-the-fly scans, E_a += tau_ms 1e-3 v_a, v_a the
  signed velocity of axis a at acquisition (recorded, or inferred from the scan: only the
  moving axes carry it).
* ``position_dependent_geometric``: the 18 axis errors with linear and quadratic profiles in
  the normalised axis position, through the HTM chain (um or urad at full stroke). Each error
  function (``eps_z(z)``: its linear term ``_u1``, or ``_u1`` and the quadratic ``_u2``
  together) is tested on its own, the choice among the 36 alternatives accounted for, so one
  identifiable function is found and named by itself. A linear term reported without its
  quadratic term is model-dependent (the straight line the selection chose through the
  error over the scanned part of the stroke: a curved error has another linear coefficient).
* ``arm_deflection``: load-dependent sag of the probe: E_y -= c_x s(u_x) + c_z s(u_z),
  s(u) = 16 u^2 (1 - u)^2 (moving load on a beam; c in um at mid-stroke); each carriage's
  sag is a function of its own.
* ``parameter_bias``: the 21 errors free of their Table II PDFs (prior release).
* ``step_event`` (also for Hall maps): an abrupt shift from a change point in time or
  repetition on, per axis or component (:mod:`cfm_fem.workflows.diagnose.step_event`).

Field (Hall map), change of the measured field in the magnet frame. B below is the field
the probe senses: the reference read where the fitted bench errors move the probe
(``ctx.B_read``), not at the nominal point.

* ``probe_misalignment``: Delta B_i = sum_{j != i} m_ij B_j (6 angles, mrad). Element i reads
  the field it senses, mixing included, times (1 + gain_i): the columns fit m_ij (1 + gain_i),
  and m_ij is reported divided by the fitted gain (:attr:`Columns.element`; so is k_i of
  ``planar_hall``).
* ``sensor_offset``: Hall elements not co-located: Delta B_i = sum_j dB_i/dx_j d_ij (um), d_ij
  the displacement of element i along j from the elements' centroid (sum_i d_ij = 0: a shift
  common to all three moves the readings as the magnet's offset does). Each element displaced
  from the other two along one direction (``e_<i>_<j>``) is a function of its own; two
  elements along one direction, or one element along two, are tested as pairs. The effect is
  tested with the centroid left to the registration; its offsets are reported fitted with the
  centroid's shift free (the survey's prior on the magnet does not bound where the elements
  sit in the probe), their uncertainty marginalised over it. Where the field curves over the
  offsets, G is taken at each element's own point: the problem is linearised at the offsets
  the selected model fits (:mod:`~cfm_fem.workflows.diagnose.elements`).
* ``magnet_misalignment``: magnet offset and roll beyond the survey (registration released).
* ``planar_hall``: Delta B_i = k_i B_j B_k (1/T), j, k the in-plane components; each
  element's k_i is a function of its own.
* ``hall_offset_gain``: Delta B_i = o_i + g_i B_i (offset uT, gain %); each element's offset
  is a function of its own.
* ``magnet_temperature``: Delta B = beta (T - T_mean) B (ppm/K; ppm/h against time without a
  temperature log).
* ``fringe_field_3d`` (:mod:`~cfm_fem.workflows.diagnose.fringe`): soft magnet ends that a
  2-D multipole lacks. The field of a body multipole whose amplitude g(z) varies along z is
  the gradient of the 3-D potential sum_k (-1)^k g^(2k)(z) U_k (U_0 = V the potential of the
  2-D field, lap_perp U_k = U_(k-1)). The ends are located with an Enge/Fermi profile (edges
  z_entry, z_exit, fringe length lambda, mm): a search against the calibrated baseline, then
  Gauss-Newton on the joint model, in which the baseline acts on the 3-D field
  (``Columns.replaces``): the bench errors and the magnet offsets and rotations move the
  probe through its full gradient (a z error, invisible in the 2-D reference, moves it
  through the steep fringe gradient; an offset of the magnet shows as a dipole term at the
  ends), the gains scale it, the vibration is seen through it. Near each end the data cover,
  every z plane then gets its own profile values g, g', g'', ... (the generalised gradients
  on the axis), so the fit there does not rest on the Fermi shape. Reported: g, g', g'' per
  plane, model-independent where the plane's points separate every layer of the potential;
  the Fermi z_entry, z_exit and lambda fitted to those values, as a model-dependent summary
  whose std includes its spread over the planes (a real end is not that shape). Edges and
  planes are in the map frame (they carry the magnet's z offset). An end more than 10 lambda
  outside the map is not estimated. The baseline's columns there are read through the
  measured profile, and elsewhere through the Fermi profile with its amplitude within [0, 2]
  (beyond the measured planes, far from the ends, that amplitude is not determined). Once
  the ends are accepted, the end model's misfit where it carries the signal is stated as a
  model error added to the noise there
  (:func:`~cfm_fem.workflows.diagnose.select.approximation_error`), which a further claim
  must exceed; against 2-D harmonics the pose then stays where the baseline placed it.
* ``sensor_volume_averaging``: Delta B_i = sum_j w_j d^2 B_i / dx_j^2 (w = a_j^2 / 24 for a
  box of side a_j). A field in free space is harmonic (sum_j d^2 B / dx_j^2 = 0), so the
  isotropic part of w never shows (mean-value property: a cube averages to its centre value at
  this order); the parameters are the anisotropy dw_xy = w_x - w_y and
  dw_z = w_z - (w_x + w_y) / 2, in 1e-3 mm^2. A 2-D reference has no z curvature: only dw_xy.
  A field linear in position (pure quadrupole) has no curvature: untestable, said so. Against
  a map interpolated linearly, only when the readings lie on its nodes (second differences of
  node values, step the node spacing); between nodes the map has no curvature to use. A map
  read between its nodes errs by a curvature term of the same shape, coherent across a plane
  where the field curves: the block carries the map's stated error (``ref_error``), and the
  selection credits averaging only with what an error of that size cannot explain.

Three effects are prior releases: ``parameter_bias`` (bench errors), ``magnet_misalignment``
(magnet registration) and the gains of ``hall_offset_gain`` re-use baseline columns; their
evidence is the conflict between the data and the stated prior, tested per parameter.

Every effect states its physically plausible parameter range (:data:`PLAUSIBLE`, display units):
a fit that needs a value beyond it (by more than 3 standard uncertainties) is reported as an
implausible fit with the reason, never as found.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...models.bench import ERROR_NAMES
from ...models.kinematics.chain import probe_errors_for_bench
from .elements import ELEMENT_SHARE, element_map
from .fringe import fringe_field_3d
from .priors import PLAUSIBLE, bounds_for, effect_columns
from .problem import REG_NAMES, UM, URAD, field_hessian, field_hessian_diag
from .step_event import step_event

__all__ = [
    "EFFECTS",
    "POSITIONING",
    "FIELD",
    "build",
    "ADVICE",
    "DESCRIPTION",
    "PLAUSIBLE",
    "averaging_params",
]

W_MAX_MM2 = 25.0 / 24.0  # a^2/24 of a 5 mm sensitive volume, mm^2


def _release(prob, groups, effect, names=None, J=None, new_names=(), new_units=()):
    """An effect that releases the priors of baseline parameters (of blocks ``groups``),
    optionally with new columns ``J`` (n, 3, k)."""
    rel = [
        nm
        for b in prob.baseline
        if b.group in groups
        for nm in b.names
        if names is None or nm in names
    ]
    if not rel:
        return None
    J = np.zeros((prob.n, 3, 0)) if J is None else J
    blk = effect_columns(J, list(new_names), list(new_units), effect)
    blk.release = tuple(rel)
    blk.release_bounds = bounds_for(effect, rel)[0]
    return blk


#: Highest degree of the polynomial in time that a logged temperature is smoothed with.
TEMP_MAX_DEGREE = 6


def _each_alone(names) -> list:
    """``families`` of an effect whose every parameter is a function of its own:
    [(name, [index])] in column order."""
    return [(nm, [k]) for k, nm in enumerate(names)]


def smooth_temperature(t_h, temp) -> np.ndarray:
    """A logged temperature smoothed in time (K, shape (n,)).

    A magnet's or a frame's temperature follows the hall's slowly (a thermal time constant of
    many minutes), while the logging sensor adds its own noise to every reading; over a short
    map the true change may be smaller than that noise, and a regression on the raw log then
    takes the sensor's noise for the magnet's temperature and loses the effect (errors in the
    variable). The log is fitted with a Legendre polynomial in time whose degree (at most
    :data:`TEMP_MAX_DEGREE`) the Bayesian information criterion chooses; readings at one time
    share its value.

    Parameters
    ----------
    t_h : ndarray, shape (n,), h
    temp : ndarray, shape (n,), K (or degC)

    Returns
    -------
    ndarray, shape (n,)
    """
    t = np.asarray(t_h, dtype=float)
    y = np.asarray(temp, dtype=float)
    span = np.ptp(t)
    if span <= 0 or y.size < 3:
        return y
    u = 2.0 * (t - t.min()) / span - 1.0
    best, fitted = np.inf, y
    for deg in range(min(TEMP_MAX_DEGREE, np.unique(t).size - 1) + 1):
        V = np.polynomial.legendre.legvander(u, deg)
        coef = np.linalg.lstsq(V, y, rcond=None)[0]
        rss = float(((y - V @ coef) ** 2).sum())
        bic = y.size * np.log(max(rss, 1e-300) / y.size) + (deg + 1) * np.log(y.size)
        if bic < best:
            best, fitted = bic, V @ coef
    return fitted


def _time_var(prob):
    """Temperature change since the first acquisition (K; the log smoothed in time when the
    times are known, :func:`smooth_temperature`) or time since start (h)."""
    if prob.temp is not None and np.ptp(prob.temp) > 0:
        first = np.argmin(prob.t_h) if prob.t_h is not None else 0
        temp = prob.temp if prob.t_h is None else smooth_temperature(prob.t_h, prob.temp)
        return temp - temp[first], "K"
    if prob.t_h is not None and np.ptp(prob.t_h) > 0:
        return prob.t_h, "h"
    return None, None


# ------------------------------------------------------------------ positioning


def thermal_drift(prob):
    tau, u = _time_var(prob)
    if tau is None:
        return "no time or temperature column (t_s, temp_C): drift cannot be told from noise"
    n = prob.n
    J = np.zeros((n, 3, 6))
    q = prob.q - prob.q.mean(0)
    for a in range(3):
        J[:, a, a] = tau * UM
        J[:, a, 3 + a] = tau * q[:, a] * 1e-6
    names = [f"drift_{a}" for a in "xyz"] + [f"scale_drift_{a}" for a in "xyz"]
    blk = effect_columns(J, names, [f"um/{u}"] * 3 + [f"ppm/{u}"] * 3, "thermal_drift")
    # per axis: its offset drift, its scale drift, or both; one axis at a time, the choice
    # among the nine accounted for (a drift of one axis must not pay for six parameters)
    blk.families = (
        [(f"drift_{a}", [i]) for i, a in enumerate("xyz")]
        + [(f"scale_drift_{a}", [3 + i]) for i, a in enumerate("xyz")]
        + [(f"drift_{a}+scale_drift_{a}", [i, 3 + i]) for i, a in enumerate("xyz")]
    )
    return blk


def reversal(prob):
    if prob.dir is None:
        return "no dir_x/dir_y/dir_z columns: backlash needs the approach direction"
    d = prob.dir
    ok = [a for a in range(3) if np.any(d[:, a] > 0) and np.any(d[:, a] < 0)]
    if not ok:
        return "every axis approached from one side only: backlash is a constant offset"
    J = np.zeros((prob.n, 3, len(ok)))
    for k, a in enumerate(ok):
        J[:, a, k] = 0.5 * d[:, a] * UM
    names = [f"backlash_{'xyz'[a]}" for a in ok]
    blk = effect_columns(J, names, ["um"] * len(ok), "reversal")
    # one axis's backlash at a time, the choice among the axes accounted for: the backlash of
    # one axis must not pay for three parameters; the others join round by round
    blk.families = _each_alone(names)
    return blk


def reading_delay(prob):
    if prob.vel is None or not np.any(prob.vel != 0):
        return (
            "no on-the-fly acquisition (speed or v_x, v_y, v_z columns): a delay has no signature"
        )
    J = np.zeros((prob.n, 3, 1))
    J[:, :, 0] = prob.vel * 1e-3  # tau in ms -> mm
    return effect_columns(J, ["tau"], ["ms"], "reading_delay")


def position_dependent_geometric(prob):
    bench = prob.ctx.bench
    q = prob.q
    upts, inv = np.unique(np.round(q, 9), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    idx = [k for k, n in enumerate(ERROR_NAMES) if not n.startswith("alpha")]
    cols, names, units = [], [], []
    for order in (1, 2):
        prof = np.zeros((21, order + 1))
        prof[:, order] = 1.0
        errs = tuple(
            replace(e, profile=tuple(prof[k])) if k in idx else e
            for k, e in enumerate(bench.errors)
        )
        b2 = replace(bench, errors=errs)
        unit = np.array([URAD if ERROR_NAMES[k].startswith("eps") else UM for k in idx])
        params = np.zeros((2 * len(idx), 21))
        for i, k in enumerate(idx):
            params[i, k] = unit[i]
            params[len(idx) + i, k] = -unit[i]
        e = probe_errors_for_bench(b2, params, upts)  # (2m, npts, 3)
        d = (e[: len(idx)] - e[len(idx) :]) / 2.0  # per display unit
        cols.append(np.moveaxis(d, 0, -1)[inv])
        names += [f"{ERROR_NAMES[k]}_u{order}" for k in idx]
        units += ["urad" if u == URAD else "um" for u in unit]
    J = np.concatenate(cols, axis=-1)
    blk = effect_columns(J, names, units, "position_dependent_geometric")
    m = len(idx)
    # per error function: its linear term alone, or linear and quadratic together
    blk.families = [(ERROR_NAMES[k], [i]) for i, k in enumerate(idx)] + [
        (ERROR_NAMES[k], [i, m + i]) for i, k in enumerate(idx)
    ]
    # a linear term fitted alone is the slope of the order chosen, not the function's own
    blk.lower_order = {names[i]: names[m + i] for i in range(m)}
    return blk


def _sag(u):
    return 16.0 * u**2 * (1.0 - u) ** 2


def arm_deflection(prob):
    bench = prob.ctx.bench
    u = prob.q / bench.strokes_mm
    J = np.zeros((prob.n, 3, 2))
    J[:, 1, 0] = -_sag(u[:, 0]) * UM
    J[:, 1, 1] = -_sag(u[:, 2]) * UM
    blk = effect_columns(J, ["sag_x", "sag_z"], ["um", "um"], "arm_deflection")
    # each carriage's sag is a function of its own, the choice between the two accounted for:
    # a sag along one stroke must not pay for both (a quadratic error function of that axis,
    # one parameter, would otherwise take its place)
    blk.families = [("sag_x", [0]), ("sag_z", [1])]
    return blk


def parameter_bias(prob):
    if not any(b.group == "bench" for b in prob.baseline):
        return "no bench model"
    return _release(prob, ("bench",), "parameter_bias")


# ------------------------------------------------------------------ field


def _sensed(prob) -> np.ndarray:
    """The field the probe senses at each reading (T, shape (n, 3)): the reference read where
    the fitted bench errors move the probe (``ctx.B_read``), else at the nominal point.

    An effect of the probe acts on the field it senses: a planar Hall term on the product of
    two components, a mixing or a temperature scale on the components themselves. The bench
    moves the probe by tens of um; where the field varies on the scale of the scan radius (a
    multipole of high order read close to its axis) that move changes the field by several
    per cent, and the columns at the nominal point would miss the effect's size by as much.
    """
    B = getattr(prob.ctx, "B_read", None)
    return prob.ctx.B0 if B is None else B


def probe_misalignment(prob):
    B = _sensed(prob)
    J = np.zeros((prob.n, 3, 6))
    names = []
    k = 0
    for i in range(3):
        for j in range(3):
            if i != j:
                J[:, i, k] = B[:, j] * 1e-3
                names.append(f"m_{'xyz'[i]}{'xyz'[j]}")
                k += 1
    blk = effect_columns(J, names, ["mrad"] * 6, "probe_misalignment")
    blk.element = (0, 0, 1, 1, 2, 2)
    # one element's tilt towards one axis at a time, the choice among the six accounted for:
    # an element tilted along one direction must not pay for six parameters; tilts of other
    # elements or directions join round by round
    blk.families = _each_alone(names)
    return blk


def sensor_offset(prob):
    """Hall elements displaced relative to one another.

    One column per element and direction: element i displaced by e along j from the other
    two (the elements' centroid held: offsets 2e/3 for element i, -e/3 for the others, so
    the three columns of a direction sum to zero). Each is a function of its own, one
    parameter: one element off the others along one direction is the usual fault of a
    three-element probe (elements on separate dies) and must not pay for the two parameters
    of a general offset. Two elements along one direction span every relative offset along
    it (the third then holds the reference: e_i is element i's offset from it): one such pair
    per direction is tested, beside every pair of two directions (one element displaced
    obliquely, or two elements each along its own direction), :attr:`Columns.pairs`; further
    offsets join round by round.

    The centroid's own shift moves the readings as the magnet's offset does, so the test of
    the effect leaves it to the registration; but the magnet's survey says nothing about
    where the elements sit in the probe: held by that prior, the common shift of elements
    placed unevenly (one element a millimetre off) would leak into the relative offsets
    through their gradient-weighted columns, biased by many standard uncertainties. The
    reported offsets are fitted with the centroid's shift free (:attr:`Columns.nuisance`),
    their uncertainty marginalised over it, and stated per element from the centroid
    (:func:`_element_offsets`).

    The gradient is ``ctx.G``: each element's row at the element's own point when the problem
    is linearised at the elements' offsets (``ctx.elements_at``, whose linear term the
    residual then carries), so that the fitted offsets are the whole offsets.
    """
    G = prob.ctx.G
    J = np.zeros((prob.n, 3, 9))
    names, families = [], []
    for j, a in enumerate("xyz"):
        for i, e in enumerate("xyz"):
            J[:, :, 3 * j + i] = G[:, :, j] * ELEMENT_SHARE[i] * UM
            names.append(f"e_{e}_{a}")
            families.append((f"{e}_along_{a}", [3 * j + i]))
    blk = effect_columns(J, names, ["um"] * 9, "sensor_offset")
    blk.families = families
    blk.pairs = [(f"along_{a}", f"{p}_along_{a}", f"{q}_along_{a}")
                 for a in "xyz" for p, q in ("xy", "xz", "yz")]  # fmt: skip
    blk.pairs += [(f"{e}_along_{a}+{f}_along_{b}", f"{e}_along_{a}", f"{f}_along_{b}")
                  for a, b in ("xy", "xz", "yz") for e in "xyz" for f in "xyz"]  # fmt: skip
    # the centroid: every element moved along j
    Jc = G * UM
    centroid = [f"centroid_{a}" for a in "xyz"]
    blk.nuisance = effect_columns(Jc, centroid, ["um"] * 3, "sensor_offset")
    # with the centroid free, the magnet's offsets are no test of the survey's prior
    blk.nuisance.release = REG_NAMES[:3]
    blk.physical = _element_offsets
    return blk


def _element_offsets(names, theta, cov):
    """All three elements' offsets from their centroid (um) along each direction some element
    is fitted along, from the fitted displacements, uncertainty propagated."""
    names = list(names)
    theta = np.asarray(theta, dtype=float)
    out = {}
    for j in "xyz":
        A = element_map(names, j)
        if not A.any():
            continue
        d, C = A @ theta, A @ cov @ A.T
        for i, e in enumerate("xyz"):
            out[f"d_{e}_{j}"] = (float(d[i]), float(np.sqrt(max(C[i, i], 0.0))), "um")
    return out


def magnet_misalignment(prob):
    return _release(prob, ("registration",), "magnet_misalignment")


def planar_hall(prob):
    B = _sensed(prob)
    J = np.zeros((prob.n, 3, 3))
    for i in range(3):
        j, k = [c for c in range(3) if c != i]
        J[:, i, i] = B[:, j] * B[:, k]
    blk = effect_columns(J, [f"k_{a}" for a in "xyz"], ["1/T"] * 3, "planar_hall")
    blk.element = (0, 1, 2)
    # each element's planar term is a function of its own (a plate's own coefficient), the
    # choice among the three accounted for: a term of one element must not pay for three
    blk.families = [(f"k_{a}", [i]) for i, a in enumerate("xyz")]
    return blk


def hall_offset_gain(prob):
    # offsets are new columns; the gains are the baseline's S_HP gains with their prior released
    J = np.zeros((prob.n, 3, 3))
    for i in range(3):
        J[:, i, i] = 1e-6
    names = [f"offset_{a}" for a in "xyz"]
    blk = _release(prob, ("probe",), "hall_offset_gain", None, J, names, ["uT"] * 3)
    # one element's offset at a time, the choice among the three accounted for: an offset of
    # one element must not pay for three parameters (a step of that element from the first
    # repetitions on, one parameter, would otherwise take its place)
    blk.families = _each_alone(names)
    return blk


def magnet_temperature(prob):
    tau, u = _time_var(prob)
    if tau is None:
        return (
            "no temperature log (temp_C) nor time (t_s): a magnet temperature change is a "
            "uniform scale, the same as a common Hall gain"
        )
    B = _sensed(prob)
    J = (B * 1e-6 * tau[:, None])[..., None]
    return effect_columns(J, ["beta"], [f"ppm/{u}"], "magnet_temperature")


def sensor_volume_averaging(prob):
    ctx = prob.ctx
    step = ctx.node_step
    if not ctx.smooth and step is None:
        return (
            "the reference map is piecewise linear and the readings lie between its nodes: no "
            "second derivatives to average"
        )
    if ctx.H is None:
        if step is not None:  # readings on a map's nodes: second differences of node values
            H = np.einsum("nijj->nij", field_hessian(ctx.reference_fn, ctx.upts, step))
        else:
            H = field_hessian_diag(ctx.field_fn, ctx.upts, 1.0)
        ctx.H = H[ctx.uinv]
    H = ctx.H  # (n, 3 comps, 3 dirs) T/mm^2
    # largest change the plausible sensitive volume (5 mm side, w = 1.04 mm^2) could make
    if np.max(np.abs(H)) * W_MAX_MM2 < 1e-7 * ctx.b_ref:
        return (
            "the reference field has no curvature at the mapped points (d2B/dx^2 = 0, as in a "
            "pure quadrupole): averaging over the sensitive volume leaves a field linear in "
            "position unchanged, whatever the size of the volume"
        )
    # traceless part only: sum_j d2B/dx_j^2 = 0 (Laplace), the isotropic part of w is invisible
    J = np.stack(
        [0.5 * (H[..., 0] - H[..., 1]), (2 * H[..., 2] - H[..., 0] - H[..., 1]) / 3.0], axis=-1
    )
    blk = effect_columns(J * 1e-3, ["dw_xy", "dw_z"], ["1e-3 mm^2"] * 2, "sensor_volume_averaging")
    blk.ref_error = _reference_error_std(ctx)
    return blk


def _reference_error_std(ctx):
    """The reference's stated error at the readings' points, for the averaging test.

    A reference read between its nodes errs by a curvature term shaped by its cells, one
    sign across a plane of readings where the field curves (the ends): the shape of volume
    averaging. The selection does not credit averaging with what an error of this size could
    produce (:func:`~cfm_fem.workflows.diagnose.select.reference_explains`).

    Returns
    -------
    tuple (std, key) or None
        ``std`` (m, 3) T: the stated standard deviation of the reference's error at the
        distinct points ``ctx.upts``; ``key`` (n,): the distinct point of each row. None: no
        error stated (a 2-D field, exact everywhere, or a map read on its nodes).
    """
    error_var = getattr(ctx.reference_fn, "error_var", None)
    if error_var is None or ctx.upts is None or ctx.uinv is None:
        return None
    std = np.sqrt(np.maximum(np.asarray(error_var(ctx.upts), dtype=float), 0.0))
    if not np.any(std > 0):
        return None
    return std, np.asarray(ctx.uinv)


def averaging_params(a_mm) -> dict:
    """Catalogue parameters (1e-3 mm^2) of a box of sides ``a_mm`` = (a_x, a_y, a_z) mm."""
    w = np.asarray(a_mm, float) ** 2 / 24.0 * 1e3
    return {"dw_xy": float(w[0] - w[1]), "dw_z": float(w[2] - 0.5 * (w[0] + w[1]))}


POSITIONING = {
    "thermal_drift": thermal_drift,
    "reversal": reversal,
    "reading_delay": reading_delay,
    "position_dependent_geometric": position_dependent_geometric,
    "arm_deflection": arm_deflection,
    "parameter_bias": parameter_bias,
    "step_event": step_event,
}
FIELD = {
    "probe_misalignment": probe_misalignment,
    "sensor_offset": sensor_offset,
    "magnet_misalignment": magnet_misalignment,
    "planar_hall": planar_hall,
    "hall_offset_gain": hall_offset_gain,
    "magnet_temperature": magnet_temperature,
    "fringe_field_3d": fringe_field_3d,
    "sensor_volume_averaging": sensor_volume_averaging,
    "step_event": step_event,
}
EFFECTS = {**POSITIONING, **FIELD}

#: Effects whose model is (also) a released prior of baseline parameters.
PRIOR_RELEASE = {"parameter_bias", "magnet_misalignment", "hall_offset_gain"}

#: The measurement that reveals or separates each effect.
ADVICE = {
    "thermal_drift": "log the time (t_s) and the temperature (temp_C) of every acquisition, "
    "and repeat a reference point through the run",
    "reversal": "approach every point from both directions (dir_x, dir_y, dir_z columns)",
    "reading_delay": "scan on the fly at a second speed (or stop-and-go): a delay scales with "
    "speed, backlash does not",
    "position_dependent_geometric": "measure straightness and angular errors along each axis "
    "(laser interferometer/autocollimator, ISO 230-1) over the full stroke",
    "arm_deflection": "repeat the map with an added mass on the arm: a deflection scales with "
    "the load, a geometric error does not",
    "parameter_bias": "re-measure the stages (metrology report) whose fitted errors leave their "
    "PDFs",
    "probe_misalignment": "rotate the probe by 180 deg about its axis (probe flip) in a known "
    "field, or calibrate it in a uniform dipole field at several orientations",
    "sensor_offset": "measure a known gradient field twice with the probe flipped: element "
    "offsets change sign",
    "magnet_misalignment": "survey the magnet fiducials with the laser tracker",
    "planar_hall": "calibrate the probe in a rotating uniform field (planar Hall terms are "
    "quadratic in the in-plane field)",
    "hall_offset_gain": "zero the probe in a zero-gauss chamber and calibrate in a reference "
    "dipole (NMR)",
    "magnet_temperature": "log the magnet temperature (temp_C) during the map",
    "fringe_field_3d": "use a 3-D reference (FEM map) near the magnet ends, or map the ends "
    "separately",
    "sensor_volume_averaging": "map where the field curvature is large (near the magnet ends, "
    "or at a larger radius where the higher harmonics dominate), or repeat with a probe of a "
    "different sensitive volume",
    "step_event": "log the time (t_s) of every acquisition and repeat a reference point through "
    "the run; check the bench log for a collision, a re-homing or a loose fixture at the change "
    "point",
}

DESCRIPTION = {
    "thermal_drift": "time- or temperature-dependent offsets and scale of the axes",
    "reversal": "backlash: error depends on the approach direction",
    "reading_delay": "position read late during on-the-fly motion (speed x delay)",
    "position_dependent_geometric": "axis errors that vary along the stroke (profiles in u, u^2)",
    "arm_deflection": "load-dependent sag of the probe as the carriages move",
    "parameter_bias": "the bench errors are outside their stated (Table II) PDFs",
    "probe_misalignment": "the Hall elements are not along the magnet axes (component mixing)",
    "sensor_offset": "the three Hall elements are not co-located (component-specific shifts)",
    "magnet_misalignment": "magnet offset/roll beyond the survey (feed-down, normal/skew mix)",
    "planar_hall": "planar Hall effect: quadratic in the in-plane field",
    "hall_offset_gain": "Hall offsets and gains off their calibration",
    "magnet_temperature": "field scale following temperature (or time)",
    "fringe_field_3d": "z-dependence near magnet ends absent from a 2-D model",
    "sensor_volume_averaging": "field averaged over the sensitive volume (curvature terms)",
    "step_event": "an abrupt shift from one moment on (a slip, a knock, a re-homing)",
}


def build(prob, names=None) -> tuple[dict, dict]:
    """Build the candidate blocks applicable to ``prob``.

    Returns
    -------
    blocks : dict name -> Columns
    untestable : dict name -> reason
    """
    table = POSITIONING if prob.kind == "tracker" else FIELD
    blocks, untestable = {}, {}
    for name, fn in table.items():
        if names is not None and name not in names:
            continue
        out = fn(prob)
        if isinstance(out, str):
            untestable[name] = out
        elif out is not None:
            blocks[name] = out
    return blocks, untestable
