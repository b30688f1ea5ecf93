"""Write under a temporary name in the same folder, then rename: never half a file on disk."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import stat
import tempfile
import time
from pathlib import Path

__all__ = [
    "TEMPORARY_AGE_S",
    "atomic_path",
    "atomic_paths",
    "json_text",
    "remove_old_temporaries",
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


def check_free_space(folder, nbytes: int, what: str) -> None:
    """Refuse to write ``nbytes`` into ``folder`` when its file system has less free space
    (with a 1 MB margin): a full disk met before writing rather than in the middle.

    Raises
    ------
    OSError
        ``ENOSPC``, naming the file, the space needed and the space free; nothing written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(folder).free
    if free < nbytes + (1 << 20):
        raise OSError(
            errno.ENOSPC,
            f"{what} needs {mb(nbytes)}, {mb(free)} free",
            str(folder / what),
        )


def mb(nbytes: int) -> str:
    """``nbytes`` in MB for messages (``'12.3 MB'``)."""
    return f"{nbytes / 1e6:,.1f} MB" if nbytes >= 1e5 else f"{nbytes / 1e6:.2g} MB"


def temp_target(name: str) -> str | None:
    """The file name whose temporary ``name`` is, if ``name`` is named like a temporary of
    `atomic_path` (e.g. ``".uf_up20um.vtu.k3x_9abq.vtu"`` -> ``"uf_up20um.vtu"``); else None.

    A killed process leaves such a file behind; the name alone cannot tell whose it was.
    """
    m = _TEMP_NAME.fullmatch(name)
    return None if m is None else m["target"]


#: A temporary modified less than this long ago is left: it may be another run's, still being
#: written in the same folder. Its age is the robust test: a temporary lives only while its
#: writer writes that one file (`atomic_path`: made just before, renamed just after), so a live
#: writer's is never older than one file's write (a 1e6-node map: 74 s for all its maps side by
#: side, README), while a process id in the name would not tell a writer gone (another host on
#: a shared folder, another container's pid namespace, a reused pid). A modification time is the
#: file server's clock, compared with this host's: a skew of minutes is well within the hour.
TEMPORARY_AGE_S = 3600.0


def remove_old_temporaries(
    folder, names: re.Pattern, min_age_s: float = TEMPORARY_AGE_S, now: float | None = None
) -> list[Path]:
    """Remove the temporaries that killed writers left in ``folder`` (not its subfolders).

    Only regular files (no symbolic link) named like a temporary of `atomic_path`
    (`temp_target`) whose target name fully matches ``names``, and last modified at least
    ``min_age_s`` seconds before ``now`` (default: the time of the call), are removed: a younger
    one may be another process's file still being written (`TEMPORARY_AGE_S`).

    Returns
    -------
    list of Path
        The files removed, in name order.
    """
    now = time.time() if now is None else now
    removed = []
    for f in sorted(Path(folder).glob(".*")):
        target = temp_target(f.name)
        if target is None or not names.fullmatch(target):
            continue
        try:
            st = f.lstat()
        except OSError:  # renamed or removed by its writer meanwhile
            continue
        if stat.S_ISREG(st.st_mode) and now - st.st_mtime >= min_age_s:
            f.unlink(missing_ok=True)
            removed.append(f)
    return removed


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
    """Write ``data`` as indented JSON atomically; numpy arrays and scalars become plain JSON.

    Raises
    ------
    CfmInputError
        NaN or infinity in ``data``, naming the file and the key; nothing is written.
    """
    from ._finite import check_json_finite

    check_json_finite(path, data)
    write_text(path, json_text(data))
