"""The registration steps the magnet's pose and the bench errors the readings are expanded at
together: a pose fitted at bench errors fitted at another pose leaves their product terms,
which on a sextupole's axis (no gradient, the probe's floor alone as noise) are located and
taken by an effect."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.models.bench import ERROR_NAMES
from cfm_fem.simulation.family import write_family_case
from cfm_fem.workflows.diagnose import register as reg
from cfm_fem.workflows.diagnose.problem import hall_problem, noise_sigma
from cfm_fem.workflows.diagnose.run import reference_field
from cfm_fem.workflows.inputs import choose_bench, recording

pytestmark = pytest.mark.slow


def _problem(folder, stem):
    rec = recording(folder / f"{stem}.csv")
    bench, _ = choose_bench(folder / f"{stem}.bench.toml")
    fn, b_ref, spacing, _ = reference_field(
        str(folder / f"{stem}.reference.csv"), rec, None, "auto"
    )
    step = spacing if spacing is not None else getattr(fn, "spacing", None)
    return hall_problem(rec, fn, b_ref, bench, smooth=spacing is None, ref_spacing_mm=step,
                        ref_nodes=getattr(fn, "nodes", None),
                        ref_error=getattr(fn, "error_var", None))  # fmt: skip


def test_sextupole_axis_is_explained_once_pose_and_bench_errors_converge(tmp_path):
    # a null: a sextupole's body on a 3 x 3 grid of z lines, one through the axis, against a
    # coarse map; 0.67 uT of probe noise, hundreds of uT of vibration through the gradient off
    # the axis; the bench moves the probe by tens of um
    write_family_case(47127, tmp_path, "small", role="null", kind="hall")
    prob = reg.register(_problem(tmp_path, "family_47127"))
    obj, base, fit = reg._objective(prob)
    # converged: one more step of the pose and the bench errors together lowers the MAP
    # objective by less than one
    pose, _ = reg.pose_step(prob, base, fit)
    at, _ = reg.bench_target(prob, base, fit)
    assert at is not None and len(at) == len(ERROR_NAMES)
    assert reg._objective(reg.repose(prob, pose, bench_at=at))[0] > obj - 1.0
    # the readings on the axis (noise: the probe's floor) are explained by the baseline
    sigma = noise_sigma(prob, fit.resid, fit.edf)[0]
    z = fit.resid / sigma
    up = prob.ctx.upts[prob.ctx.uinv]
    axis = np.all(np.abs(up[:, :2]) < 1e-6, axis=1)
    assert axis.sum() >= 50
    mean_z = z[axis].mean(0) * np.sqrt(axis.sum())
    assert np.all(np.abs(mean_z) < 3.0), mean_z
    assert float((z**2).mean()) < 1.15
