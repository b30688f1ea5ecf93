"""Outputs of ``cfm-fem diagnose``: diagnosis.json, report.html, PNG plots, residual .vtu maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._atomic import atomic_path, write_json, write_text
from .vtk import write_vtu

__all__ = ["write_diagnosis"]


def _clean(obj):
    """Make a summary JSON-safe: non-finite floats become None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_diagnosis(out_dir, summary: dict, arrays: dict, report_html, images: dict) -> dict:
    """Write every output atomically; return the paths written.

    Parameters
    ----------
    out_dir : path-like
    summary : dict
        The ``diagnosis.json`` document, `cfm_fem.workflows.diagnose.workflow.Diagnosis.summary`
        (keys ``mismatch``, ``located``, ``effects``, ``fit``, ``advice``, plus extra keys).
    arrays : dict
        ``point_pos`` (m, 3) mm, ``zp_before``/``zp_after`` (m, 3), ``sig_before`` (m, 3) bool,
        ``pos`` (n, 3), ``resid_before``/``resid_after`` (n, 3), ``z_before`` (n, 3), ``rep``.
    report_html : str or None
        The report (`cfm_fem.report.diagnosis.diagnosis_report`), written as ``report.html``;
        None: no report (``--no-report``).
    images : dict of file name -> bytes
        PNG figures (``fit.png``, ...), written beside it.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, png in images.items():
        p = out / name
        with atomic_path(p) as tmp:
            tmp.write_bytes(png)
        paths[name.removesuffix(".png")] = p
    unit = summary["fit"]["unit"]
    pts = arrays["point_pos"]
    write_vtu(
        out / "residual_points.vtu",
        pts,
        point_data={
            "z_mean_before": arrays["zp_before"].astype(np.float32),
            "z_mean_after": arrays["zp_after"].astype(np.float32),
            "significant_before": arrays["sig_before"].astype(np.int8),
        },
        field_data={"n_reps": float(summary["fit"]["n_reps"])},
    )
    write_vtu(
        out / "residual_rows.vtu",
        arrays["pos"],
        point_data={
            f"resid_before_{unit}": arrays["resid_before"].astype(np.float32),
            f"resid_after_{unit}": arrays["resid_after"].astype(np.float32),
            "z_before": arrays["z_before"].astype(np.float32),
            "rep": arrays["rep"].astype(np.int32),
        },
    )
    paths["vtu_points"] = out / "residual_points.vtu"
    paths["vtu_rows"] = out / "residual_rows.vtu"
    if report_html is not None:
        write_text(out / "report.html", report_html)
        paths["report"] = out / "report.html"
    write_json(out / "diagnosis.json", _clean(summary))  # last: its presence means complete
    paths["json"] = out / "diagnosis.json"
    return paths
