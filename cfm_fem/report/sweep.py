"""The HTML report of ``cfm-fem sweep``: the paper's design curve (U_f against U_p), a slice
per U_p, U_f histograms, GUM flags, outside fractions, notes and provenance.

Numbers in the tables come from ``summary.json``; the figures from a `SweepDigest` of the maps.
"""

from __future__ import annotations

import json

from .html import HtmlReport
from .plots import count_histograms, fig4_curve, uf_slices
from .sweep_digest import SweepDigest

__all__ = ["sweep_report", "column_titles", "draw_sweep_report", "write_sweep_report"]

_COMPONENTS = ("absB", "Bx", "By", "Bz")


def column_titles(summary: dict) -> list[str]:
    """A title per column: ``U_p = 20 um`` (gauss), ``htm_total (U_p 23.4 um)`` (htm)."""
    if summary["mode"] == "gauss":
        return [f"U_p = {u:g} um" for u in summary["up_um"]]
    return [
        f"{c} (U_p {u:.3g} um)" for c, u in zip(summary["columns"], summary["up_um"], strict=True)
    ]


def _design_table(rep: HtmlReport, s: dict) -> None:
    pct = s["uf_units"]
    rows = []
    for k, title in enumerate(column_titles(s)):
        rows.append(
            [
                title,
                *(pct[q][k] for q in ("p50", "p95", "p99", "max")),
                s["uf_nodes"][k],
                100 * s["outside_fraction"][k],
                100 * s["walk_failed_fraction"][k],
            ]
        )
    rep.table(
        ["column", "U_f p50", "p95", "p99", "max", "nodes with U_f", "outside %", "walk failed %"],
        rows,
        table_id="uf_percentiles",
    )
    region = s.get("region_description", "the whole map")
    weighting = s.get("statistics_weighting", "")
    how = (
        "each node weighted by the volume it stands for (" + s["node_volume_rule"] + ")"
        if weighting.startswith("volume")
        else "every node counted once"
    )
    rep.paragraph(
        f"Percentiles of U_f over the nodes of {region} that have a U_f figure, {how}. A node "
        "has a U_f figure when every one of its trials has a value; a trial whose perturbed "
        f"position leaves the map is {s['outside_rule']}. {s['processed_nodes']} of "
        f"{s['nodes']} nodes simulated. Outside: share of all trials of the simulated nodes "
        "whose perturbed position left the map.",
        "note",
    )


def _gum_table(rep: HtmlReport, s: dict) -> None:
    rep.heading("GUM against Monte Carlo (GUM-S1 section 8)", 3)
    rows = []
    for title, share in zip(column_titles(s), s["gum_disagree_fraction"], strict=True):
        rows.append([title, *(None if share[c] is None else 100 * share[c] for c in _COMPONENTS)])
    rep.table(
        ["column", "|B| flagged %", "Bx %", "By %", "Bz %"], rows, table_id="gum_flags", digits=3
    )
    rep.paragraph(
        "Share of the nodes with a U_f figure whose linearised GUM interval differs from the "
        "Monte Carlo one beyond the tolerance: " + s["definitions"]["gum_disagree"],
        "note",
    )


def _design(rep: HtmlReport, d: dict) -> None:
    rep.heading("Design answer")
    rep.paragraph(d["answer"])
    region = "whole map" if d["region_mm"] is None else f"box {d['region_mm']} mm"
    rep.table(
        ["U_p [um]", f"p{100 * d['coverage']:g} of U_f [units]", "u [units]", "nodes"],
        [
            [u, p, s, n]
            for u, p, s, n in zip(
                d["up_um"], d["percentile_units"], d["u_percentile_units"], d["nodes"], strict=True
            )
        ],
        table_id="design",
        digits=4,
    )
    rep.paragraph(f"Region: {region} ({d['region_nodes']} nodes). {d['definition']}.", "note")


def sweep_report(
    summary: dict, digest: SweepDigest, command_line: str | None = None, design: dict | None = None
):
    """Report of ``cfm-fem sweep``.

    Parameters
    ----------
    summary : dict
        The sweep's ``summary.json`` document (`cfm_fem.models.sweep.summarize` plus provenance).
    digest : SweepDigest
        Histograms and plane nodes of its maps.
    command_line : str, optional
        Default: the one in the provenance.
    design : dict, optional
        The ``design.json`` document of ``cfm-fem design``: its answer goes on top.

    Returns
    -------
    HtmlReport
    """
    s = summary
    prov = s.get("provenance") or {}
    command_line = command_line or prov.get("command_line")
    titles = column_titles(s)
    rep = HtmlReport("Field uncertainty U_f over the map (cfm-fem sweep)")
    rep.paragraph(
        f"Map {s['source']} ({s['nodes']} nodes). B_ref = {s['b_ref_T']:.6g} T "
        f"({s['b_ref_rule']}); units = 1e-4 B_ref. {s.get('estimator_rule', s['trials'])}; seed "
        f"{s['seed']}; U_f of one node "
        f"known to +-{100 * s['uf_relative_mc_std']:.1f} % (1 sigma, Monte Carlo). Mode "
        f"{s['mode']}: {s['perturbation']}."
    )
    if design is not None:
        _design(rep, design)
    rep.heading("Design curve: U_f against U_p")
    _design_table(rep, s)
    pct = s["uf_units"]
    series = {q: [float("nan") if v is None else v for v in pct[q]] for q in ("p50", "p95", "max")}
    rep.figure(
        "uf_vs_up.png",
        fig4_curve(s["up_um"], series),
        "U_f (95 %) percentiles over the nodes with a U_f figure against U_p (paper Fig. 4): "
        "read off the U_p that keeps U_f below a target (cfm-fem design answers it with its "
        "Monte Carlo uncertainty).",
    )
    rep.heading("U_f on the plane through the axis")
    slices = [digest.plane(k) for k in range(len(titles))]
    rep.figure(
        "uf_slices.png",
        uf_slices(slices, titles, "U_f on the plane y = y0 nearest y = 0"),
        "Nodes on the plane nearest y = 0 coloured by U_f; grey: nodes without a U_f figure "
        "(trials left the map). Open sweep.pvd in ParaView (open_in_paraview.py) for any plane.",
    )
    rep.heading("Distribution of U_f over the nodes")
    rep.figure(
        "uf_histograms.png",
        count_histograms([digest.histogram(k) for k in range(len(titles))], titles, "U_f"),
        "Histogram of U_f over the nodes with a U_f figure, per column.",
    )
    _gum_table(rep, s)
    rep.heading("Notes", 3)
    rep.bullets(
        [
            f"interpolation: {s['interpolation']}",
            *(f"{k}: {v}" for k, v in s["definitions"].items()),
            *s["notes"],
        ]
    )
    rep.heading("Provenance", 3)
    rep.code(json.dumps(prov, indent=1, sort_keys=True))
    rep.heading("Reproduce", 3)
    rep.code(command_line or "(command line not recorded)")
    return rep


def draw_sweep_report(summary: dict, result, command_line: str | None = None,
                      design: dict | None = None) -> dict:  # fmt: skip
    """The report's files of a sweep still in memory, drawn before its maps are written (on a
    thread beside the map writers: VTK writes without the GIL).

    Parameters
    ----------
    summary : dict
        The ``summary.json`` document the run writes (as read back: `json_text` then
        `json.loads`).
    result : cfm_fem.models.sweep.SweepResult
    command_line, design : optional
        As `sweep_report`.

    Returns
    -------
    dict
        File name -> bytes or text: the PNG figures and ``report.html``, for `write_run`.
    """
    digest = SweepDigest.of_result(result, summary["uf_units"]["max"])
    rep = sweep_report(summary, digest, command_line, design)
    return {**rep.images, "report.html": rep.render()}


def write_sweep_report(
    out_dir, command_line: str | None = None, design: dict | None = None, result=None,
    drawn: dict | None = None,
):  # fmt: skip
    """Write ``report.html`` and its PNG figures beside a written sweep (its ``summary.json``
    and maps, read back one file at a time: bounded memory also for maps written as pieces);
    ``design``: the answer of ``cfm-fem design``, shown on top; ``result``: the
    `cfm_fem.models.sweep.SweepResult` (or `cfm_fem.models.sweep.CompactSweep`) the maps were
    written from, still in memory: the figures are drawn from it and the maps not read back;
    ``drawn``: the files `draw_sweep_report` made of this run, written as they are.

    Returns
    -------
    list of Path
        The files written.
    """
    from ..io.run_files import write_run
    from ..io.sweep_maps import iter_map_nodes, read_summary

    if drawn is not None:
        return write_run(out_dir, drawn)
    summary = read_summary(out_dir)
    if result is not None:
        digest = SweepDigest.of_result(result, summary["uf_units"]["max"])
    else:
        digest = SweepDigest(summary["uf_units"]["max"])
        for k, points, arrays in iter_map_nodes(out_dir):
            digest.add(k, points, arrays["U_f_units"], arrays["complete"] == 1)
    rep = sweep_report(summary, digest, command_line, design)
    return write_run(out_dir, {**rep.images, "report.html": rep.render()})
