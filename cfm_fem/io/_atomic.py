"""Write under a temporary name in the same folder, then rename: never half a file on disk."""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path

__all__ = [
    "atomic_path",
    "atomic_paths",
    "json_text",
    "temp_target",
    "write_json",
    "write_text",
]

#: The temporary names `atomic_path` and `atomic_paths` give: ``.<name>.<8 random>.<suffix>``
#: (`tempfile.mkstemp` with prefix ``.<name>.``; its random part is 8 of [a-z0-9_]).
_TEMP_NAME = re.compile(r"\.(?P<target>.+?\.(?P<ext>[^./]+))\.[a-z0-9_]{8}\.(?P=ext)")


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it to ``path`` only if the block succeeds.

    ``suffix`` defaults to the suffix of ``path`` (writers choose the format from it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=(path.suffix if suffix is None else suffix), dir=path.parent
    )
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs follow the umask
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def temp_target(name: str) -> str | None:
    """The file name whose temporary ``name`` is, if ``name`` is named like a temporary of
    `atomic_path` (e.g. ``".uf_up20um.vtu.k3x_9abq.vtu"`` -> ``"uf_up20um.vtu"``); else None.

    A killed process leaves such a file behind; the name alone cannot tell whose it was.
    """
    m = _TEMP_NAME.fullmatch(name)
    return None if m is None else m["target"]


@contextlib.contextmanager
def atomic_paths(paths):
    """`atomic_path` for several files that belong together: yield one temporary path beside each
    of ``paths`` and rename them all only once the whole block succeeded.

    A writer that fails on its third file then leaves none of the three (a ``summary.json``
    missing beside ``points.csv`` looked like a finished run).
    """
    paths = [Path(p) for p in paths]
    tmps = []
    try:
        with contextlib.ExitStack() as stack:
            for p in paths:
                tmps.append(stack.enter_context(_kept_temp(p)))
            yield tmps
            for tmp, p in zip(tmps, paths, strict=True):
                os.replace(tmp, p)
    finally:
        for tmp in tmps:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


@contextlib.contextmanager
def _kept_temp(path):
    """A temporary file beside ``path`` with the umask's permissions (the caller renames it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    yield Path(tmp)


def write_text(path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _jsonable(obj):
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj)}")


def json_text(data) -> str:
    """``data`` as indented JSON; numpy arrays and scalars become plain JSON.

    Raises
    ------
    ValueError
        NaN or infinity in ``data`` (not JSON).
    """
    return json.dumps(data, indent=2, default=_jsonable, allow_nan=False) + "\n"


def write_json(path, data) -> None:
    """Write ``data`` as indented JSON atomically; numpy arrays and scalars become plain JSON."""
    write_text(path, json_text(data))
