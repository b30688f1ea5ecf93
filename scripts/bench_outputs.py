"""Time the outputs of the README's sweep: the report's figures and the six VTU maps.

    python scripts/bench_outputs.py             # figures 3 times, each way to write twice
    python scripts/bench_outputs.py --repeat 1  # each once

Runs ``cfm-fem sweep meshes/quadrupole.vtu --up 0:50:10`` once (through the command line's
own code, kernels compiled by it if needed) and keeps its result in memory; then prints

* the CPU time of `draw_sweep_report` (the report's three figures and its HTML) with each
  figure saved as it is drawn (`cfm_fem.report.plots.png_bytes` with ``crop=False``, the
  command's way) and with every figure cropped to its content (``crop=True``: matplotlib
  draws a cropped figure twice);
* the wall and CPU time of `write_sweep` (six maps, ``sweep.pvd``, ``summary.json``) with one
  and with two map writers, and beside the figures on a thread of their own with one writer
  until they are done and two after (the command's way).

CPU time is the process's, all its threads.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _sweep_result(tmp):
    """The README sweep's result and provenance, captured from the command's `write_sweep`."""
    import cfm_fem.io.sweep_out as sweep_out
    from cfm_fem.cli import main

    captured = {}
    write = sweep_out.write_sweep

    def capture(out, res, provenance=None, **kw):
        captured.update(res=res, provenance=provenance)
        return write(out, res, provenance, **kw)

    sweep_out.write_sweep = capture
    argv = ["sweep", str(ROOT / "meshes" / "quadrupole.vtu"), "--up", "0:50:10", "--out", tmp]
    try:
        with (
            open(os.devnull, "w") as null,
            contextlib.redirect_stderr(null),
            contextlib.redirect_stdout(null),
        ):
            rc = main(argv)
    finally:
        sweep_out.write_sweep = write
    if rc != 0:
        raise SystemExit(f"cfm-fem {' '.join(argv)} exited with {rc}")
    return captured["res"], captured["provenance"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="passes of each figure variant")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from cfm_fem.io._atomic import json_text
    from cfm_fem.io.sweep_out import write_sweep
    from cfm_fem.models.sweep import summarize
    from cfm_fem.report import plots
    from cfm_fem.report.sweep import draw_sweep_report

    print(f"load average before: {os.getloadavg()[0]:.2f}; {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory() as tmp:
        res, prov = _sweep_result(f"{tmp}/run")
        document = json.loads(json_text({**summarize(res), "provenance": prov}))
        draw_sweep_report(document, res)  # matplotlib's imports and caches
        saved = plots.png_bytes
        for _ in range(args.repeat):
            for crop in (False, True):
                plots.png_bytes = lambda fig, _crop=crop, **_: saved(fig, crop=_crop)
                c = time.process_time()
                draw_sweep_report(document, res)
                print(f"figures and HTML, crop={crop}: {time.process_time() - c:.2f} s CPU")
        plots.png_bytes = saved

        def timed(label, write):
            out = tempfile.mkdtemp(dir=tmp)
            t, c = time.perf_counter(), time.process_time()
            write(out)
            print(f"{label:48s} {time.perf_counter() - t:6.2f} s wall "
                  f"{time.process_time() - c:6.2f} s CPU")  # fmt: skip

        def own_thread(out):
            pool = ThreadPoolExecutor(1)
            drawing = pool.submit(draw_sweep_report, document, res)
            write_sweep(out, res, prov, writers=1, widen_after=drawing)
            drawing.result()
            pool.shutdown()

        for _ in range(max(1, args.repeat - 1)):
            timed("maps, 1 writer", lambda out: write_sweep(out, res, prov, writers=1))
            timed("maps, 2 writers", lambda out: write_sweep(out, res, prov, writers=2))
            timed("maps (1 writer, 2 after the figures), figures beside", own_thread)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
