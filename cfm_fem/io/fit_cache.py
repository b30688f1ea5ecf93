"""Harmonic fits kept on disk between runs, keyed by what determines them.

A map's per-node harmonic fits (`cfm_fem.models.harmonic.fit_harmonic`) take seconds (46,051
nodes) to minutes (a million); a user who sweeps the same map again with other U_p values,
another bench or another trial count gets the same fits. They are kept in the user's cache
folder under a key hashed from the map's nodes and field (their bytes, whatever file they came
from), the fit's options and the source of the code that fits (so a changed fit never reads an
old one). A fit read back is the one that was stored, bit for bit.

The folder is ``$CFM_FEM_FIT_CACHE`` when set (``off``: no cache), else
``$XDG_CACHE_HOME/cfm_fem/fits`` or ``~/.cache/cfm_fem/fits``; a folder that cannot be written
means no cache, silently (the fit is computed as without one). The folder is kept under
`MAX_BYTES`: the files read least recently are removed first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .._numba_cache import user_cache_base
from ..models.harmonic import HarmonicFit, fit_harmonic
from ._atomic import atomic_path

__all__ = ["ENV", "MAX_BYTES", "cache_folder", "cached_fit", "fit_key"]

#: The environment variable naming the cache folder; ``off`` turns the cache off.
ENV = "CFM_FEM_FIT_CACHE"
#: The cache folder's bound, bytes (a 46,051-node map's fits take 21 MB).
MAX_BYTES = 2 * 1024**3
#: The modules whose source determines a fit (package-relative).
_FIT_SOURCES = ("models/harmonic.py", "models/harmonic_basis.py", "_kernels/harmonic_fit.py")
_PACKAGE = Path(__file__).resolve().parents[1]


def cache_folder(env=None) -> Path | None:
    """The fits' cache folder, or None when the cache is off.

    Parameters
    ----------
    env : mapping, optional
        The environment (default ``os.environ``).
    """
    env = os.environ if env is None else env
    given = env.get(ENV)
    if given:
        return None if given.strip().lower() == "off" else Path(given)
    base = user_cache_base(env)
    return None if base is None else base / "cfm_fem" / "fits"


def _code_fingerprint() -> bytes:
    h = hashlib.sha256(np.__version__.encode())
    for rel in _FIT_SOURCES:
        h.update((_PACKAGE / rel).read_bytes())
    return h.digest()


def fit_key(points, B, options: dict) -> str:
    """The cache key of the fits of ``B`` (n, 3) at ``points`` (n, 3) with ``options``.

    Returns
    -------
    str
        64 hexadecimal digits: SHA-256 of the fitting code's source, the options (JSON) and the
        nodes' and field's float64 bytes.
    """
    h = hashlib.sha256(_code_fingerprint())
    h.update(json.dumps(options, sort_keys=True, default=repr).encode())
    for a in (points, B):
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _load(path: Path, cls):
    """The fit stored at ``path``, or None if it is absent, unreadable or not of ``cls``."""
    names = [f.name for f in dataclasses.fields(cls)]
    try:
        with np.load(path, allow_pickle=False) as z:
            if sorted(z.files) != sorted(names):
                return None
            values = {n: z[n] for n in names}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return None
    for f in dataclasses.fields(cls):  # scalars were stored as 0-d arrays
        if values[f.name].ndim == 0:
            values[f.name] = values[f.name].item()
    with contextlib.suppress(OSError):
        os.utime(path)  # read recently: kept longest
    return cls(**values)


def _store(path: Path, fit) -> None:
    arrays = {f.name: np.asarray(getattr(fit, f.name)) for f in dataclasses.fields(fit)}
    with contextlib.suppress(OSError), atomic_path(path) as tmp:
        np.savez(tmp, **arrays)
    _prune(path.parent)


def _prune(folder: Path, max_bytes: int = MAX_BYTES) -> None:
    """Remove the least recently read fits until the folder holds at most ``max_bytes``."""
    with contextlib.suppress(OSError):
        files = [(p.stat().st_mtime, p.stat().st_size, p) for p in folder.glob("*.npz")]
        total = sum(s for _, s, _ in files)
        for _, size, p in sorted(files, key=lambda t: t[0]):
            if total <= max_bytes:
                break
            p.unlink(missing_ok=True)
            total -= size


def cached_fit(points, B, env=None, **options):
    """`fit_harmonic` of ``B`` at ``points``, read from the cache when it was stored there.

    Parameters
    ----------
    points : array_like, shape (n, 3), mm
    B : array_like, shape (n, 3), T
    env : mapping, optional
        The environment (`cache_folder`).
    **options
        Passed to `fit_harmonic`; all but ``source`` (a file name for messages) enter the key.

    Returns
    -------
    fit : HarmonicFit
    path : Path or None
        The cache file the fits were read from; None when they were fitted now.

    Raises
    ------
    CfmInputError
        As `fit_harmonic`.
    """
    folder = cache_folder(env)
    if folder is not None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            folder = None
    if folder is None:
        return fit_harmonic(points, B, **options), None
    keyed = {k: v for k, v in options.items() if k != "source"}
    path = folder / f"{fit_key(points, B, keyed)}.npz"
    fit = _load(path, HarmonicFit) if path.exists() else None
    if fit is not None:
        return fit, path
    fit = fit_harmonic(points, B, **options)
    _store(path, fit)
    return fit, None
