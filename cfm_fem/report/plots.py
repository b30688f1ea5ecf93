"""Figures of the reports (matplotlib); every function returns PNG bytes.

Figure analogues of the paper: Fig. 4 (U_f against U_p, and the map on the longitudinal plane),
Fig. 10 (systematic positioning error over the volume), Fig. 12 / 13 (95 % intervals of simulation
and experiment), and histograms of E_p and E_f with their coverage intervals.

Figures are `matplotlib.figure.Figure` objects saved by their own canvas, not pyplot's: no
global figure registry (the sweep draws its report on a thread beside the maps), and pyplot's
backend machinery is not imported.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.figure import Figure

__all__ = [
    "subplots",
    "png_bytes",
    "hist_figure",
    "interval_figure",
    "fig4_curve",
    "fig4_plane",
    "fig10_systematic",
    "residual_figure",
    "uf_slices",
    "count_histograms",
    "share_bars",
]

DPI = 110


def subplots(*args, figsize, **kwargs):
    """A new figure of ``figsize`` (inches) and its axes, as ``Figure.subplots(*args,
    **kwargs)`` makes them; returns (figure, axes)."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kwargs)


def png_bytes(fig, crop: bool = True) -> bytes:
    """Render ``fig`` to PNG bytes.

    ``crop``: trim the figure to its drawn content (``bbox_inches="tight"``), which draws it
    twice; a figure laid out already (``tight_layout``, ``constrained_layout``) passes False
    and is drawn once.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight" if crop else None)
    return buf.getvalue()


def _margins(fig, rows: int, cols: int, margins, gaps) -> None:
    """Place a ``rows`` x ``cols`` grid of panels by ``margins`` (left, right, bottom, top)
    and ``gaps`` between panels (across, down), in inches.

    Fixed margins, sized for the fonts the figures use, lay a figure out without the extra
    text measurements of matplotlib's tight or constrained layout (most of a many-panel
    figure's drawing time)."""
    left, right, bottom, top = margins
    wgap, hgap = gaps
    w, h = fig.get_size_inches()
    aw = (w - left - right - (cols - 1) * wgap) / cols
    ah = (h - bottom - top - (rows - 1) * hgap) / rows
    fig.subplots_adjust(
        left=left / w, right=1.0 - right / w, bottom=bottom / h, top=1.0 - top / h,
        wspace=wgap / aw, hspace=hgap / ah,
    )  # fmt: skip


def _hist(ax, x, low, high, label, unit, color="C0"):
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    ax.hist(x, bins=80, color=color, alpha=0.75, density=True)
    for v, ls in ((low, "--"), (high, "--"), (float(np.mean(x)), "-")):
        ax.axvline(v, color="k", ls=ls, lw=1)
    ax.set_title(f"{label}: mean {np.mean(x):.3g}, 95 % [{low:.3g}, {high:.3g}]", fontsize=8)
    ax.set_xlabel(unit, fontsize=8)
    ax.tick_params(labelsize=7)


def hist_figure(panels, title: str) -> bytes:
    """Histograms with the mean (solid) and the 95 % interval (dashed).

    Parameters
    ----------
    panels : sequence of (samples (M,), low, high, label, unit)
    title : str
    """
    n = len(panels)
    cols = 3 if n in (5, 6, 9) else min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = subplots(rows, cols, figsize=(3.3 * cols, 2.6 * rows), squeeze=False)
    for k, (x, lo, hi, label, unit) in enumerate(panels):
        _hist(axes[k // cols][k % cols], x, lo, hi, label, unit, color=f"C{k % 10}")
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].set_visible(False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return png_bytes(fig)


def interval_figure(rows, unit: str, title: str, labels=("MC", "experiment")) -> bytes:
    """Fig. 12 / 13 analogue: systematic -+ 2u of simulation and experiment per quantity.

    Parameters
    ----------
    rows : list of dict
        `cfm_fem.workflows.compare.interval_view` rows.
    unit : str
        Axis label unit.
    """
    fig, ax = subplots(figsize=(1.6 + 1.3 * len(rows), 3.4))
    for i, r in enumerate(rows):
        for j, (side, lab) in enumerate(zip(("sim", "exp"), labels, strict=True)):
            d = r[side]
            x = i + (-0.12 if j == 0 else 0.12)
            ax.errorbar(
                x,
                d["systematic"],
                yerr=[[d["systematic"] - d["low"]], [d["high"] - d["systematic"]]],
                fmt="o" if j == 0 else "s",
                color=f"C{j}",
                capsize=4,
                label=lab if i == 0 else None,
            )
        ax.annotate(
            "overlap" if r["overlap"] else "NO overlap",
            (i, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(0, -10),
            textcoords="offset points",
            ha="center",
            fontsize=7,
        )
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xticks(range(len(rows)), [r["name"] for r in rows])
    ax.set_ylabel(unit)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return png_bytes(fig)


def fig4_curve(up_um, series: dict, paper=None, analytic=None) -> bytes:
    """U_f (95 %) against U_p.

    Parameters
    ----------
    up_um : sequence of float
    series : dict of label -> sequence of float (units), one value per U_p
    paper : dict of U_p -> U_f (units), optional
        The paper's figures, drawn as crosses.
    analytic : sequence of float, optional
        1.96 U_p |grad |B|| / B_ref, dashed.
    """
    fig, ax = subplots(figsize=(4.8, 3.4))
    for k, (lab, v) in enumerate(series.items()):
        ax.plot(up_um, v, "o-", color=f"C{k}", label=lab)
    if analytic is not None:
        ax.plot(up_um, analytic, "k--", lw=1, label="1.96 U_p |grad|B|| / B_ref")
    if paper:
        ax.plot(list(paper), list(paper.values()), "rx", ms=9, mew=2, label="paper (its magnet)")
    ax.set_xlabel("U_p [um]")
    ax.set_ylabel("U_f (95 %) [units of 1e-4 B_ref]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return png_bytes(fig, crop=False)


def _marker_size(n_points: int, area_pts: float) -> float:
    """Scatter marker area (pt^2) that fills about a third of ``area_pts`` (pt^2) for
    ``n_points`` points, between 6 and 60: dense maps stay readable, sparse ones visible."""
    return float(np.clip(area_pts / 3.0 / max(n_points, 1), 6.0, 60.0))


def fig4_plane(points, uf, up_um, title: str) -> bytes:
    """U_f on the longitudinal x-z plane, one panel per U_p (nodes near y = 0).

    Parameters
    ----------
    points : ndarray, shape (k, 3), mm
    uf : ndarray, shape (k, n_up), units
    up_um : sequence of float
    """
    panels = [(points, uf[:, k], f"U_p = {up:g} um") for k, up in enumerate(up_um)]
    return _xz_panels(panels, title)


def _xz_panels(panels, title: str) -> bytes:
    """Nodes on z (across) and x (up) coloured by U_f on one scale, one panel per
    (points (k, 3) mm, uf (k,) units, title); NaN (no U_f figure) drawn grey."""
    n = len(panels)
    cols = min(2, n)
    rows = (n + cols - 1) // cols
    first = panels[0][0] if panels else None
    same = all(np.array_equal(pts, first) for pts, _, _ in panels)  # one plane: shared axes
    fig, axes = subplots(rows, cols, figsize=(6.0 * cols, 2.9 * rows), squeeze=False,
                         sharex=same, sharey=same)  # fmt: skip
    _margins(fig, rows, cols, (0.8, 1.05, 0.45, 0.6), (0.85, 0.65))
    finite = [uf[np.isfinite(uf)] for _, uf, _ in panels]
    vmax = max((float(v.max()) for v in finite if v.size), default=1.0) or 1.0
    sc = None
    for k, (pts, uf, label) in enumerate(panels):
        ax = axes[k // cols][k % cols]
        size = _marker_size(len(pts), 6.0 * 72 * 2.9 * 72 * 0.6)
        bad = ~np.isfinite(uf)
        ax.scatter(pts[bad, 2], pts[bad, 0], s=size, marker="s", linewidths=0, color="0.8")
        sc = ax.scatter(
            pts[~bad, 2], pts[~bad, 0], c=uf[~bad], s=size, marker="s", linewidths=0,
            cmap="viridis", vmin=0, vmax=vmax,
        )  # fmt: skip
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("z [mm]", fontsize=9)
        ax.set_ylabel("x [mm]", fontsize=9)
        ax.tick_params(labelsize=8)
        if same:  # the axes' labels on the outer panels only
            ax.label_outer()
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].set_visible(False)
    if sc is not None:
        w, h = fig.get_size_inches()  # a bar in the right margin, beside the panels
        cax = fig.add_axes((1.0 - 0.85 / w, 0.45 / h, 0.15 / w, 1.0 - 1.05 / h))
        cb = fig.colorbar(sc, cax=cax)
        cb.set_label("U_f (95 %) [units of 1e-4 B_ref]", fontsize=9)
        cb.ax.tick_params(labelsize=8)
    fig.suptitle(title, fontsize=11)
    return png_bytes(fig, crop=False)  # laid out by its margins


def fig10_systematic(points, mean_um, title: str) -> bytes:
    """Fig. 10 analogue: systematic positioning error per point over the volume.

    Parameters
    ----------
    points : ndarray, shape (m, 3), mm
        Commanded axis positions.
    mean_um : ndarray, shape (m, 3), um
        Systematic error per point and axis.
    """
    fig = Figure(figsize=(11.0, 8.6))
    norm = np.sqrt((mean_um**2).sum(1))
    panels = [(f"E_{a}", mean_um[:, k]) for k, a in enumerate("xyz")] + [("|E|", norm)]
    size = _marker_size(len(points), 150.0 * 150.0)
    for k, (name, v) in enumerate(panels):
        ax = fig.add_subplot(2, 2, k + 1, projection="3d")
        sc = ax.scatter(
            points[:, 0], points[:, 2], points[:, 1], c=v, cmap="coolwarm", s=size, depthshade=False
        )
        ax.set_xlabel("x [mm]", fontsize=9, labelpad=6)
        ax.set_ylabel("z [mm]", fontsize=9, labelpad=6)
        ax.set_zlabel("y [mm]", fontsize=9, labelpad=6)
        ax.tick_params(labelsize=8)
        ax.set_title(f"systematic {name}", fontsize=10)
        cb = fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.14)
        cb.set_label(f"{name} [um]", fontsize=9)
        cb.ax.tick_params(labelsize=8)
    fig.suptitle(title, fontsize=11)
    fig.subplots_adjust(left=0.02, right=0.95, bottom=0.04, top=0.92, wspace=0.15, hspace=0.15)
    return png_bytes(fig)


def residual_figure(z, labels, title: str) -> bytes:
    """Histogram of standardised residuals per quantity against the standard normal."""
    z = np.asarray(z, dtype=np.float64)
    fig, axes = subplots(1, z.shape[1], figsize=(3.0 * z.shape[1], 2.6), squeeze=False)
    grid = np.linspace(-4, 4, 200)
    for k, lab in enumerate(labels):
        ax = axes[0][k]
        v = z[:, k][np.isfinite(z[:, k])]
        if v.size:
            ax.hist(v, bins=20, density=True, alpha=0.7, color=f"C{k}")
        ax.plot(grid, np.exp(-0.5 * grid**2) / np.sqrt(2 * np.pi), "k--", lw=1)
        ax.set_title(f"{lab}: {np.mean(np.abs(v) > 2) * 100:.0f} % beyond |z| > 2", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return png_bytes(fig)


def uf_slices(slices, labels, title: str) -> bytes:
    """U_f on a plane y = const, one panel per column (z across, x up; one colour scale;
    grey: nodes without a U_f figure).

    Parameters
    ----------
    slices : sequence of `cfm_fem.report.sweep_digest.PlaneSlice`
    labels : sequence of str
        Panel titles (``U_p = 20 um``).
    """
    panels = [(s.points, s.uf, f"{label} (y = {s.y_mm:.3g} mm)")
              for s, label in zip(slices, labels, strict=True)]  # fmt: skip
    return _xz_panels(panels, title)


def count_histograms(histograms, labels, title: str, unit: str = "units") -> bytes:
    """Histograms given as counts, one panel each.

    Parameters
    ----------
    histograms : sequence of (edges (b + 1,), counts (b,))
    labels : sequence of str
    """
    n = len(histograms)
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig, axes = subplots(rows, cols, figsize=(3.6 * cols, 2.5 * rows), squeeze=False)
    for k, ((edges, counts), label) in enumerate(zip(histograms, labels, strict=True)):
        ax = axes[k // cols][k % cols]
        ax.stairs(counts, edges, fill=True, color=f"C{k % 10}", alpha=0.75)
        ax.set_title(f"{label}: {int(np.sum(counts))} nodes", fontsize=8)
        ax.set_xlabel(unit, fontsize=7)
        ax.tick_params(labelsize=6)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].set_visible(False)
    fig.suptitle(title, fontsize=9)
    _margins(fig, rows, cols, (0.5, 0.15, 0.4, 0.5), (0.5, 0.6))
    return png_bytes(fig, crop=False)


def share_bars(names, shares, title: str) -> bytes:
    """Horizontal bars of each name's share per axis.

    Parameters
    ----------
    names : list of str, length k
    shares : ndarray, shape (k, 3)
        Per name and axis X, Y, Z (any unit, e.g. %).
    title : str
    """
    k = len(names)
    fig, ax = subplots(figsize=(7.0, 0.45 * k + 1.2))
    y = np.arange(k)
    for a, label in enumerate("XYZ"):
        ax.barh(y + (a - 1) * 0.27, shares[:, a], height=0.27, label=label)
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.axvline(0.0, color="k", lw=0.6)
    ax.legend(loc="lower right")
    ax.set_title(title)
    return png_bytes(fig)
