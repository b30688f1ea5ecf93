"""One run at a time per output folder: an OS advisory lock on ``DIR/.cfm_fem.lock``.

Two runs writing into the same folder at once corrupt each other: a sweep without ``--resume``
deletes the chunk store ``DIR/.cfm_fem_chunks`` on start (the other run's chunks included), its
end deletes the store and the maps its ``sweep.pvd`` does not name (maybe the other run's), and
the files of two runs end up mixed. Every command that writes into ``--out`` holds
`output_lock` for the whole run, so a second run into a folder in use stops at once with a
message naming the run that holds it; nothing in the folder is written or removed.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import functools
import json
import os
import shlex
import socket
import sys
import threading
import warnings
from pathlib import Path

from ..errors import CfmInputError, CfmInputWarning

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["LOCK_NAME", "output_lock", "locks_output", "lock_holder"]

#: The lock file inside the output folder. Hidden, and named like no output, temporary
#: (`cfm_fem.io._atomic.temp_target`) or store: no clean-up of a sweep touches it.
LOCK_NAME = ".cfm_fem.lock"

#: Folders this process holds the lock of: real path -> descriptor. A writer called
#: inside a command that holds the lock (`cfm_fem.io.sweep_out.write_sweep` in ``cfm-fem
#: sweep``) takes it again: a second descriptor would be a second holder to flock (locks belong
#: to the open file description), and the run would refuse itself.
_HELD: dict[str, int] = {}
_HELD_GUARD = threading.Lock()
#: Attempts to lock the file the name refers to (`_acquire`); more are needed only while other
#: runs remove lock files as fast as they fail.
_ATTEMPTS = 20


@contextlib.contextmanager
def output_lock(out_dir, command: str | None = None, option: str = "--out"):
    """Hold the exclusive lock of the output folder ``out_dir`` for the block.

    The lock is ``fcntl.flock(LOCK_EX | LOCK_NB)`` on ``out_dir/.cfm_fem.lock`` (`LOCK_NAME`):
    an advisory lock of the operating system, taken without waiting. It belongs to this
    process's open file, so the kernel releases it when the process ends in any way (also
    SIGKILL or a crash): a killed run leaves no stale lock, and the file it leaves (with the
    killed run's record in it) is taken over by the next run. After locking, the holder's pid,
    host, start time (ISO 8601) and command are written into the file for the message of a run
    that finds the folder in use.

    ``out_dir`` (and missing parents) are created. A block that ends in an exception (bad
    input, Ctrl-C, a failed write) removes the lock file if this call created it, then the
    folders this call created if they are empty: a run that fails leaves the folder as it was,
    or no folder. A block that succeeds leaves the lock file (it is not an output, and no
    clean-up removes it): deleting it on exit would let a run that opened it just before lock
    a file no longer in the folder while a third run locks a new one. For the failure case,
    each run checks after locking that the name still refers to the file it locked, and
    starts again if not.

    Re-entrant within a process: a nested `output_lock` of the same folder (a writer called by
    a command that holds it) shares the outer lock, so it does not keep two threads of one
    process apart. Descriptors are not inherited by programs the process starts (Python's
    default), but a child made by ``fork`` without ``exec`` shares the lock.

    Without ``fcntl`` (Windows) there is no lock and nothing is created: runs into the same
    folder are not kept apart there. A file system that refuses locks (some network mounts)
    gives a `CfmInputWarning` and the run goes on unlocked; on NFS, flock works across hosts
    where the server supports locks.

    Parameters
    ----------
    out_dir : path-like
        The output folder.
    command : str, optional
        What runs, for the message of another run (default: this process's ``sys.argv``).
    option : str
        The option or parameter that named the folder, for the messages (``"--out"``).

    Yields
    ------
    Path or None
        The lock file; None when no lock is taken (Windows, a file system without locks, or a
        nested call).

    Raises
    ------
    CfmInputError
        Another process holds the lock ("DIR is in use by another cfm-fem run (pid N on HOST,
        started T: COMMAND); wait for it to finish or choose another --out"): nothing was
        written or removed. Or the folder or the lock file cannot be made (a file in the way, no
        permission, a read-only file system).
    """
    if fcntl is None:  # pragma: no cover - Windows: no advisory locks of this kind
        yield None
        return
    out = Path(out_dir)
    key = os.path.realpath(out)
    with _HELD_GUARD:
        nested = key in _HELD
    if nested:  # the outer call holds it, and releases it
        yield None
        return
    made = _make_folders(out, option)
    try:
        fd, created = _acquire(out, option, command)
    except BaseException:
        _remove_empty(made)
        raise
    if fd is not None:  # None: the file system takes no locks (warned)
        with _HELD_GUARD:
            _HELD[key] = fd
    ok = False
    try:
        yield None if fd is None else out / LOCK_NAME
        ok = True
    finally:
        if fd is not None:
            with _HELD_GUARD:
                _HELD.pop(key, None)
            try:
                if not ok and created:
                    _unlink_if_same(out / LOCK_NAME, fd)
            finally:
                os.close(fd)  # releases the lock
        if not ok:
            _remove_empty(made)


def locks_output(func):
    """Decorator of a writer whose first argument is its output folder: the call holds
    `output_lock` of that folder (named ``out_dir`` in the messages), as a command does."""

    @functools.wraps(func)
    def locked(out_dir, *args, **kwargs):
        with output_lock(out_dir, option="out_dir"):
            return func(out_dir, *args, **kwargs)

    return locked


def lock_holder(text: str) -> str:
    """The holder of a lock for a message, from the lock file's ``text``: ``"pid N on HOST,
    started T: COMMAND"``, or a note that the file names none (its holder has not written it
    yet, or an older cfm-fem wrote another format)."""
    try:
        rec = json.loads(text)
        return f"pid {rec['pid']} on {rec['host']}, started {rec['started']}: {rec['command']}"
    except (ValueError, TypeError, KeyError):
        return "its lock file does not say which"


def _make_folders(out: Path, option: str) -> list[Path]:
    """Create ``out`` and its missing parents; return the folders created, outermost first."""
    missing = []
    p = out
    while not p.exists() and not p.is_symlink() and p.parent != p:
        missing.append(p)
        p = p.parent
    made = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:
            continue  # made meanwhile by another run: not ours to remove
        except OSError as exc:
            _remove_empty(made)
            raise CfmInputError(
                f"{option} {str(out)!r} cannot be created: {exc.strerror or exc}"
            ) from None
        made.append(d)
    return made


def _remove_empty(made: list[Path]) -> None:
    """Remove the folders ``made`` (outermost first) that are empty, innermost first."""
    for d in reversed(made):
        try:
            d.rmdir()
        except OSError:
            return  # not empty: another run's files, or work kept for --resume


def _acquire(out: Path, option: str, command: str | None):
    """Lock ``out/LOCK_NAME``: (descriptor, whether this call created the file), or
    (None, False) on a file system without locks."""
    path = out / LOCK_NAME
    for _ in range(_ATTEMPTS):
        created = False
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o666)
            created = True
        except FileExistsError:
            try:
                fd = os.open(path, os.O_RDWR | _NOFOLLOW)
            except FileNotFoundError:
                continue  # removed by a run that failed: make it again
            except PermissionError:  # a read-only lock file locks as well
                fd = _open(path, os.O_RDONLY | _NOFOLLOW, out, option)
            except OSError as exc:  # a folder of that name, a symbolic link, ...
                raise _cannot(out, option, exc) from None
        except OSError as exc:
            raise _cannot(out, option, exc) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            text = os.pread(fd, 1 << 16, 0).decode("utf-8", "replace")
            os.close(fd)
            raise CfmInputError(
                f"{out} is in use by another cfm-fem run ({lock_holder(text)}); wait for it to "
                f"finish or choose another {option}"
            ) from None
        except OSError as exc:  # ENOLCK, EINVAL: no locks on this file system
            _close_and_unlink(fd, path, created)
            warnings.warn(
                f"{option} {out}: cannot lock {LOCK_NAME} ({exc.strerror or exc}); another run "
                "into this folder at the same time is not prevented",
                CfmInputWarning,
                stacklevel=4,
            )
            return None, False
        if not _same_file(path, fd):  # removed or replaced after it was opened: not the lock
            os.close(fd)
            continue
        _write_record(fd, command)
        return fd, created
    raise CfmInputError(  # pragma: no cover - needs lock files removed as fast as made
        f"{out}: could not lock {LOCK_NAME} in {_ATTEMPTS} attempts (other runs keep removing "
        f"it); try again or choose another {option}"
    )


def _open(path: Path, flags: int, out: Path, option: str) -> int:
    try:
        return os.open(path, flags)
    except OSError as exc:
        raise _cannot(out, option, exc) from None


#: Open the lock without following a symbolic link: a link planted in the output folder would
#: otherwise have the run truncate and write whatever file it points to.
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _cannot(out: Path, option: str, exc: OSError) -> CfmInputError:
    if exc.errno == errno.ELOOP or (out / LOCK_NAME).is_symlink():
        return CfmInputError(
            f"{option} {str(out)!r}: the lock file {LOCK_NAME} in it is a symbolic link; not "
            "followed (remove the link)"
        )
    return CfmInputError(
        f"{option} {str(out)!r}: cannot create the lock file {LOCK_NAME} in it: "
        f"{exc.strerror or exc}"
    )


def _same_file(path: Path, fd: int) -> bool:
    """True if ``path`` names the open file ``fd``."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    own = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)


def _unlink_if_same(path: Path, fd: int) -> None:
    """Remove ``path`` if it still names the locked file ``fd`` (never another run's)."""
    if _same_file(path, fd):
        with contextlib.suppress(OSError):
            os.unlink(path)


def _close_and_unlink(fd: int, path: Path, created: bool) -> None:
    if created:
        _unlink_if_same(path, fd)
    os.close(fd)


def _write_record(fd: int, command: str | None) -> None:
    """Write who holds the lock into it (in place: a renamed file would be another file)."""
    if command is None:
        command = shlex.join(["python", *sys.argv]) if sys.argv and sys.argv[0] else "python"
    started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    rec = {"pid": os.getpid(), "host": socket.gethostname(), "started": started,
           "command": command}  # fmt: skip
    data = (json.dumps(rec) + "\n").encode("utf-8")
    with contextlib.suppress(OSError):  # opened read-only: the lock holds without a record
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
