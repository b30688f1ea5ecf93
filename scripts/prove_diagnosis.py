"""Blind proof of `cfm-fem diagnose` on recordings simulated independently of it.

Recordings come from :mod:`cfm_fem.simulation` (its own HTM chain with Table II draws, a magpylib
permanent-magnet quadrupole through both ends, scan timing and speeds), which shares no model code
with the diagnosis. Each recording is diagnosed the way a user does, with the command line
(``cfm-fem diagnose --tracker REC | --hall-map REC --reference FIELD --no-report --out DIR``,
its entry point called in the worker process), and the ``diagnosis.json`` is scored against the
truth written beside the recording:

* nulls (no concealed effect): a false alarm is any effect claimed; the rate with its exact
  (Clopper-Pearson, one-sided) 95 % upper bound;
* concealed effects: detection rate, rank-1 rate, rate of other effects claimed, and the pulls
  (fit - truth) / std of every reported parameter of the concealed effect with a known truth;
* the slip (``step_event``, not in the catalogue): located in the repetitions from the step on,
  and not claimed as thermal drift.

Goals (PASS/FAIL): false alarms <= 1 % of the nulls; rank-1 >= 95 %; pull std in 0.8-1.25; the
step located and not claimed as drift in >= 95 % of its runs.

Full run (936 points x 10 repetitions; realistic sizes)::

    python scripts/prove_diagnosis.py --nulls 50 --seeds 20 --jobs 2 --out proof/

``--rescore --model-dependent`` scores the kept runs again with the parameters the diagnosis
reports as model-dependent (the soft ends' profile) scored too. ``--merge A B ... --out DIR``
pools the runs of earlier proofs (more seeds of some cases, a case run again) into one summary.

Family mode: ``--family N --first-seed S`` runs N cases of the randomized family
(:mod:`cfm_fem.simulation.family`: dipoles to octupoles and solenoids, benches stacked in any
order, grids, on-the-fly lines, circles and sparse maps, probe noise 0.5-20 uT), seeds S to
S + N - 1, the first ``--null-share`` of them nulls and the rest one concealed effect each at a
drawn 5-8 sigma of joint significance (``--nulls-only``: all nulls). Its summary reports every
goal per stratum (magnet order, source, ends, bench stack, scan kind, noise regime, reference,
kind): false alarms with their exact one-sided 95 % Clopper-Pearson upper bound, rank-1 rates
(all, and at >= 6 sigma), pulls per effect, and the seeds to replay
(``write_family_case(seed, folder, size, role)``)::

    nice -n 5 python scripts/prove_diagnosis.py --family 80 --first-seed 1 --jobs 2 --out fam/

``--replicas N`` runs each case N times, replica k > 0 with the readings' noise drawn afresh
(the same magnet, bench, scan and concealed effect); the summary then gives each case's pulls
over its replicas and, per effect, their std about each case's mean: the spread the stated std
must match, apart from the bias a configuration puts on a parameter.

Goals of the family: false alarms <= 1 % pooled and CP95 upper <= 3 % in every stratum; every
effect at >= 6 sigma ranked first in >= 95 % of its runs per magnet order; pull std 0.8-1.25
per effect.

Quick run: ``--small`` (small grids, 4 repetitions). ``--cases reversal,null_hall`` restricts the
cases; ``--no-velocities`` leaves v_x, v_y, v_z out of the recordings (the diagnosis then infers
the moving axes). Writes DIR/results.json (every run and the summary) and DIR/summary.md.
"""

from __future__ import annotations

import os

# one BLAS / numba thread per worker: the workers already share the machine
_THREADS = {v: "1" for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
_THREADS["NUMBA_NUM_THREADS"] = "1"
os.environ.update(_THREADS)

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
import zlib  # noqa: E402
from pathlib import Path  # noqa: E402

from cfm_fem.simulation import CASES, write_case  # noqa: E402
from cfm_fem.simulation.benches import STACKS, stack_label  # noqa: E402
from cfm_fem.simulation.family import (  # noqa: E402
    draw_config,
    write_family_case,
    written_config,
)
from cfm_fem.simulation.family_summary import (  # noqa: E402
    FAMILY_GOALS,
    markdown_family,
    summarise_family,
)
from cfm_fem.simulation.magnets import ORDER_NAMES  # noqa: E402
from cfm_fem.simulation.scoring import GOALS, score, summarise  # noqa: E402


def tasks(cases, nulls: int, seeds: int, skip: int = 0) -> list:
    """(case, seed) of every run; seeds differ between cases (a hash of the name). ``skip``:
    leave out the first seeds of each case (more runs of a case after a run of fewer)."""
    out = []
    for case in cases:
        n = nulls if CASES[case][2] is None else seeds
        base = 1000 * (zlib.crc32(case.encode()) % 100000)
        out += [(case, base + i) for i in range(skip, skip + n)]
    return out


def _cli(argv) -> tuple[int, str]:
    """``cfm-fem ARGV`` in this worker process (the command line's own entry point, imported
    once per worker instead of once per run): exit code and what it wrote to stderr."""
    import contextlib
    import io

    from cfm_fem.cli import main as cli_main

    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            code = cli_main(argv)
        except SystemExit as e:  # argparse errors
            code = e.code if isinstance(e.code, int) else 2
    return int(code or 0), err.getvalue()


def run_one(job) -> dict:
    """Simulate one case, diagnose it with the command line, score it."""
    case, seed, out, small, velocities, keep = job
    sim_dir, run_dir = Path(out) / "sim" / case, Path(out) / "runs" / f"{case}_{seed}"
    files = write_case(case, seed, sim_dir, "small" if small else "full", velocities)
    truth = json.loads(Path(files["truth"]).read_text())
    if run_dir.exists():
        shutil.rmtree(run_dir)
    argv = ["diagnose", *files["args"], "--no-report", "--out", str(run_dir)]
    t0 = time.perf_counter()
    code, err = _cli(argv)
    seconds = time.perf_counter() - t0
    base = {"case": case, "seed": seed, "kind": files["kind"], "expected": files["expected"]}
    if code != 0:
        return base | {"error": err.strip()[-2000:], "seconds": seconds}
    summary = json.loads((run_dir / "diagnosis.json").read_text())
    result = score(summary, truth) | {"seconds": seconds}
    result["effects"] = summary["effects"]  # as reported, for the record
    if not keep:
        Path(files["recording"]).unlink()
        for p in run_dir.iterdir():
            if p.name != "diagnosis.json":
                p.unlink()
    return result


def family_jobs(n: int, first_seed: int, null_share: float) -> list:
    """(seed, role) of the family runs: seeds first_seed .. first_seed + n - 1, the first
    round(n null_share) of them nulls."""
    n_null = int(round(n * null_share))
    return [(first_seed + i, "null" if i < n_null else "effect") for i in range(n)]


def family_filters(a) -> dict:
    """The labels the ``--only-kind``, ``--only-reference``, ``--only-magnet`` and
    ``--only-stack`` options ask of a family case's configuration: {label: allowed values}."""
    filters = {}
    if a.only_kind:
        filters["kind"] = {a.only_kind}
    if a.only_reference:
        filters["reference"] = {a.only_reference}
    for key, names in (("magnet", a.only_magnet), ("bench_stack", a.only_stack)):
        if names:
            filters[key] = set(names.split(","))
    return filters


def _labels(cfg) -> dict:
    """A configuration's labels the filters read (the reference is None on a tracker)."""
    strata = cfg["strata"]
    return {"kind": cfg["kind"], "reference": cfg.get("reference"),
            "magnet": strata["magnet"], "bench_stack": strata["bench_stack"]}  # fmt: skip


def matches(cfg, filters: dict) -> bool:
    """Whether a configuration (a case's as written: its truth's ``config``) has the labels
    the filters ask."""
    labels = _labels(cfg)
    return all(labels[k] in allowed for k, allowed in filters.items())


def may_match(cfg, filters: dict) -> bool:
    """Whether a case of this first draw (:func:`draw_config`) is run: it has the labels the
    filters ask, or, for an effect case, a reference of 2-D harmonics where the exact one is
    asked (the family replaces harmonics the body departs from by the exact field).

    The first draw is the configuration written but for an effect case the family redraws
    (an effect beyond its physical range there, ``attempts`` > 1 in the truth) or whose
    reference it replaces, which takes the case's sizing to know; such a case is selected on
    its first draw and checked again once written (:func:`run_family_one`), so a case runs
    only if its written configuration has the labels too. A redrawn configuration is drawn
    from a seed of its own, so the redrawn cases kept are a random share of those whose
    written configuration has the labels."""
    if matches(cfg, filters):
        return True
    if cfg["role"] != "effect" or "exact" not in filters.get("reference", ()):
        return False
    return cfg.get("reference") == "harmonics" and matches(cfg | {"reference": "exact"}, filters)


def run_family_one(job) -> dict:
    """Simulate one family case, diagnose it with the command line, score it; a case whose
    written configuration leaves the filters (:func:`may_match`) is not diagnosed and its
    result is marked ``deselected``."""
    seed, role, out, size, keep, filters, replica = job
    stem = f"family_{seed}" + (f"_r{replica}" if replica else "")
    sim_dir, run_dir = Path(out) / "sim", Path(out) / "runs" / stem
    t0 = time.perf_counter()
    files = write_family_case(seed, sim_dir, size, role=role, replica=replica)
    t_sim = time.perf_counter() - t0
    truth = json.loads(Path(files["truth"]).read_text())
    if not matches(truth["config"], filters):
        if not keep:
            for f in ("recording", "reference", "truth", "bench"):
                if files[f]:
                    Path(files[f]).unlink()
        return {"case": truth["case"], "seed": seed, "replica": replica, "role": role,
                "deselected": True, "seconds": t_sim,
                "note": f"deselected: written as {_labels(truth['config'])} "
                        f"(attempts {truth['attempts']})"}  # fmt: skip
    if run_dir.exists():
        shutil.rmtree(run_dir)
    code, err = _cli(["diagnose", *files["args"], "--no-report", "--out", str(run_dir)])
    seconds = time.perf_counter() - t0
    sig = truth["significance"] or {}
    base = {"case": truth["case"], "seed": seed, "replica": replica, "role": role,
            "kind": truth["kind"],
            "expected": truth["expected"], "strata": truth["strata"],
            "sigma": sig.get("sigma_drawn") if truth["expected"] else None,
            "sigma_noise_only": sig.get("sigma_noise_only") if truth["expected"] else None,
            "seconds": seconds, "sim_seconds": t_sim}  # fmt: skip
    if code != 0:
        return base | {"error": err.strip()[-2000:]}
    summary = json.loads((run_dir / "diagnosis.json").read_text())
    result = score(summary, truth) | base
    result["effects"] = [{k: e.get(k) for k in ("name", "params", "param_std", "delta_bic")}
                         for e in summary["effects"]]  # fmt: skip
    if not keep:
        for f in ("recording", "reference"):
            if files[f]:
                Path(files[f]).unlink()
        for p in run_dir.iterdir():
            if p.name != "diagnosis.json":
                p.unlink()
    return result


def run_family(a) -> int:
    """The family proof: run, summarise per stratum, write FAMILY results and summary."""
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    share = 1.0 if a.nulls_only else a.null_share
    size = "small" if a.small or a.size == "small" else "full"
    filters = family_filters(a)
    jobs = []
    per_effect = {e: 0 for e in (a.only_effect or "").split(",") if e}
    for seed, role in family_jobs(a.family, a.first_seed, share):
        cfg = draw_config(seed, size, role)
        if role == "null" and "reference" in filters:  # exact: a null's sizing is cheap
            cfg = written_config(seed, size, role)
        if not may_match(cfg, filters):
            continue
        if per_effect:  # the seeds whose drawn effect is one of these, the first N of each
            e = cfg.get("effect")
            if e not in per_effect or (a.per_effect is not None and per_effect[e] >= a.per_effect):
                continue
            per_effect[e] += 1
        jobs.append((seed, role, str(out), size, a.keep, filters))
    jobs = [(*j, k) for j in jobs for k in range(a.replicas)]
    t0 = time.perf_counter()
    if a.family_merge:
        runs = {}
        for folder in a.family_merge:
            path = Path(folder) / "family_results.json"
            if not path.is_file():
                raise SystemExit(f"prove_diagnosis: {path}: no family_results.json")
            runs |= {(r["seed"], r["role"], r.get("replica", 0)): r
                     for r in json.loads(path.read_text())["runs"]}  # fmt: skip
        results = sorted(runs.values(), key=lambda r: (r["role"], r["seed"], r.get("replica", 0)))
        what = f"pooled from {', '.join(a.family_merge)}"
    else:
        print(f"{len(jobs)} family runs, size {size}, {a.jobs} worker(s)", flush=True)
        results = sorted(run_all(jobs, a.jobs, run_family_one),
                         key=lambda r: (r["seed"], r["replica"]))  # fmt: skip
        dropped = [r for r in results if r.get("deselected")]
        results = [r for r in results if not r.get("deselected")]
        if dropped:
            print(f"{len(dropped)} run(s) deselected: written outside the filters "
                  f"(seeds {sorted({r['seed'] for r in dropped})})", flush=True)  # fmt: skip
        what = (f"seeds {a.first_seed}-{a.first_seed + a.family - 1}, size {size}, "
                f"{time.perf_counter() - t0:.0f} s wall with {a.jobs} worker(s)")  # fmt: skip
    summary = summarise_family(results)
    header = (
        f"Family proof of `cfm-fem diagnose`: {len(results)} runs "
        f"({sum(r['role'] == 'null' for r in results)} nulls), {what}; goals {FAMILY_GOALS}."
    )
    md = markdown_family(summary, header)
    print()
    print(md)
    (out / "family_summary.md").write_text(md)
    (out / "family_results.json").write_text(
        json.dumps(
            {"summary": summary, "runs": results, "goals": FAMILY_GOALS}, indent=1, default=str
        )
    )
    print(f"goals: {'PASS' if all(summary['goals'].values()) else 'FAIL'}")
    print(f"wrote {out / 'family_results.json'}, {out / 'family_summary.md'}")
    return 0


def run_all(jobs: list, workers: int, one=run_one) -> list:
    """Run the jobs on a pool of ``workers`` processes, printing each result as it comes."""
    results = []
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        for i, r in enumerate(pool.imap_unordered(one, jobs), 1):
            results.append(r)
            what = (
                r.get("error", "")[-200:]
                or r.get("note")
                or f"expected {r['expected']}, claimed {r['claimed']}"
            )
            print(f"[{i}/{len(jobs)}] {r['case']} seed {r['seed']}: {r['seconds']:.1f} s; {what}",
                  flush=True)  # fmt: skip
    return results


def rescore(out: Path, model_dependent: bool = False) -> list:
    """Score again the runs recorded in OUT/results.json from their kept diagnosis.json and
    truth files (after a change of the scoring, without diagnosing again); ``model_dependent``:
    score the parameters reported as model-dependent too."""
    runs = json.loads((out / "results.json").read_text())["runs"]
    results = []
    for r in runs:
        diag = out / "runs" / f"{r['case']}_{r['seed']}" / "diagnosis.json"
        truth = out / "sim" / r["case"] / f"{r['case']}_{r['seed']}.truth.json"
        if "error" in r or not diag.exists():
            results.append(r)
            continue
        summary = json.loads(diag.read_text())
        new = score(summary, json.loads(truth.read_text()), model_dependent)
        results.append(new | {"seconds": r["seconds"], "effects": summary["effects"]})
    return results


def merged(folders: list) -> list:
    """The runs of earlier proofs pooled: every FOLDER/results.json in turn, a later folder's run
    of the same case and seed replacing an earlier one."""
    runs = {}
    for folder in folders:
        path = Path(folder) / "results.json"
        if not path.is_file():
            raise SystemExit(f"prove_diagnosis: {path}: no results.json (run a proof there first)")
        for r in json.loads(path.read_text())["runs"]:
            runs[r["case"], r["seed"]] = r
    return list(runs.values())


def _pct(pair):
    k, n = pair
    return f"{k}/{n} ({100.0 * k / n:.0f} %)" if n else "-"


def _fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def markdown(summary: dict, seconds: dict, header: str) -> str:
    """The summary as a Markdown table (one row per case)."""
    lines = [
        header,
        "",
        "| case | kind | runs | false alarms (CP95 upper) | detected | rank 1 | other claims "
        "| pull mean | pull std | s/run | goals |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, r in summary.items():
        fa = "-"
        if r["expected"] is None:
            fa = f"{_pct(r['false_alarms'])} (<= {_fmt(100 * r['cp95_upper'], '.1f')} %)"
        goals = ", ".join(f"{g} {'PASS' if ok else 'FAIL'}" for g, ok in r["goals"].items())
        if "step" in r:
            s = r["step"]
            goals += f"; step located {s['located']}/{s['n']}, drift {s['claimed_drift']}/{s['n']}"
        runs = f"{r['runs']}" + (f" ({r['errors']} failed)" if r["errors"] else "")
        lines.append(
            f"| {case} | {r['kind']} | {runs} "
            f"| {fa} | {_pct(r['detected']) if 'detected' in r else '-'} "
            f"| {_pct(r['rank1']) if 'rank1' in r else '-'} "
            f"| {_pct(r['other_claims']) if 'other_claims' in r else '-'} "
            f"| {_fmt(r['pull_mean'])} | {_fmt(r['pull_std'])} | {seconds[case]:.1f} | {goals} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--nulls", type=int, default=50, help="null recordings of each kind")
    ap.add_argument("--seeds", type=int, default=20, help="seeds per concealed-effect case")
    ap.add_argument(
        "--skip-seeds",
        type=int,
        default=0,
        metavar="N",
        help="leave out the first N seeds of each case (--seeds more after a run of N)",
    )
    ap.add_argument("--small", action="store_true", help="small grids, 4 repetitions")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    ap.add_argument("--out", default="proof", help="output folder")
    ap.add_argument("--cases", help="comma-separated case names (default: all)")
    ap.add_argument("--no-velocities", action="store_true", help="leave out v_x, v_y, v_z")
    ap.add_argument("--keep", action="store_true", help="keep recordings and full outputs")
    ap.add_argument(
        "--rescore", action="store_true", help="score the runs in --out again (same options)"
    )
    ap.add_argument(
        "--model-dependent",
        action="store_true",
        help="with --rescore: score the parameters reported as model-dependent too",
    )
    ap.add_argument(
        "--merge",
        nargs="+",
        metavar="DIR",
        help="pool the results of earlier proofs in DIR ... (a later folder's run of a case and "
        "seed replaces an earlier one) and write their summary to --out",
    )
    ap.add_argument("--family", type=int, metavar="N", help="N cases of the randomized family")
    ap.add_argument("--first-seed", type=int, default=1, help="first seed of --family")
    ap.add_argument(
        "--null-share", type=float, default=0.5, help="share of nulls among --family runs"
    )
    ap.add_argument("--nulls-only", action="store_true", help="--family runs all nulls")
    ap.add_argument("--size", choices=("small", "full"), default="full", help="--family size")
    ap.add_argument(
        "--only-kind",
        choices=("hall", "tracker"),
        help="--family: run only the seeds whose drawn recording is of this kind",
    )
    ap.add_argument(
        "--only-reference",
        choices=("exact", "coarse", "harmonics"),
        help="--family: run only the Hall seeds whose drawn reference is of this kind",
    )
    ap.add_argument(
        "--only-magnet",
        metavar="NAMES",
        help="--family: run only the seeds whose drawn magnet is one of these (comma-separated: "
        "dipole, quadrupole, sextupole, octupole, solenoid; none for a tracker recording)",
    )
    ap.add_argument(
        "--only-stack",
        metavar="NAMES",
        help="--family: run only the seeds whose drawn bench stack is one of these "
        "(comma-separated, foundation first: X-Y-Z, ..., Z-Y-X)",
    )
    ap.add_argument(
        "--only-effect",
        metavar="NAMES",
        help="--family: run only the seeds whose drawn concealed effect is one of these "
        "(comma-separated), at most --per-effect of each",
    )
    ap.add_argument(
        "--per-effect", type=int, metavar="N", help="--only-effect: the first N seeds of each"
    )
    ap.add_argument(
        "--replicas",
        type=int,
        default=1,
        metavar="N",
        help="family mode: run each case N times, replica k > 0 with the readings' noise drawn "
        "afresh (the same magnet, bench, scan and effect); the summary gives each case's pull "
        "std over its replicas",
    )
    ap.add_argument(
        "--family-merge",
        nargs="+",
        metavar="DIR",
        help="pool the family runs of earlier proofs in DIR ... and write their summary to --out",
    )
    a = ap.parse_args(argv)
    if a.family_merge:
        a.family = a.family or 1
    if a.family is not None:
        if a.family < 1 or not 0.0 <= a.null_share <= 1.0:
            ap.error("--family needs N >= 1 and --null-share in [0, 1]")
        if a.replicas < 1:
            ap.error("--replicas needs N >= 1")
        known = {
            "--only-magnet": (a.only_magnet, [*ORDER_NAMES.values(), "none"]),
            "--only-stack": (a.only_stack, [stack_label(s) for s in STACKS]),
        }
        for opt, (names, allowed) in known.items():
            bad = [n for n in (names or "").split(",") if names and n not in allowed]
            if bad:
                ap.error(f"{opt}: unknown {', '.join(bad)}; expected some of {', '.join(allowed)}")
        return run_family(a)
    cases = list(CASES) if not a.cases else [c.strip() for c in a.cases.split(",")]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        ap.error(f"unknown case(s) {', '.join(unknown)}; expected some of {', '.join(CASES)}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [
        (c, s, str(out), a.small, not a.no_velocities, a.keep)
        for c, s in tasks(cases, a.nulls, a.seeds, a.skip_seeds)
    ]
    size = "small" if a.small else "full (936 points x 10 repetitions)"
    if not a.merge:
        print(f"{len(jobs)} runs, size {size}, {a.jobs} worker(s)", flush=True)
    t0 = time.perf_counter()
    if a.model_dependent and not a.rescore:
        ap.error("--model-dependent goes with --rescore")
    if a.merge:
        results = merged(a.merge)
        size = f"pooled from {', '.join(a.merge)}"
    elif a.rescore:
        results = rescore(out, a.model_dependent)
    else:
        results = run_all(jobs, a.jobs)
    results.sort(key=lambda r: (r["case"], r["seed"]))
    summary = summarise(results)
    seconds = {c: sum(r["seconds"] for r in results if r["case"] == c) / summary[c]["runs"]
               for c in summary}  # fmt: skip
    wall = time.perf_counter() - t0
    header = (
        f"Independent proof of `cfm-fem diagnose`: {len(results)} runs, size {size}, "
        f"velocities {'absent' if a.no_velocities else 'written'}; goals {GOALS}; "
        f"{wall:.0f} s wall with {a.jobs} worker(s)."
    )
    if a.merge:
        header = f"Independent proof of `cfm-fem diagnose`: {len(results)} runs {size}; "
        header += f"goals {GOALS}."
    md = markdown(summary, seconds, header)
    print()
    print(md)
    for case, r in summary.items():
        for p, (n, m, s) in r["pulls"].items():
            print(f"  pulls {case}.{p}: n={n} mean={m:.2f} std={_fmt(s)}")
    (out / "summary.md").write_text(md)
    (out / "results.json").write_text(
        json.dumps({"summary": summary, "runs": results, "goals": GOALS}, indent=1, default=str)
    )
    failed = [c for c, r in summary.items() if not all(r["goals"].values())]
    print(f"goals: {'PASS' if not failed else 'FAIL (' + ', '.join(failed) + ')'}")
    print(f"wrote {out / 'results.json'}, {out / 'summary.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
