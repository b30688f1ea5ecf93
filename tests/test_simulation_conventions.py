"""The simulator's parameters in the diagnosis' conventions: the change a parameter makes in a
simulated recording against the column the diagnosis fits for it (sign and size). The tool's
model is only compared with here, never used to make data."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("magpylib")

from cfm_fem.simulation import bench as sb  # noqa: E402
from cfm_fem.simulation import hall, write_case  # noqa: E402


def test_bench_errors_move_the_probe_as_the_tools_columns():
    from cfm_fem.io.bench_toml import read_reference_bench
    from cfm_fem.models.bench import ERROR_NAMES
    from cfm_fem.models.kinematics import sensitivities

    assert sb.NAMES == ERROR_NAMES
    q = np.random.default_rng(0).uniform(0, 1, (60, 3)) * [150, 150, 800]
    S = sensitivities(read_reference_bench(), q, at=np.zeros(21))  # mm per mm or rad
    for k, name in enumerate(sb.NAMES):
        unit = 1e-6 if name.startswith(("eps", "alpha")) else 1e-3
        moved = sb.probe_position(q, {name: 5.0}) - (q + sb.TOOL_MM)
        np.testing.assert_allclose(moved, 5.0 * unit * S[:, :, k], atol=1e-7, err_msg=name)


@pytest.fixture(scope="module")
def hall_problem_small(tmp_path_factory):
    from cfm_fem.io.bench_toml import read_reference_bench
    from cfm_fem.io.recordings import read_hall_map
    from cfm_fem.workflows.diagnose.problem import hall_problem
    from cfm_fem.workflows.diagnose.run import reference_field as _reference

    f = write_case("null_hall", 11, tmp_path_factory.mktemp("conv"), size="small")
    rec = read_hall_map(f["recording"])
    fn, b_ref, smooth, _ = _reference(str(f["reference"]), rec)
    return hall_problem(rec, fn, b_ref, read_reference_bench(), smooth=smooth), rec


def _change(effects):
    base, _ = hall.simulate(11, size="small")
    moved, _ = hall.simulate(11, effects, size="small")
    return np.stack([moved[c] - base[c] for c in ("Bx", "By", "Bz")], -1)


def _column(prob, rec, name, block=None):
    from cfm_fem.workflows.diagnose import effects as E

    blocks = prob.baseline if block is None else [getattr(E, block)(prob)]
    for b in blocks:
        if name in b.names:
            J = b.J[..., b.names.index(name)]
            # rows of the problem are the recording's rows: same order as the simulation
            assert np.allclose(rec.cmd[:, 2], prob.pos[:, 2])
            return J
    raise KeyError(name)


@pytest.mark.parametrize(
    "effect, name, value, block",
    [
        ("magnet_misalignment", "magnet_dx", 30.0, None),
        ("magnet_misalignment", "magnet_dz", 30.0, None),
        ("magnet_misalignment", "magnet_roll", 200.0, None),
        ("magnet_misalignment", "magnet_rot_x", 200.0, None),
        ("sensor_offset", "e_y_x", 30.0, "sensor_offset"),
        ("sensor_offset", "e_x_y", 30.0, "sensor_offset"),
        ("probe_misalignment", "m_zx", 0.3, "probe_misalignment"),
    ],
)
def test_hall_parameters_match_the_tools_columns(hall_problem_small, effect, name, value, block):
    prob, rec = hall_problem_small
    params = {name: value}
    if effect == "sensor_offset":  # the tool's element i displaced from the other two, the
        # elements' centroid held: element i moved by 2/3 of it, the others by -1/3
        i, j = name[2], name[-1]
        params = {f"d_{k}_{j}": value * (2.0 if k == i else -1.0) / 3.0 for k in "xyz"}
    change = _change({effect: params})
    col = value * _column(prob, rec, name, block)
    scale = np.abs(col).max()
    assert scale > 1e-5  # the parameter has a signature at this size (10 uT and more)
    # same sign and size, to the field's curvature over the parameter's reach
    assert np.abs(change - col).max() < 0.03 * scale
