"""The whole map's results of an out-of-core sweep (`cfm_fem.workflows.sweep.slabs`): the slabs'
records merged in slab order into ``summary.json`` (percentiles over per-node files on disk, in
bounded memory), and the maps written one slab piece at a time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...io.slab_files import SlabMapWriter, drop_pages, open_per_node, read_slab_piece
from ...models.field import FieldMap
from ...models.mesh import sliver_note, tie_note
from ...models.node_weights import weighted_percentiles
from ...models.sweep import assemble_result, harmonic_summary
from .problem import fallback_note

__all__ = [
    "disk_percentiles",
    "disk_weighted_percentiles",
    "merge_slabs",
    "write_slab_outputs",
]


def zero_sums(n_col: int) -> dict:
    """The counts a slab adds to the run's summary (`merge_slabs`)."""
    return dict(n_out=np.zeros(n_col, np.int64), n_lost=np.zeros(n_col, np.int64), processed=0,
                star=0, dis=np.zeros((n_col, 4), np.int64), cells=0, halo_nodes=0,
                unreachable=0, slivers=0, ties=0)  # fmt: skip


def merge_slabs(records: dict, K: int, work: Path, lay, n: int, notes: list, file: str) -> dict:
    """The run's summary from the slabs' records (merged in slab order: the same summary
    however the slabs ran) and the per-node files in ``work``.

    Parameters
    ----------
    records : dict of int -> dict
        Each slab's done record (``sums``, ``mesh_notes``, ``template``, ``fit_box``).
    K : int
        Number of slabs.
    work : Path
        The work folder (``uf.npy``, ``complete.npy``, ``volume.npy``, ``e2.npy``, ``fit.npy``).
    lay : `cfm_fem.workflows.sweep.slabs._Layout`
    n : int
        Nodes of the map (duplicates merged).
    notes : list of str
    file : str
    """
    cfg, n_col, htm = lay.cfg, lay.n_col, lay.htm
    sums, template, mesh_notes = zero_sums(n_col), None, []
    for k in range(K):
        record = records[k]
        for key, v in record["sums"].items():
            sums[key] = sums[key] + (np.asarray(v, dtype=np.int64) if np.ndim(v) else v)
        mesh_notes += [m for m in record["mesh_notes"] if m not in mesh_notes]
        template = template or record["template"]
    uf_all = open_per_node(work / "uf.npy", "r")
    ok_all = open_per_node(work / "complete.npy", "r")
    vol_all = open_per_node(work / "volume.npy", "r")
    notes = list(notes)
    if htm:  # as SweepResult.column_up_um, over the whole map
        e2_all = open_per_node(work / "e2.npy", "r")
        ups = [float(np.sqrt(np.nanmean(e2_all[:, k])) * 1e3) for k in range(n_col)]
        if sums["unreachable"]:
            notes.append(f"{sums['unreachable']} node(s) lie outside the strokes of the bench's "
                         "axes: no statistics (NaN)")  # fmt: skip
    else:
        ups = [float(u) for u in cfg.up_um]
    if sums["ties"]:
        mesh_notes.append(tie_note(int(sums["ties"]), lay.span))
    if sums["slivers"]:
        mesh_notes.append(sliver_note(int(sums["slivers"])))
    harmonic = "harmonic" in template
    if harmonic:
        n_linear = int((open_per_node(work / "fit.npy", "r")[:, 0] == 0).sum())
        if n_linear:
            mesh_notes.append(fallback_note(n_linear, n, template["harmonic"]["fallback_rule"]))
    summary = _summary(template, ups, n, (uf_all, ok_all, vol_all), sums, notes + mesh_notes,
                       lay.kind, file)  # fmt: skip
    if harmonic:  # the whole map's fits, from the per-node file and the slabs' boxes
        boxes = [records[k]["fit_box"] for k in range(K) if records[k].get("fit_box")]
        box = None
        if boxes:
            box = [np.min([b[0] for b in boxes], axis=0).tolist(),
                   np.max([b[1] for b in boxes], axis=0).tolist()]  # fmt: skip
        fit_all = open_per_node(work / "fit.npy", "r")
        summary.update(harmonic_summary(fit_all[:, 0].astype(np.int64),
                                        fit_all[:, 1] / lay.b_ref * 1e4, box,
                                        template["harmonic"]))  # fmt: skip
        del fit_all
    summary["slabs"] = {
        "count": K,
        "axis": "xyz"[lay.plan.axis],
        "edges_mm": [float(e) for e in lay.plan.edges],
        "halo_mm": float(lay.halo),
        "halo_rule": f"{lay.halo_cells:g} cell sizes ({lay.step:.6g} mm) + {lay.reach} "
        f"({6 * lay.sigma * 1e3:.6g} um), doubled per slab where a cell of an own node was not "
        "certified",
        "halo_outside_nodes": int(sums["halo_nodes"]),
    }
    if sums["halo_nodes"]:
        summary["notes"].append(
            f"{sums['halo_nodes']} node(s) had trials whose walk reached the halo border of their "
            f"slab: those trials are counted as outside"
            + (" and left out (not extrapolated)" if cfg.outside == "extrapolate" else "")
            + " (use fewer slabs or a wider halo)"
        )
    return summary


def write_slab_outputs(out: Path, store, K: int, cfg, b_ref: float, summary: dict) -> None:
    """One map piece per slab and U_p value, the .pvtu indices, sweep.pvd, summary.json; each
    piece's statistics assembled (`assemble_result`) from the slabs' stored arrays."""
    writer = SlabMapWriter(out, summary, cfg, b_ref)
    harmonic = "harmonic" in summary
    htm = cfg.mode == "htm"
    for p in range(K):
        cells, ghost, g = read_slab_piece(store, p, K, harmonic)
        sub = FieldMap(points=g["points"], B=g["B"], source=summary["source"])
        fit = {"degree": g["fit_degree"], "residual_T": g["fit_residual"]} if harmonic else None
        parts = (g["stats"], g["n_out"], g["n_lost"], g["star"], g["pos"] if htm else None)
        res = assemble_result(sub, None, cfg, b_ref, parts, g["gradient"],
                              n_left_out=g["n_left"], field_fit=fit,
                              node_volume_mm3=g["volume"])  # fmt: skip
        writer.write_piece(p, res, cells, ghost)
    writer.finish(K)


def disk_percentiles(chunks, qs, in_memory_limit: int = 1 << 22):
    """``np.percentile(values, qs)`` (linear) of values given in chunks, bit for bit.

    Parameters
    ----------
    chunks : callable() -> iterable of ndarray
        Yields the values (float64, finite) chunk by chunk; called several times.
    qs : sequence of float
        Percentiles, 0..100.
    in_memory_limit : int
        Up to this many values they are gathered and numpy is called; beyond, exact order
        statistics are found by histogram refinement, O(chunk) memory.

    Returns
    -------
    list of float or None
        None for every q when there are no values.
    """
    n = sum(len(c) for c in chunks())
    if n == 0:
        return [None for _ in qs]
    if n <= in_memory_limit:
        vals = np.concatenate(list(chunks()))
        return [float(np.percentile(vals, q)) for q in qs]
    out = []
    for q in qs:
        # numpy's linear method: virtual index (n - 1) * q / 100, then its _lerp
        vi = np.asarray((n - 1) * np.true_divide(q, 100))
        prev = np.floor(vi)
        gamma = np.asarray(vi - prev)
        i0 = int(prev)
        i1 = min(i0 + 1, n - 1)
        a, b = _order_stat(chunks, i0), _order_stat(chunks, i1)
        a, b = np.float64(a), np.float64(b)
        diff = b - a
        res = np.add(a, diff * gamma)
        if gamma >= 0.5:
            res = np.subtract(b, diff * (1 - gamma))
        out.append(float(res))
    return out


def _order_stat(chunks, rank, bins: int = 4096, gather: int = 1 << 20):
    """The value of 0-based ``rank`` in sorted order, by histogram refinement."""
    lo, hi = np.inf, -np.inf
    for c in chunks():
        if len(c):
            lo, hi = min(lo, c.min()), max(hi, c.max())
    below = 0  # values < lo
    while True:
        sel = [c[(c >= lo) & (c <= hi)] for c in chunks()]
        count = sum(len(s) for s in sel)
        if count <= gather or lo == hi:
            vals = np.sort(np.concatenate(sel))
            return float(vals[rank - below])
        edges = np.linspace(lo, hi, bins + 1)
        hist = np.zeros(bins, dtype=np.int64)
        for s in sel:
            hist += np.bincount(
                np.clip(np.searchsorted(edges, s, side="right") - 1, 0, bins - 1), minlength=bins
            )
        cum = np.cumsum(hist)
        j = int(np.searchsorted(cum, rank - below, side="right"))
        below += int(cum[j - 1]) if j else 0
        new_lo = edges[j]
        new_hi = edges[j + 1] if j + 1 < bins else hi
        new_hi = np.nextafter(new_hi, -np.inf) if j + 1 < bins else new_hi
        if new_lo == lo and new_hi == hi:  # cannot split further
            vals = np.sort(np.concatenate(sel))
            return float(vals[rank - below])
        lo, hi = new_lo, max(new_hi, new_lo)


def disk_weighted_percentiles(chunks, qs, in_memory_limit: int = 1 << 22, bins: int = 4096):
    """`cfm_fem.models.node_weights.weighted_percentiles` of values and weights given in
    chunks: the same figures, in O(chunk) memory beyond ``in_memory_limit`` values.

    Parameters
    ----------
    chunks : callable() -> iterable of (ndarray, ndarray)
        Yields (values, weights) chunk by chunk (values finite, weights >= 0); called several
        times.
    qs : sequence of float
        Percentiles, 0..100.

    Returns
    -------
    list of float or None
    """
    pairs = lambda: ((v[w > 0], w[w > 0]) for v, w in chunks())  # noqa: E731
    n = sum(len(v) for v, _ in pairs())
    if n == 0:
        return [None for _ in qs]
    if n <= in_memory_limit:
        parts = list(pairs())
        return weighted_percentiles(
            np.concatenate([v for v, _ in parts]), np.concatenate([w for _, w in parts]), qs
        )
    total = sum(float(w.sum()) for _, w in pairs())
    return [_weighted_stat(pairs, q / 100.0 * total * (1.0 - 1e-12), in_memory_limit, bins)
            for q in qs]  # fmt: skip


def _weighted_stat(pairs, target, gather, bins):
    """The smallest value whose cumulative weight (values in increasing order) reaches
    ``target``, by weighted histogram refinement."""
    lo, hi = np.inf, -np.inf
    for v, _ in pairs():
        if len(v):
            lo, hi = min(lo, v.min()), max(hi, v.max())
    below = 0.0  # weight of the values < lo
    while True:
        sel = [(v[(v >= lo) & (v <= hi)], w[(v >= lo) & (v <= hi)]) for v, w in pairs()]
        count = sum(len(v) for v, _ in sel)
        if count <= gather or lo == hi:
            vals = np.concatenate([v for v, _ in sel])
            order = np.argsort(vals, kind="stable")
            cum = below + np.cumsum(np.concatenate([w for _, w in sel])[order])
            i = min(int(np.searchsorted(cum, target, side="left")), len(vals) - 1)
            return float(vals[order[i]])
        edges = np.linspace(lo, hi, bins + 1)
        hist = np.zeros(bins)
        for v, w in sel:
            idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, bins - 1)
            hist += np.bincount(idx, weights=w, minlength=bins)
        cum = below + np.cumsum(hist)
        j = min(int(np.searchsorted(cum, target, side="left")), bins - 1)
        below = float(cum[j - 1]) if j else below
        new_lo = edges[j]
        new_hi = np.nextafter(edges[j + 1], -np.inf) if j + 1 < bins else hi
        if new_lo == lo and new_hi == hi:  # cannot split further
            gather = count
            continue
        lo, hi = new_lo, max(new_hi, new_lo)


def _summary(template, ups, n, per_node, sums, notes, kind, file):
    uf_all, ok_all, vol_all = per_node
    s = dict(template)
    n_col = len(ups)
    step = 1 << 20

    def blocks(k):
        for a in range(0, n, step):
            ok = np.array(ok_all[a : a + step, k])
            yield np.array(uf_all[a : a + step, k])[ok], np.array(vol_all[a : a + step, 0])[ok]
            for arr in (uf_all, ok_all, vol_all):  # one block resident at a time
                drop_pages(getattr(arr, "_mmap", None))

    def column(k):
        return lambda: (v for v, _ in blocks(k))

    pct = {"p50": [], "p95": [], "p99": [], "max": []}
    per = {"p50": [], "p95": [], "p99": [], "max": []}
    uf_nodes, uf_volume = [], []
    for k in range(n_col):
        vals = disk_percentiles(column(k), [50, 95, 99, 100])
        for name, v in zip(per, vals, strict=True):
            per[name].append(v)
        weighted = disk_weighted_percentiles(lambda k=k: blocks(k), [50, 95, 99])
        for name, v in zip(("p50", "p95", "p99"), weighted, strict=True):
            pct[name].append(v)
        pct["max"].append(per["max"][-1])
        uf_nodes.append(int(sum(len(c) for c in column(k)())))
        uf_volume.append(sum(float(w.sum()) for _, w in blocks(k)))
    volume = sum(float(np.asarray(vol_all[a : a + step, 0]).sum()) for a in range(0, n, step))
    n_samples = max(sums["processed"], 1) * s["trials"]
    s["up_um"] = list(ups)
    s["uf_units"] = pct
    s["uf_units_per_node"] = per
    s["region_nodes"] = int(n)
    s["region_volume_mm3"] = volume
    s["uf_volume_fraction"] = [v / volume if volume > 0 else None for v in uf_volume]
    s["uf_nodes"] = uf_nodes
    s["nodes"] = int(n)
    s["processed_nodes"] = int(sums["processed"])
    s["outside_fraction"] = [float(v / n_samples) for v in sums["n_out"]]
    s["walk_failed_fraction"] = [float(v / n_samples) for v in sums["n_lost"]]
    s["gum_disagree_fraction"] = [
        {name: (float(sums["dis"][k, c] / uf_nodes[k]) if uf_nodes[k] else None)
         for c, name in enumerate(("Bx", "By", "Bz", "absB"))}
        for k in range(n_col)
    ]  # fmt: skip
    s["gum_disagree_nodes"] = [
        {name: int(sums["dis"][k, c]) for c, name in enumerate(("Bx", "By", "Bz", "absB"))}
        for k in range(n_col)
    ]
    s["linear_in_up_fraction"] = (
        float(sums["star"] / sums["processed"]) if sums["processed"] else None
    )
    s["interpolation"] = s["interpolation"].rsplit(";", 1)[0] + f"; {sums['cells']} simplices"
    s["notes"] = list(notes)
    s["source"] = file
    return s
