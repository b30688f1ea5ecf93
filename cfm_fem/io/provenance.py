"""What produced an output: input hashes, version, command line.

The same record goes into ``summary.json`` (key ``provenance``), into every ``.vtu`` (field data
``provenance_utf8``, the UTF-8 bytes of the JSON text, see `cfm_fem.io.sweep_out.provenance_text`)
and, as an XML comment that ParaView skips, into ``sweep.pvd`` and every ``.pvtu`` index
(`xml_comment`, read back with `read_xml_provenance`).
"""

from __future__ import annotations

import hashlib
import json
import platform
import re
from pathlib import Path

from ..errors import CfmInputError
from ._files import open_regular

__all__ = ["file_sha256", "bench_input", "provenance", "xml_comment", "read_xml_provenance"]

#: Start of the XML comment that carries the provenance JSON.
XML_TAG = "cfm_fem provenance:"


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes, hex; a file that cannot be read is a `CfmInputError` (the
    out-of-core sweep hashes its input before it reads it)."""
    h = hashlib.sha256()
    try:
        with open_regular(path, "an input file") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise CfmInputError(f"cannot read the file: {exc.strerror or exc}", file=path) from None
    return h.hexdigest()


def bench_input(path=None) -> dict:
    """The provenance entry of the bench file a run used: the file given, or (``path`` None)
    the packaged CFM reference bench that the commands fall back to.

    Returns
    -------
    dict
        ``path``, ``sha256`` of its bytes and ``packaged_default`` (True for the packaged
        reference bench ``cfm_fem/data/cfm_reference_bench.toml``).
    """
    if path is not None:
        return {"path": str(Path(path)), "sha256": file_sha256(path), "packaged_default": False}
    from importlib import resources

    from .bench_toml import REFERENCE_BENCH

    ref = resources.files("cfm_fem.data").joinpath(REFERENCE_BENCH)
    with resources.as_file(ref) as p:  # the installed file (a temporary copy from a zip)
        return {"path": str(p), "sha256": file_sha256(p), "packaged_default": True}


def provenance(inputs: dict, command_line: str | None = None) -> dict:
    """Provenance record: ``inputs`` maps a role ('field', 'bench') to a path (or None: not
    used), or to a ready entry such as `bench_input` gives."""
    from .. import __version__

    files = {}
    for role, p in inputs.items():
        if isinstance(p, dict):
            files[role] = dict(p)
        elif p is not None:
            files[role] = {"path": str(Path(p)), "sha256": file_sha256(p)}
    return {
        "cfm_fem_version": __version__,
        "python": platform.python_version(),
        "command_line": command_line,
        "inputs": files,
    }


def xml_comment(record: dict | None) -> str:
    """The provenance as one XML comment line, lossless.

    The JSON is ASCII (``ensure_ascii``) and every ``-`` that would make ``--`` (not allowed in
    an XML comment) is written as the JSON escape ``\\u002d``, which JSON reads back as ``-``;
    ``--`` can only occur inside JSON strings, so the text stays valid JSON.
    """
    text = json.dumps(record or {}, sort_keys=True, ensure_ascii=True)
    while "--" in text:
        text = text.replace("--", "-\\u002d")
    return f"<!-- {XML_TAG} {text} -->"


def read_xml_provenance(path) -> dict | None:
    """Provenance written by `xml_comment` into an XML file (``.pvd``, ``.pvtu``), or None."""
    text = Path(path).read_text(encoding="utf-8")
    m = re.search(r"<!-- " + re.escape(XML_TAG) + r" (.*?) -->", text, re.S)
    return None if m is None else json.loads(m.group(1))
