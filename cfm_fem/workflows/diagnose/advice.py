"""Advice: what the diagnosis could not tell, why, and which measurement would tell it."""

from __future__ import annotations

from . import effects as fx
from .select import overlaps

__all__ = ["advise"]


def _overlap_advice(prob, o, cal, sel):
    strong = [nm for nm, b in (sel.rounds[0] if sel.rounds else []) if b > o["bic_min"]]
    if not strong:
        return [], []
    ov = overlaps(prob, cal.sigma0, cal.base, sel.candidates, list(dict.fromkeys(strong))[:6])
    out = []
    for a, b, val in ov:
        if val > o["overlap_max"] and (a in sel.selected or b in sel.selected) and a != b:
            other = b if a in sel.selected else a
            chosen = a if a in sel.selected else b
            out.append(
                f"'{chosen}' and '{other}' have nearly the same signature in these data "
                f"(overlap {val:.2f}): the choice rests on the smaller model. To separate "
                f"them: {fx.ADVICE[other]}; {fx.ADVICE[chosen]}."
            )
    return out, ov


def _absorption_advice(sel, absorption, absorbed):
    out = []
    for name in absorbed:
        by = sorted({b for a in absorption[name] for b in a["absorbed_by"]})
        out.append(
            f"'{name}' is absorbed: in these data its signature is reproduced by the baseline "
            f"parameters ({', '.join(by[:4]) or 'none: no signature'}), so it cannot be revealed "
            f"whatever its size. To reveal it: {fx.ADVICE[name]}."
        )
    released = {n for c in sel.accepted for n in c.released}
    for name, lst in absorption.items():
        lst = [a for a in lst if a["absorbed_by"]]  # parameters without any signature: silent
        if name in absorbed or not lst:
            continue
        by = sorted({b for a in lst for b in a["absorbed_by"]})
        hit = released.intersection(by)
        txt = (
            f"parameters {', '.join(a['name'] for a in lst)} of '{name}' are absorbed by the "
            f"baseline ({', '.join(by[:4])}): these data cannot reveal them"
        )
        if hit:
            txt += f"; the prior conflict found in {', '.join(sorted(hit))} may equally be {name}"
        out.append(f"{txt}. To reveal them: {fx.ADVICE[name]}.")
    return out


def _conflict_advice(conflicts):
    out = []
    for c in conflicts:
        route = (
            f"modelled by '{c['effect']}' (its prior released)"
            if c["effect"]
            else "the registration of the instrument, not an effect of the bench"
        )
        out.append(
            f"the calibrated {c['name']} = {c['value']:.4g} +- {c['std']:.2g} {c['unit']} is "
            f"{abs(c['z']):.1f} sigma from its prior ({c['prior_mean']:.4g} +- "
            f"{c['prior_std']:.2g} {c['unit']}): the recording conflicts with the stated PDF, "
            f"which is {route}. Check the calibration or survey it comes from."
        )
    return out


def advise(
    prob, o, cal, sel, blocks, *, absorption, absorbed, implausible, untestable, conflicts, loc1
):
    """Advice sentences and the overlaps of the strongest candidates.

    Returns
    -------
    advice : list of str
    overlaps : list of (str, str, float)
    """
    advice, ov = _overlap_advice(prob, o, cal, sel)
    for c in implausible:
        advice.append(
            f"'{c['name']}' would fit (delta BIC {c['delta_bic']}) but only with physically "
            f"implausible parameters, so it is not claimed: {c['reason']}."
        )
    advice += _absorption_advice(sel, absorption, absorbed)
    advice += _conflict_advice(conflicts)
    for name, why in untestable.items():
        advice.append(f"{name} cannot be tested: {why}. To test it: {fx.ADVICE[name]}.")
    if loc1["located"]:
        where = "; ".join(f"{d['component']}: {d['where']}" for d in loc1["located"][:3])
        if sel.selected:
            advice.append(
                "significant residuals remain after the selected effects (" + where + "): an "
                "effect outside the catalogue, or one the data cannot separate; nothing more "
                "is claimed"
            )
        else:
            advice.append(
                "the recordings differ from the calibrated model where the residuals are "
                f"significant ({where}), but no catalogued effect explains it with enough "
                "evidence: a cause outside the catalogue; nothing is claimed. Check those "
                "regions and readings"
            )
    elif implausible and not sel.selected:
        advice.append(
            "the recordings differ from the calibrated model but no catalogued effect explains "
            "it with plausible parameters; nothing is claimed"
        )
    if cal.ident["n_not_identifiable"]:
        advice.append(
            f"{cal.ident['n_not_identifiable']} combinations of the bench parameters are not "
            "identifiable from these data (held at their priors): see calibration."
            "not_identifiable"
        )
    return advice, ov
