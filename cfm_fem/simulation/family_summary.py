"""Summarise scored diagnoses of family cases per stratum: every goal reported for each magnet
order, bench stack, scan kind, noise regime (and source, ends, reference, kind), not pooled only.

Works on the dicts of :func:`.scoring.score`, each with the case's ``strata``, ``role``,
``sigma`` (the drawn joint significance, None for a null) and ``seed`` added.
"""

from __future__ import annotations

import numpy as np

from .scoring import GOALS, clopper_pearson_upper

__all__ = ["FAMILY_GOALS", "STRATA", "summarise_family", "markdown_family"]

#: Goals of the family proof.
FAMILY_GOALS = {
    "false_alarm_pooled_max": GOALS["false_alarm_max"],  # share of nulls with any alarm
    "false_alarm_cp95_max": 0.03,  # one-sided 95 % upper bound, per stratum
    "rank1_min": GOALS["rank1_min"],  # effects at >= rank1_sigma ranked first, per magnet
    "rank1_sigma": 6.0,
    "pull_std": GOALS["pull_std"],  # per effect
}
STRATA = ("kind", "magnet", "source", "ends", "bench_stack", "scan", "noise", "reference")


def _label(run, stratum):
    return run["kind"] if stratum == "kind" else run["strata"][stratum]


def _alarm(run) -> bool:
    """A null's false alarm: any effect claimed, or a mismatch stated (a residual located, a
    plane called bad, a calibrated parameter in conflict with its prior) other than conflicts
    the simulated truth itself has (``mismatch_true``,
    :func:`cfm_fem.simulation.scoring.true_conflicts`)."""
    mismatch = bool(run.get("mismatch")) and not run.get("mismatch_true", False)
    return bool(run["false_alarm"]) or mismatch


def _nulls(runs) -> dict:
    ok = [r for r in runs if "error" not in r]
    k, n = sum(_alarm(r) for r in ok), len(ok)
    return {
        "false_alarms": [k, n],
        "claimed": [sum(bool(r["false_alarm"]) for r in ok), n],
        "cp95_upper": clopper_pearson_upper(k, n) if n else None,
        "errors": len(runs) - n,
        "seeds": sorted(r["seed"] for r in ok if _alarm(r)),
    }


def _sigma_noise_only(run) -> float:
    """A run's significance without the reference's reading error (its drawn one where the
    truth states no other)."""
    return run.get("sigma_noise_only") or run.get("sigma") or 0.0


def _effects(runs) -> dict:
    ok = [r for r in runs if "error" not in r]
    strong = [r for r in ok if (r.get("sigma") or 0.0) >= FAMILY_GOALS["rank1_sigma"]]
    # the same effects judged by their significance against the readings' own std alone
    # (a coarse reference's reading error left out: ``sigma_noise_only`` of the truth)
    noise_only = [r for r in ok if _sigma_noise_only(r) >= FAMILY_GOALS["rank1_sigma"]]
    return {
        "rank1": [sum(bool(r["rank1"]) for r in ok), len(ok)],
        "rank1_strong": [sum(bool(r["rank1"]) for r in strong), len(strong)],
        "rank1_strong_noise_only": [sum(bool(r["rank1"]) for r in noise_only), len(noise_only)],
        "detected": [sum(bool(r["detected"]) for r in ok), len(ok)],
        "errors": len(runs) - len(ok),
        "missed_seeds": sorted((r["seed"], r["expected"]) for r in ok if not r["rank1"]),
    }


def summarise_family(scores: list) -> dict:
    """Per stratum and pooled: false alarms with the CP95 upper bound, rank-1 rates (all drawn
    effects, and those at >= 6 sigma), pulls per effect, and the goals met.

    Returns
    -------
    dict
        ``pooled`` {nulls, effects}, ``strata`` {stratum: {label: {nulls, effects}}},
        ``per_effect`` {effect: {runs, rank1, pull_n, pull_mean, pull_std, first_instead
        {what was ranked first in the misses: count}}}, ``null_claims`` {effect: nulls on which
        it was claimed}, ``goals``
        {goal: bool} (those with runs to judge them), ``failing`` (which strata or effects
        miss which goal).
    """
    nulls = [r for r in scores if r["role"] == "null" or r.get("expected") is None]
    effects = [r for r in scores if r not in nulls]
    out = {"pooled": {"nulls": _nulls(nulls), "effects": _effects(effects)}, "strata": {}}
    for st in STRATA:
        labels = sorted({_label(r, st) for r in scores})
        out["strata"][st] = {
            lab: {
                "nulls": _nulls([r for r in nulls if _label(r, st) == lab]),
                "effects": _effects([r for r in effects if _label(r, st) == lab]),
            }
            for lab in labels
        }
    per = {}
    for r in effects:
        if "error" in r:
            continue
        row = per.setdefault(r["expected"], {"runs": 0, "rank1": 0, "pulls": []})
        row["runs"] += 1
        row["rank1"] += bool(r["rank1"])
        row["pulls"] += list(r["pulls"].get(r["expected"], {}).values())
    for row in per.values():
        p = row.pop("pulls")
        row["pull_n"] = len(p)
        row["pull_mean"] = float(np.mean(p)) if p else None
        row["pull_std"] = float(np.std(p, ddof=1)) if len(p) > 1 else None
    out["per_effect"] = dict(sorted(per.items()))
    claims = {}
    for r in nulls:
        for name in r.get("claimed") or ():
            claims[name] = claims.get(name, 0) + 1
    out["null_claims"] = dict(sorted(claims.items(), key=lambda kv: -kv[1]))
    for r in effects:
        if "error" in r or r["rank1"]:
            continue
        first = (r.get("claimed") or ["nothing"])[0]
        row = out["per_effect"][r["expected"]].setdefault("first_instead", {})
        row[first] = row.get(first, 0) + 1
    out["replicas"] = _replica_pulls(effects)
    out["goals"], out["failing"] = _goals(out)
    return out


def _replica_pulls(effects) -> dict:
    """Pulls of each case run with several noise replicas (``replica`` in the scores).

    Across cases a pull mixes the noise with the case's own configuration (a parameter the
    configuration biases); over the replicas of one case only the noise varies, so their
    spread about the case's mean pull is what the stated std must match.

    Returns
    -------
    dict
        ``cases`` [{seed, effect, replicas, params {name: {n, mean, std}}}] and ``per_effect``
        {effect: {cases, n, within_std}}: the pooled std of the pulls about their case's mean
        (each (case, parameter) with n pulls giving n - 1 degrees of freedom).
    """
    groups = {}
    for r in effects:
        if "error" in r or "replica" not in r:
            continue
        groups.setdefault((r["seed"], r["expected"]), []).append(r)
    cases, per = [], {}
    for (seed, eff), runs in sorted(groups.items()):
        if len(runs) < 2:
            continue
        pulls = {}
        for r in runs:
            for name, v in r["pulls"].get(eff, {}).items():
                pulls.setdefault(name, []).append(v)
        params = {
            name: {"n": len(v), "mean": float(np.mean(v)), "std": float(np.std(v, ddof=1))}
            for name, v in pulls.items()
            if len(v) > 1
        }
        cases.append({"seed": seed, "effect": eff, "replicas": len(runs), "params": params})
        row = per.setdefault(eff, {"cases": 0, "ss": 0.0, "dof": 0, "n": 0})
        row["cases"] += 1
        for p in params.values():  # the sum of squares about the case's mean, from its std
            row["ss"] += p["std"] ** 2 * (p["n"] - 1)
            row["dof"] += p["n"] - 1
            row["n"] += p["n"]
    for row in per.values():
        dof = row.pop("dof")
        row["within_std"] = float(np.sqrt(row.pop("ss") / dof)) if dof else None
    return {"cases": cases, "per_effect": dict(sorted(per.items()))}


def _goals(out) -> tuple:
    g, failing = FAMILY_GOALS, []
    k, n_nulls = out["pooled"]["nulls"]["false_alarms"]
    goals = {}  # a goal without runs to judge it is left out
    if n_nulls:
        goals["false_alarm_pooled"] = k / n_nulls <= g["false_alarm_pooled_max"]
    cp_ok, r1_ok = True, True
    for st, labels in out["strata"].items():
        for lab, row in labels.items():
            cp = row["nulls"]["cp95_upper"]
            if cp is not None and cp > g["false_alarm_cp95_max"]:
                cp_ok = False
                failing.append(f"false alarms {st}={lab}: CP95 upper {100 * cp:.1f} %")
    for lab, row in out["strata"]["magnet"].items():
        k, n = row["effects"]["rank1_strong"]
        if n and k / n < g["rank1_min"]:
            r1_ok = False
            failing.append(f"rank 1 at >= 6 sigma, magnet={lab}: {k}/{n}")
    if n_nulls:
        goals["false_alarm_cp95_per_stratum"] = cp_ok
    if out["pooled"]["effects"]["rank1_strong"][1]:
        goals["rank1_per_magnet"] = r1_ok
    lo, hi = g["pull_std"]
    pull_ok = True
    for eff, row in out["per_effect"].items():
        s = row["pull_std"]
        if s is not None and not lo <= s <= hi:
            pull_ok = False
            failing.append(f"pull std {eff}: {s:.2f} over {row['pull_n']} parameters")
    if any(row["pull_std"] is not None for row in out["per_effect"].values()):
        goals["pull_std_per_effect"] = pull_ok
    return goals, failing


def _pct(pair):
    k, n = pair
    return f"{k}/{n} ({100.0 * k / n:.0f} %)" if n else "-"


def markdown_family(summary: dict, header: str) -> str:
    """The family summary as Markdown: one table per stratum, then the effects and goals. A
    null's false alarm is any effect claimed or any mismatch stated (``mismatch`` true)."""
    lines = [header, ""]
    rows = [("pooled", "all", summary["pooled"])]
    for st, labels in summary["strata"].items():
        rows += [(st, lab, row) for lab, row in labels.items()]
    lines += [
        "| stratum | label | nulls: false alarms | CP95 upper | of which effect claimed "
        "| effects: rank 1 | rank 1 at >= 6 sigma | at >= 6 sigma without the reference's error "
        "| false-alarm seeds | missed (seed, effect) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for st, lab, row in rows:
        nu, ef = row["nulls"], row["effects"]
        cp = "-" if nu["cp95_upper"] is None else f"{100 * nu['cp95_upper']:.1f} %"
        miss = ", ".join(f"{s} {e}" for s, e in ef["missed_seeds"][:8])
        miss += " ..." if len(ef["missed_seeds"]) > 8 else ""
        fas = ", ".join(str(s) for s in nu["seeds"][:10]) + (
            " ..." if len(nu["seeds"]) > 10 else ""
        )
        lines.append(
            f"| {st} | {lab} | {_pct(nu['false_alarms'])} | {cp} | {_pct(nu['claimed'])} "
            f"| {_pct(ef['rank1'])} "
            f"| {_pct(ef['rank1_strong'])} | {_pct(ef['rank1_strong_noise_only'])} "
            f"| {fas or '-'} | {miss or '-'} |"
        )
    lines += [
        "",
        "| effect | runs | rank 1 | ranked first instead | pulls | pull mean | pull std |",
        "|---|---|---|---|---|---|---|",
    ]
    for eff, row in summary["per_effect"].items():
        m = "-" if row["pull_mean"] is None else f"{row['pull_mean']:.2f}"
        s = "-" if row["pull_std"] is None else f"{row['pull_std']:.2f}"
        inst = ", ".join(f"{k} {v}" for k, v in row.get("first_instead", {}).items()) or "-"
        lines.append(
            f"| {eff} | {row['runs']} | {row['rank1']}/{row['runs']} | {inst} | {row['pull_n']} "
            f"| {m} | {s} |"
        )
    lines += _markdown_replicas(summary.get("replicas") or {})
    claims = ", ".join(f"{k} {v}" for k, v in summary.get("null_claims", {}).items())
    lines += ["", f"Claimed on nulls (effect: nulls): {claims or 'none'}."]
    lines += [
        "",
        "Goals: "
        + ", ".join(f"{k} {'PASS' if v else 'FAIL'}" for k, v in summary["goals"].items()),
    ]
    lines += [f"- {f}" for f in summary["failing"]]
    return "\n".join(lines) + "\n"


def _markdown_replicas(rep: dict) -> list:
    """The table of pulls over each case's noise replicas (none without replicas)."""
    if not rep.get("cases"):
        return []
    lines = [
        "",
        "Pulls over each case's noise replicas (the same case, the readings' noise drawn afresh):",
        "",
        "| seed | effect | replicas | parameter | pulls | mean | std |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in rep["cases"]:
        for name, p in c["params"].items():
            lines.append(
                f"| {c['seed']} | {c['effect']} | {c['replicas']} | {name} | {p['n']} "
                f"| {p['mean']:.2f} | {p['std']:.2f} |"
            )
    lines += ["", "| effect | cases | pulls | std about each case's mean |", "|---|---|---|---|"]
    for eff, row in rep["per_effect"].items():
        s = "-" if row["within_std"] is None else f"{row['within_std']:.2f}"
        lines.append(f"| {eff} | {row['cases']} | {row['n']} | {s} |")
    return lines
