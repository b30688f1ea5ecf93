"""Score diagnoses of simulated recordings against their truth, and summarise many of them.

Works on plain dicts: ``summary`` is a ``diagnosis.json`` as `cfm-fem diagnose` writes it,
``truth`` the ``.truth.json`` the simulator writes beside each recording.
"""

from __future__ import annotations

import numpy as np

__all__ = ["known_truth", "score", "summarise", "clopper_pearson_upper", "GOALS"]

#: The goals the proof checks.
GOALS = {
    "false_alarm_max": 0.01,  # share of nulls with any effect claimed
    "rank1_min": 0.95,  # share of runs with the concealed effect ranked first
    "pull_std": (0.8, 1.25),  # std of (fit - truth) / std over the runs of an effect
    "step_min": 0.95,  # share of step runs with the step located and no drift claimed
}


def known_truth(truth: dict, effect: str, param: str):
    """True value of a reported parameter (display units), or None when the truth has none.

    A parameter the simulation set (or drew: bench errors, registration, gains) has its value;
    any other parameter of a concealed effect is zero.
    """
    if param in truth["params"]:
        return float(truth["params"][param])
    if effect in truth["effects"]:
        return 0.0
    return None


def _step(summary, truth, names) -> dict:
    """Was the step located (a step effect named, or the x residual located by repetition with
    one sign from the step on and the other sign, or nothing, before), and was it claimed as
    drift?"""
    step = truth["effects"]["step_event"]
    reps = {}
    for loc in summary.get("located", []):
        w = str(loc.get("where", ""))
        if loc.get("component") == "x" and w.startswith("repetition "):
            reps[int(w.split()[1])] = float(loc.get("mean_z", 0.0))
    after = {np.sign(z) for r, z in reps.items() if r >= step["from_rep"]}
    before = {np.sign(z) for r, z in reps.items() if r < step["from_rep"]}
    split = len(after) == 1 and not (before & after) and 0.0 not in after
    return {
        "named": "step_event" in names,
        "located_reps": sorted(reps),
        "located": "step_event" in names or split,
        "claimed_drift": "thermal_drift" in names,
    }


#: A prior conflict is a true statement when the simulated value itself lies this many prior
#: standard deviations from the prior's mean.
TRUE_CONFLICT_SIGMA = 3.0


def true_conflicts(summary: dict, truth: dict) -> list:
    """Names of the prior conflicts a diagnosis states that the simulated truth itself has: the
    drawn value of the parameter lies at least :data:`TRUE_CONFLICT_SIGMA` prior standard
    deviations from the prior's mean (a survey drawn far in its tail is a real conflict)."""
    params = truth.get("params", {})
    out = []
    for c in summary.get("prior_conflicts", []):
        t, mean, std = params.get(c.get("name")), c.get("prior_mean"), c.get("prior_std")
        if t is None or mean is None or not (std or 0) > 0:
            continue
        if abs(float(t) - float(mean)) >= TRUE_CONFLICT_SIGMA * float(std):
            out.append(c["name"])
    return out


def score(summary: dict, truth: dict, model_dependent: bool = False) -> dict:
    """One diagnosis against its truth; ``model_dependent``: score the parameters the
    diagnosis reports as model-dependent too.

    Returns
    -------
    dict
        ``claimed`` (effect names, strongest first), ``detected``, ``rank1``, ``false_alarm``
        (a null with any effect claimed), ``alarm`` (a null with any effect claimed or a mismatch
        stated: a residual located, a plane called bad, a prior conflict the truth does not
        have), ``true_conflicts`` (:func:`true_conflicts`), ``mismatch_true`` (the mismatch
        is only such conflicts), ``other_claims``,
        ``pulls`` {effect: {param: pull}} of every reported parameter with a known truth (not
        those the diagnosis reports as ``model_dependent``), ``step`` (step case only).
    """
    names = [e["name"] for e in summary["effects"]]
    expected = truth.get("expected")
    pulls = {}
    for e in summary["effects"]:
        for p, v in e["params"].items():
            if p in e.get("model_dependent", ()) and not model_dependent:
                continue  # the parameter of an approximate shape: no truth shares its meaning
            t = known_truth(truth, e["name"], p)
            s = e.get("param_std", {}).get(p)
            if t is None or s is None or v is None or not s > 0:
                continue
            pulls.setdefault(e["name"], {})[p] = (float(v) - t) / float(s)
    true_c = true_conflicts(summary, truth)
    only_true = (
        bool(summary.get("mismatch"))
        and bool(true_c)
        and not summary.get("located")
        and not summary.get("outliers")
        and len(true_c) == len(summary.get("prior_conflicts", []))
    )
    out = {
        "case": truth.get("case"),
        "seed": truth.get("seed"),
        "kind": truth.get("kind"),
        "expected": expected,
        "claimed": names,
        "mismatch": bool(summary.get("mismatch")),
        "detected": None if expected is None else expected in names,
        "rank1": None if expected is None else bool(names) and names[0] == expected,
        "false_alarm": bool(names) if expected is None else None,
        "alarm": (bool(names) or (bool(summary.get("mismatch")) and not only_true))
        if expected is None
        else None,
        "true_conflicts": true_c,
        "mismatch_true": only_true,
        "other_claims": [n for n in names if n != expected],
        "pulls": pulls,
    }
    if "step_event" in truth["effects"]:
        out["step"] = _step(summary, truth, names)
    return out


def clopper_pearson_upper(k: int, n: int, level: float = 0.95) -> float:
    """Exact one-sided upper confidence bound of a binomial rate (k successes in n)."""
    from scipy import stats

    return 1.0 if k >= n else float(stats.beta.ppf(level, k + 1, n - k))


def _rate(flags):
    flags = [bool(f) for f in flags if f is not None]
    return (sum(flags), len(flags))


def summarise(scores: list) -> dict:
    """Per case: rates, pull statistics and the goals met (PASS/FAIL).

    Returns
    -------
    dict
        case -> {runs, kind, expected, detected, rank1, false_alarms, cp95_upper,
        other_claims, pulls {effect.param: (n, mean, std)} of every claimed effect, pull_mean
        and pull_std pooled over the concealed effect's parameters, step, goals}.
    """
    by_case = {}
    for s in scores:
        by_case.setdefault(s["case"], []).append(s)
    out = {}
    for case, runs in sorted(by_case.items()):
        ok = [r for r in runs if "error" not in r]
        row = {"runs": len(runs), "errors": len(runs) - len(ok), "kind": runs[0]["kind"]}
        row["expected"] = runs[0]["expected"]
        goals = {}
        if row["expected"] is None:
            k, n = _rate(r["false_alarm"] for r in ok)
            row["false_alarms"] = [k, n]
            row["cp95_upper"] = clopper_pearson_upper(k, n) if n else None
            row["mismatch"] = list(_rate(r["mismatch"] for r in ok))
            goals["false_alarms"] = bool(n) and k / n <= GOALS["false_alarm_max"]
        else:
            row["detected"] = list(_rate(r["detected"] for r in ok))
            row["rank1"] = list(_rate(r["rank1"] for r in ok))
            row["other_claims"] = list(_rate(bool(r["other_claims"]) for r in ok))
            k, n = row["rank1"]
            if row["expected"] != "step_event":
                goals["rank1"] = bool(n) and k / n >= GOALS["rank1_min"]
        per, pooled = {}, []
        for r in ok:
            for effect, pulls in r["pulls"].items():
                for p, v in pulls.items():
                    per.setdefault(f"{effect}.{p}", []).append(v)
                    if effect == row["expected"]:
                        pooled.append(v)
        row["pulls"] = {
            p: [len(v), float(np.mean(v)), float(np.std(v, ddof=1)) if len(v) > 1 else None]
            for p, v in sorted(per.items())
        }
        row["pull_mean"] = float(np.mean(pooled)) if pooled else None
        row["pull_std"] = float(np.std(pooled, ddof=1)) if len(pooled) > 1 else None
        if row["pull_std"] is not None:
            lo, hi = GOALS["pull_std"]
            goals["pull_std"] = lo <= row["pull_std"] <= hi
        steps = [r["step"] for r in ok if "step" in r]
        if steps:
            good = sum(s["located"] and not s["claimed_drift"] for s in steps)
            row["step"] = {
                "located": sum(s["located"] for s in steps),
                "claimed_drift": sum(s["claimed_drift"] for s in steps),
                "n": len(steps),
            }
            goals["step"] = good / len(steps) >= GOALS["step_min"]
        if row["errors"]:
            goals["runs"] = False
        row["goals"] = goals
        out[case] = row
    return out
