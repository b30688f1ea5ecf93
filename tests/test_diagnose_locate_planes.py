"""The isolated-plane test of the diagnosis: its false-alarm rate on clean maps is bounded.

A clean map's standardised residuals are white noise; the test flags a plane only when, in
one family over every plane, axis and component, both its departure from its neighbours and
its own mean are significant at family-wise level q (Holm). Over many clean maps the fraction
with any plane flagged must stay near q, also when the noise model is a little too small
(every residual wider than stated), and a real bad plane must still be found.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy import stats

from cfm_fem.workflows.diagnose.locate import isolated_planes

Q = 0.01
N_MAPS = 400


def _grid(nx=9, ny=8, nz=13):
    g = np.meshgrid(np.linspace(0, 150, nx), np.linspace(0, 150, ny), np.linspace(0, 800, nz),
                    indexing="ij")  # fmt: skip
    return np.column_stack([a.ravel() for a in g])


def _false_alarms(widen: float, seed: int) -> int:
    pos = _grid()
    prob = SimpleNamespace(pos=pos)
    rng = np.random.default_rng(seed)
    return sum(
        bool(isolated_planes(prob, widen * rng.standard_normal((len(pos), 3)), q=Q))
        for _ in range(N_MAPS)
    )


def _bound(k: int) -> float:
    """One-sided 95 % Clopper-Pearson upper bound of a rate seen k times in N_MAPS."""
    return float(stats.beta.ppf(0.95, k + 1, N_MAPS - k))


def test_clean_maps_flag_a_plane_at_most_at_the_family_wise_level():
    k = _false_alarms(1.0, seed=11)
    # the rate's upper bound must admit q, and the count must not exceed what q allows
    assert k <= stats.binom.ppf(0.999, N_MAPS, Q), (k, _bound(k))


def test_a_noise_model_too_small_by_a_quarter_does_not_make_planes_bad():
    k = _false_alarms(1.25, seed=12)
    assert k <= stats.binom.ppf(0.999, N_MAPS, Q), (k, _bound(k))


def test_a_bad_plane_is_found():
    pos = _grid()
    rng = np.random.default_rng(13)
    z = rng.standard_normal((len(pos), 3))
    bad = pos[:, 2] == 0.0  # the first plane of every z line
    z[bad, 1] += 2.0  # 2 sigma on each of its 72 readings: 17 sigma on the plane mean
    found = isolated_planes(SimpleNamespace(pos=pos), z, q=Q)
    assert found and found[0]["axis"] == "z" and found[0]["position_mm"] == 0.0
    assert found[0]["component"] == "y"
