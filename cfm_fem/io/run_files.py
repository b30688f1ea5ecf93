"""The files of one run of any command, written into its output folder, each atomically.

Every command builds its documents in memory (JSON as dicts, CSV and HTML as text, figures as
PNG bytes) and hands them to `write_run` only after everything was computed, so a failure never
leaves part of a run on disk.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._atomic import atomic_path, write_json, write_text

__all__ = ["json_ready", "write_run"]


def json_ready(obj):
    """JSON has no NaN: non-finite floats become null (arrays become lists first)."""
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def write_run(out_dir, files: dict) -> list[Path]:
    """Write the files of one run into ``out_dir`` (created), each atomically.

    Parameters
    ----------
    out_dir : path-like
    files : dict of file name -> dict (JSON), str (text) or bytes (binary, e.g. PNG)

    Returns
    -------
    list of Path
        The files written, in the order given.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, content in files.items():
        path = out / name
        if isinstance(content, dict):
            write_json(path, json_ready(content))
        elif isinstance(content, str):
            write_text(path, content)
        else:
            with atomic_path(path) as tmp:
                tmp.write_bytes(bytes(content))
        written.append(path)
    return written
