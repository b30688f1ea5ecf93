"""Hall maps read exactly where the bench puts the probe, shared by the diagnosis tests of
`hall_problem`'s expansion in the bench's errors and the magnet's pose."""

import numpy as np

from cfm_fem.models.recordings import Recording
from cfm_fem.workflows.diagnose.problem import bench_move, hall_problem, posed_field


def exact_reading(field, bench, pts, q, theta, pose):
    """B (n, 3) T of ``field`` at the points ``pts`` (n, 3) mm moved by the bench's errors
    ``theta`` at the axis positions ``q``, the magnet at ``pose`` (um, urad)."""
    return posed_field(field, pose)(pts + bench_move(bench, q, theta))


def exact_problem(field, reference, step_mm, bench, pts, q, at, pose):
    """`hall_problem` of one noiseless repetition of ``field``'s exact readings, expanded at
    the errors ``at`` with the magnet at ``pose``; ``reference`` is what it reads (``field``
    itself, or a wrapper of it)."""
    n = len(pts)
    rec = Recording(
        kind="hall",
        point_id=np.arange(n),
        rep=np.zeros(n, dtype=np.int64),
        cmd=pts,
        B=exact_reading(field, bench, pts, q, at, pose),
    )
    return hall_problem(rec, reference, step_mm, bench, pose=pose, bench_at=at)
