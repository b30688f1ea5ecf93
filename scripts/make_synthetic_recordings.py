"""Write a small synthetic tracker recording and Hall map (CSV, see `cfm-fem compare --help`)
for the compare example.

    python scripts/make_synthetic_recordings.py OUTDIR [--seed S]

OUTDIR/tracker.csv: 3 x 3 x 3 grid over the strokes of the reference bench, 5 repetitions, plus
a bidirectional ISO 230-2 run along X (5 targets, 3 runs per direction, 4 um reversal), tracker
noise 2 um. OUTDIR/hall_map.csv: QFDp4 (R_ref = 10 mm assumed)
on the mid-plane y = 0, |x| <= 8 mm, z = -50, 0, 50 mm, 10 repetitions, measured by one simulated
bench and the paper's S_HP probe. Both come from cfm_fem.workflows.synthetic (one draw of the bench
errors).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cfm_fem.io.bench_toml import read_reference_bench
from cfm_fem.io.harmonics import read_qfdp4
from cfm_fem.io.recordings import write_hall_map, write_tracker
from cfm_fem.workflows.synthetic import synthetic_hall_map, synthetic_tracker


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", help="output folder")
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    bench = read_reference_bench()
    out = Path(args.out)
    trk = synthetic_tracker(bench, seed=args.seed, reps=5, tracker_std_um=2.0, reversal_um=4.0)
    write_tracker(out / "tracker.csv", trk, comments=[f"synthetic: {trk.source}"])
    hall = synthetic_hall_map(read_qfdp4(), bench, seed=args.seed, reps=10)
    write_hall_map(out / "hall_map.csv", hall, comments=[f"synthetic: {hall.source}"])
    print(
        f"wrote {out / 'tracker.csv'} ({len(trk)} rows), {out / 'hall_map.csv'} ({len(hall)} rows)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
