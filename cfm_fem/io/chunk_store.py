"""On-disk store of finished sweep chunks: one ``.npz`` per chunk plus a ``manifest.json``.

Layout of ``DIR/.cfm_fem_chunks/``::

    manifest.json              the run key and what it was computed from (written first)
    chunk_<start>_<stop>.npz   arrays of nodes start .. stop-1 and the run key

Every file is written under a hidden temporary name and renamed, so a chunk file is always
complete. A run killed (SIGKILL) during a write cannot delete its temporary file; a run that
resumes from the store removes it once it is an hour old (`ChunkStore.remove_partial`; a younger
one may be another run's file still being written), and the store goes as a whole after a
successful run. What the arrays mean and when a store may be reused is decided by
:mod:`cfm_fem.workflows.sweep.resume`; this module only reads and writes files.
"""

from __future__ import annotations

import json
import re
import shutil
import zipfile
from pathlib import Path

import numpy as np

from ..errors import CfmInputError
from ._atomic import TEMPORARY_AGE_S, atomic_path, remove_old_temporaries, write_json

__all__ = ["STORE_NAME", "ChunkStore"]

#: Folder of the store inside the output folder.
STORE_NAME = ".cfm_fem_chunks"
_CHUNK = re.compile(r"^chunk_(\d+)_(\d+)\.npz$")
#: Files of the store written through a temporary (`atomic_path`).
_STORE_FILE = re.compile(r"chunk_\d+_\d+\.npz|manifest\.json")


class ChunkStore:
    """Chunk files of one output folder.

    Parameters
    ----------
    out_dir : path-like
        The output folder of the run; the store is ``out_dir / STORE_NAME``.
    """

    def __init__(self, out_dir):
        self.path = Path(out_dir) / STORE_NAME
        if self.path.is_symlink():  # its files would be written, read and removed elsewhere
            raise CfmInputError(
                "is a symbolic link; the chunk store must be a folder of the output folder "
                "(remove the link)",
                file=self.path,
            )

    def exists(self) -> bool:
        """True if the store folder is there."""
        return self.path.is_dir()

    def read_manifest(self) -> dict | None:
        """The manifest, or None if there is none or it cannot be read."""
        try:
            return json.loads((self.path / "manifest.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def write_manifest(self, manifest: dict) -> None:
        """Create the store (if needed) and write its manifest atomically."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CfmInputError(
                f"cannot create the chunk store: {exc.strerror or exc}", file=self.path
            ) from None
        write_json(self.path / "manifest.json", manifest)

    def chunk_path(self, start: int, stop: int) -> Path:
        """File of the chunk of nodes ``start .. stop-1``."""
        return self.path / f"chunk_{int(start)}_{int(stop)}.npz"

    def completed(self) -> list[tuple[int, int]]:
        """Node ranges (start, stop) that have a chunk file, sorted."""
        if not self.exists():
            return []
        found = []
        for p in self.path.iterdir():
            m = _CHUNK.match(p.name)
            if m:
                found.append((int(m[1]), int(m[2])))
        return sorted(found)

    def remove_partial(self, min_age_s: float = TEMPORARY_AGE_S) -> int:
        """Delete the temporary files that killed writers left; return how many.

        Only temporaries of the store's own files (``.chunk_<a>_<b>.npz.<8 random>.npz``,
        ``.manifest.json.<8 random>.json``) last modified at least ``min_age_s`` seconds ago go
        (`cfm_fem.io._atomic.remove_old_temporaries`): a younger one may be another process's
        file still being written, and any other file is left alone.
        """
        if not self.exists():
            return 0
        return len(remove_old_temporaries(self.path, _STORE_FILE, min_age_s))

    def save(self, start: int, stop: int, arrays: dict) -> None:
        """Write the arrays of one chunk atomically (uncompressed ``.npz``)."""
        with atomic_path(self.chunk_path(start, stop), suffix=".npz") as tmp, open(tmp, "wb") as f:
            np.savez(f, **arrays)

    def load(self, start: int, stop: int) -> dict | None:
        """Arrays of one chunk, or None if the file is missing or unreadable."""
        try:
            with np.load(self.chunk_path(start, stop), allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None

    def remove(self) -> None:
        """Delete the store and everything in it."""
        shutil.rmtree(self.path, ignore_errors=True)
