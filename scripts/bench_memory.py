"""Peak memory of `cfm-fem sweep` in memory, with ``--pieces`` and with ``--slabs``, same map.

Each variant runs in its own process (``cfm-fem sweep`` in-process via ``main``); the peak
resident set size (``ru_maxrss``) of that process is printed, with a floor (read the map and
build the interpolation mesh, nothing else) and the ratios. Not a timing benchmark.

    python scripts/bench_memory.py              # 48 x 48 x 96 grid (221,184 nodes), 6 U_p values
    python scripts/bench_memory.py --n 64 --pieces 32 --slabs 16

The map is a plain CSV table written like an Opera export (z fastest, z the longest axis), so
``--slabs`` streams it; every variant reads the same file.

What ``--slabs`` bounds: the map, the mesh, the kernel arrays and the statistics are held one
slab (plus halo) at a time (nodes keep their whole-map index as random-stream key); what grows
with the map is on disk. Run two lengths of the same cross-section with the slab count scaled
to keep slab and halo equal, e.g. ``--n 40 --slabs 8`` and ``--n 40 --nz 240 --slabs 24``: the
slab peak stays flat, the others grow. (Growing all axes at a fixed node count per slab makes
slabs thinner, so the fixed-width halo holds more nodes.)

What ``--pieces`` bounds: the per-node statistics and the output arrays (one piece and one
chunk at a time). What it does not: the map, the mesh and the per-node gradients, about the
"floor" line, and the compact per-node summary arrays (~29 bytes per node and U_p value).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def _write_map(path: Path, n: int, nz: int) -> None:
    ax = np.linspace(-20.0, 20.0, n)
    az = np.linspace(-40.0, 40.0, nz) * (nz / (2 * n))  # same spacing whatever nz
    pts = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1).reshape(-1, 3)
    g = 0.05  # T/mm, a quadrupole-like field plus a sextupole term and a solenoid part
    B = np.c_[
        g * pts[:, 1] + 1e-4 * (pts[:, 0] ** 2 - pts[:, 1] ** 2),
        g * pts[:, 0] + 2e-4 * pts[:, 0] * pts[:, 1],
        0.1 + 1e-3 * pts[:, 2],
    ]
    with open(path, "w") as f:
        f.write("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n")
        for a in range(0, len(pts), 65536):
            rows = np.c_[pts[a : a + 65536], B[a : a + 65536]].tolist()
            f.write("".join(",".join(map(repr, r)) + "\n" for r in rows))


def _child(mode, field, out, pieces, trials, chunk, slabs) -> None:
    from cfm_fem.cli import main

    if mode == "floor":
        from cfm_fem.io import read_field
        from cfm_fem.io.vtk import write_vtu
        from cfm_fem.models.sweep import SweepConfig
        from cfm_fem.workflows.sweep.problem import node_gradients, prepare_sweep

        fm = read_field(field)
        mesh, _, _ = prepare_sweep(fm, SweepConfig(up_um=[50.0], trials=trials))
        node_gradients(mesh, fm.B)
        write_vtu(Path(out + ".vtu"), fm.points[:4], None, {"B": fm.B[:4]})  # loads VTK too
        rc = 0
    else:
        args = ["sweep", field, "--up", "0:50:10", "--trials", str(trials), "--out", out]
        args += ["--chunk-nodes", str(chunk)]
        if mode == "pieces":
            args += ["--pieces", str(pieces)]
        if mode == "slabs":
            args += ["--slabs", str(slabs)]
        rc = main(args)
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(json.dumps({"mode": mode, "rc": rc, "peak_mib": peak_kb / 1024}))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--n", type=int, default=48, help="grid points along x and y (default 48)")
    p.add_argument("--nz", type=int, help="grid points along z, the slab axis (default 2 n)")
    p.add_argument("--pieces", type=int, default=16)
    p.add_argument("--slabs", type=int, default=8)
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--chunk-nodes", type=int, default=4096)
    p.add_argument("--child", nargs=2, metavar=("MODE", "DIR"), help=argparse.SUPPRESS)
    a = p.parse_args()
    a.nz = a.nz or 2 * a.n
    if a.child:
        mode, tmp = a.child
        _child(mode, str(Path(tmp) / "map.csv"), str(Path(tmp) / mode), a.pieces, a.trials,
               a.chunk_nodes, a.slabs)  # fmt: skip
        return
    with tempfile.TemporaryDirectory() as tmp:
        _write_map(Path(tmp) / "map.csv", a.n, a.nz)
        rows = {}
        for mode in ("floor", "in-memory", "pieces", "slabs"):
            cmd = [sys.executable, __file__, "--child", mode, tmp, "--n", str(a.n),
                   "--pieces", str(a.pieces), "--trials", str(a.trials), "--slabs", str(a.slabs),
                   "--chunk-nodes", str(a.chunk_nodes)]  # fmt: skip
            res = subprocess.run(cmd, capture_output=True, text=True, check=True)
            rows[mode] = json.loads(res.stdout.strip().splitlines()[-1])
            assert rows[mode]["rc"] == 0, res.stderr
    nodes = a.n**2 * a.nz
    floor, full, pc, sl = (rows[m]["peak_mib"] for m in ("floor", "in-memory", "pieces", "slabs"))
    print(f"map: {a.n} x {a.n} x {a.nz} grid = {nodes:,} nodes (CSV), 6 U_p values, "
          f"{a.trials} trials, "
          f"chunks of {a.chunk_nodes} nodes")  # fmt: skip
    print(f"{'variant':<34}{'peak RSS [MiB]':>16}")
    print(f"{'floor (map, mesh, gradient, VTK)':<34}{floor:16.0f}")
    print(f"{'in-memory (one .vtu per U_p)':<34}{full:16.0f}")
    print(f"{f'--pieces {a.pieces} (.pvtu)':<34}{pc:16.0f}")
    print(f"{f'--slabs {a.slabs} (.pvtu, streamed)':<34}{sl:16.0f}")
    print(f"ratio pieces / in-memory: {pc / full:.2f}")
    print(f"ratio slabs / in-memory: {sl / full:.2f}")
    print(
        f"above the floor: in-memory {full - floor:.0f} MiB, pieces {pc - floor:.0f} MiB "
        f"(ratio {(pc - floor) / max(full - floor, 1e-9):.2f})"
    )


if __name__ == "__main__":
    main()
