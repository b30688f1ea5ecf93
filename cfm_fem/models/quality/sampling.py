"""The field a probe reads at displaced scan points, from the model between a map's nodes.

A reading at the scan point p displaced by e is

    B(p + e) = B_nom(p) + [M(p + e) - M(p)]

with ``B_nom`` the nominal value of the scan point (the node's own value when the scan points
are nodes, the model's value on circles) and ``M`` the model between nodes, so a zero
displacement reads exactly the nominal value. With the local harmonic model
(`cfm_fem.models.harmonic`), ``M`` near p is the model of the usable node nearest to p, the
same for every displacement of that point: it is smooth in e (no switch of node inside a
trial's displacement), and a displacement beyond that node's reach is outside the model. With
the linear interpolant ``M`` is evaluated wherever p + e lands.
"""

from __future__ import annotations

import numpy as np

from ... import _kernels
from ...errors import CfmInputError
from ...threads import map_blocks
from ..harmonic import HarmonicFit, neighbourhoods
from ..harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents

__all__ = ["LocalField"]

_EVAL_BLOCK = 65536  # points per call of the evaluation kernel on a thread


class LocalField:
    """Readings of the model between nodes at displaced scan points.

    Parameters
    ----------
    model : object
        Anything with ``field_at(points) -> (B, inside)``; a `HarmonicFit` is evaluated node by
        node as the module docstring says.
    points : ndarray, shape (n, 3), mm
        Scan points.
    B_nominal : ndarray, shape (n, 3), T, optional
        Nominal readings; default the model's field at ``points``.

    Raises
    ------
    CfmInputError
        A scan point outside the model.
    """

    def __init__(self, model, points, B_nominal=None):
        self.model = model
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if isinstance(model, HarmonicFit):
            self._prepare_harmonic(model)
        m0, inside = self._model(np.zeros((1,) + self.points.shape))
        if not inside.all():
            i = int(np.argmax(~inside[0]))
            raise CfmInputError(
                f"scan point {self.points[i].round(6).tolist()} mm is outside the field "
                f"model of the map ({_model_name(model)}); choose a smaller --radius or z range"
            )
        self.model_at_points = m0[0]
        self.B_nominal = self.model_at_points if B_nominal is None else np.asarray(B_nominal)

    def _prepare_harmonic(self, fit: HarmonicFit) -> None:
        idx, used, tree = fit._used
        if idx.size == 0:
            raise CfmInputError("no node of the map has a usable harmonic model")
        near, _ = neighbourhoods(tree, used, self.points, 1)
        g = idx[near[:, 0]]
        nodes, inv = np.unique(g, return_inverse=True)
        gmat = field_basis(MAX_DEGREE)
        self._cexp = np.ascontiguousarray(np.einsum("cmj,nj->ncm", gmat, fit.coef[nodes]))
        self._which = inv.astype(np.int64)
        self._centre = fit.centers[g]
        self._scale = fit.scale[g]
        self._reach = fit.reach_mm[g]
        self._exps = monomial_exponents(MAX_DEGREE)

    def _model(self, disp):
        """Model field at points + disp, disp (m, n, 3) mm: (B (m, n, 3) T, inside (m, n))."""
        m, n = disp.shape[0], disp.shape[1]
        if not isinstance(self.model, HarmonicFit):
            b, inside = self.model.field_at((self.points[None] + disp).reshape(-1, 3))
            return b.reshape(m, n, 3), inside.reshape(m, n)
        rel = self.points[None] - self._centre[None] + disp  # (m, n, 3)
        inside = np.sqrt((rel**2).sum(-1)) <= self._reach[None]
        u = np.ascontiguousarray((rel / self._scale[None, :, None]).reshape(-1, 3))
        which = np.tile(self._which, m)

        def block(i0, i1):  # points are independent: any split gives the same numbers
            out = np.empty((i1 - i0, 3))
            _kernels.poly_points(self._cexp, which[i0:i1], self._exps, u[i0:i1], out)
            return (out,)

        (out,) = map_blocks(block, m * n, _EVAL_BLOCK)
        return out.reshape(m, n, 3), inside

    def read(self, disp) -> tuple[np.ndarray, np.ndarray]:
        """Readings at the displaced scan points.

        Parameters
        ----------
        disp : ndarray, shape (m, n, 3), mm
            Displacement of every scan point in each of m trials (magnet frame).

        Returns
        -------
        B : ndarray, shape (m, n, 3), T
            NaN where ``inside`` is False.
        inside : ndarray, shape (m, n), bool
        """
        b, inside = self._model(np.asarray(disp, dtype=np.float64))
        b = b - self.model_at_points[None] + self.B_nominal[None]
        b[~inside] = np.nan
        return b, inside


def _model_name(model) -> str:
    """The ``--field-model`` of ``model`` and how far it reaches, for messages."""
    if isinstance(model, HarmonicFit):
        return "--field-model harmonic: each node's fit, within its reach"
    return "--field-model linear: the interpolant ends at the nodes' hull"
