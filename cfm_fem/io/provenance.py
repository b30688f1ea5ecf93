"""What produced an output: input hashes, version, command line."""

from __future__ import annotations

import hashlib
import platform
from pathlib import Path

__all__ = ["file_sha256", "provenance"]


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def provenance(inputs: dict, command_line: str | None = None) -> dict:
    """Provenance record: ``inputs`` maps a role ('field', 'bench') to a path (or None)."""
    from .. import __version__

    files = {}
    for role, p in inputs.items():
        if p is not None:
            files[role] = {"path": str(Path(p)), "sha256": file_sha256(p)}
    return {
        "cfm_fem_version": __version__,
        "python": platform.python_version(),
        "command_line": command_line,
        "inputs": files,
    }
