"""Scan grids shared by the diagnosis tests: bench-axis positions Q and magnet-frame points P
(5 x 4 x 7 points, mm), and the reference bench."""

import numpy as np

from cfm_fem.io.bench_toml import read_reference_bench

BENCH = read_reference_bench()
Q = np.stack(
    np.meshgrid(
        np.linspace(0, 150, 5), np.linspace(0, 150, 4), np.linspace(0, 800, 7), indexing="ij"
    ),
    -1,
).reshape(-1, 3)
P = np.stack(
    np.meshgrid(
        np.linspace(-6, 6, 5), np.linspace(-6, 6, 4), np.linspace(-300, 300, 7), indexing="ij"
    ),
    -1,
).reshape(-1, 3)
