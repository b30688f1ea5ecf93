"""Effects at a magnet's end read against a coarse FEM-like map (the family's magpylib magnets,
the map read between its nodes by its harmonic fits).

At an end the map's own error between its nodes is largest, where both the averaging's columns
(the field's curvature) and an element offset's (its gradient along z) are: both effects are
credited only with what that error, at the share the readings allow, cannot give. Seeds 140122
(8.0 sigma, a grid of 4 x 4 lines through one end) and 140086 (5.1 sigma, a sparse map)
conceal averaging alone on octupoles; against the exact field either is named alone.

The smooth term of the map's error across the scan has priors of the stated error's size: it
does not absorb a probe tilt whose signature it could reproduce only far beyond them (seed
140024: a solenoid on circles through both ends, tilts m_yz and m_zy of 0.17 and -1.06 mrad).
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.simulation import write_family_case
from cfm_fem.workflows.diagnose.calibrate import Columns
from cfm_fem.workflows.diagnose.context import ProblemContext
from cfm_fem.workflows.diagnose.effects import _reference_error_std
from cfm_fem.workflows.diagnose.select import free_columns


def _diagnose_full(seed, tmp_path):
    files = write_family_case(seed, tmp_path / "case", "full", role="effect")
    truth = json.loads(Path(files["truth"]).read_text())
    assert truth["config"]["reference"] == "coarse"
    out = tmp_path / "out"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    return json.loads((out / "diagnosis.json").read_text()), truth


@pytest.mark.slow  # a full-size case: about 25 s
@pytest.mark.parametrize("seed", [140122, 140086])
def test_averaging_at_an_octupole_end_is_not_taken_for_an_element_offset(seed, tmp_path):
    d, truth = _diagnose_full(seed, tmp_path)
    assert truth["expected"] == "sensor_volume_averaging"
    assert truth["config"]["magnet"]["order"] == 4
    assert [e["name"] for e in d["effects"]] == ["sensor_volume_averaging"], d["candidates"]
    dw_z, want = d["effects"][0]["params"]["dw_z"], truth["params"]["dw_z"]
    assert abs(dw_z - want) < 0.15 * abs(want), (dw_z, want)


def _context(share):
    def reference_fn(p):
        return np.zeros((len(p), 3))

    reference_fn.error_var = lambda p: np.tile([4.0, 9.0, 16.0], (len(p), 1))
    upts = np.zeros((2, 3))
    return ProblemContext(reference_fn=reference_fn, upts=upts, uinv=np.array([0, 1, 1]),
                          ref_share=share)  # fmt: skip


def test_the_reference_bound_takes_the_stated_error_at_its_share():
    full, key = _reference_error_std(_context(None))
    np.testing.assert_allclose(full, [[2.0, 3.0, 4.0]] * 2)
    np.testing.assert_array_equal(key, [0, 1, 1])
    part, _ = _reference_error_std(_context(np.array([0.25, 1.0, 0.04])))
    np.testing.assert_allclose(part, [[1.0, 3.0, 0.8]] * 2)
    # a share above 1 is no licence to state more than the map does
    more, _ = _reference_error_std(_context(np.array([4.0, 1.0, 1.0])))
    np.testing.assert_allclose(more, full)


@pytest.mark.slow  # a full-size case: about 15 s
def test_a_probe_tilt_is_not_absorbed_by_the_reference_error_term(tmp_path):
    d, truth = _diagnose_full(140024, tmp_path)
    assert truth["config"]["magnet"]["source"] == "solenoid"
    assert [e["name"] for e in d["effects"]] == ["probe_misalignment"], d["candidates"]
    e = d["effects"][0]
    want = truth["effects"]["probe_misalignment"]
    assert set(e["params"]) == set(want), e["params"]
    for name, value in want.items():  # within 3 of their stated std
        assert abs(e["params"][name] - value) < 3.0 * e["param_std"][name], (name, e, want)


def _block(names, group, prior_std):
    k = len(names)
    J = np.ones((4, 3, k))
    return Columns(J, names, ["u"] * k, np.zeros(k), np.full(k, prior_std), group)


def test_the_reference_term_is_no_free_baseline():
    bench = _block(["alpha_xy", "gain_x"], "bench", 10.0)
    prob = SimpleNamespace(baseline=[bench, _block(["ref_x_000", "ref_y_000"], "reference", 0.1)])
    model = Columns(
        np.arange(60.0).reshape(4, 3, 5),
        ["alpha_xy", "ref_x_000", "gain_x", "ref_y_000", "m_yz"],
        ["u"] * 5,
        np.zeros(5),
        np.ones(5),
        "bench+reference+probe_misalignment",
    )
    free = free_columns(prob, model)
    assert free.names == ["alpha_xy", "gain_x", "m_yz"]
    np.testing.assert_array_equal(free.J, model.J[..., [0, 2, 4]])
    no_term = SimpleNamespace(baseline=[_block(["alpha_xy"], "bench", 10.0)])
    assert free_columns(no_term, model) is model
