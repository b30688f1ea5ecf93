"""Volume averaging at an octupole's end read against a coarse FEM-like map (the family's
magpylib permanent-magnet octupoles, the map read between its nodes by its harmonic fits).

At an end the map's own error between its nodes is largest, where both the averaging's columns
(the field's curvature) and an element offset's (its gradient along z) are: both effects are
credited only with what that error, at the share the readings allow, cannot give. Seeds 140122
(8.0 sigma, a grid of 4 x 4 lines through one end) and 140086 (5.1 sigma, a sparse map)
conceal averaging alone; against the exact field either is named alone.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.simulation import write_family_case
from cfm_fem.workflows.diagnose.context import ProblemContext
from cfm_fem.workflows.diagnose.effects import _reference_error_std


@pytest.mark.slow  # a full-size case: about 25 s
@pytest.mark.parametrize("seed", [140122, 140086])
def test_averaging_at_an_octupole_end_is_not_taken_for_an_element_offset(seed, tmp_path):
    files = write_family_case(seed, tmp_path / "case", "full", role="effect")
    truth = json.loads(Path(files["truth"]).read_text())
    assert truth["expected"] == "sensor_volume_averaging"
    assert truth["config"]["magnet"]["order"] == 4
    assert truth["config"]["reference"] == "coarse"
    out = tmp_path / "out"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
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
