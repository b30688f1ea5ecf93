"""Write twin recordings (CSV, see `cfm-fem compare --help`) with concealed effects: tracker
and/or Hall map.

    python scripts/make_twin.py --kind tracker --effects '{"reversal": {"backlash_z": 8}}' \
        --seed 3 --out twin_tracker.csv
    python scripts/make_twin.py --kind hall --effects '{"planar_hall": {"k_z": 0.02}}' \
        --out twin_hall.csv      # reference: cfm_fem/data/qfdp4_harmonics.csv

The truth (bench errors, effect parameters) is written as '#' comment lines at the top.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from cfm_fem.io.recordings import write_hall_map, write_tracker
from cfm_fem.workflows.diagnose.twin import hall_twin, tracker_twin


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--kind", choices=["tracker", "hall"], default="tracker")
    p.add_argument("--effects", default="{}", help="JSON: {effect: {param: value}}")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--speeds", default=None, help="comma-separated on-the-fly speeds (mm/s)")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    eff = json.loads(a.effects)
    if a.kind == "tracker":
        speeds = None if a.speeds is None else [float(s) for s in a.speeds.split(",")]
        rec, truth = tracker_twin(a.seed, eff, n_reps=a.reps, speeds=speeds)
        write = write_tracker
    else:
        rec, truth, _ = hall_twin(a.seed, eff, n_reps=a.reps)
        write = write_hall_map
    comments = [f"cfm-fem twin, seed {a.seed}, concealed effects: {json.dumps(eff)}"]
    comments.append("true errors (mm/rad): " + " ".join(f"{v:.4g}" for v in truth["errors"]))
    write(a.out, rec, comments)
    print(f"wrote {a.out}: {len(rec)} rows ({len(np.unique(rec.point_id))} points)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
