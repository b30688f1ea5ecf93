"""The finite-value contract of every writer: what cfm_fem writes, its readers take back.

A writer checks its numbers before it opens a file, so a run whose inputs drove a result to
NaN, infinity or an implausible size (a magnet offset of 1e9 mm gives fields of 1e104 T) stops
with one message naming the file, the column and the first bad row, and nothing is written.
The limits are the readers' (`cfm_fem.io._parse.MAX_COORD_MM`, `MAX_FIELD_T`).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import CfmInputError

__all__ = ["check_finite", "check_json_finite"]

#: The advice every refusal ends with: the numbers come from the run's inputs.
_ADVICE = "check the options and input files that produced it"


def check_finite(file, name: str, values, *, limit: float | None = None, unit: str = "",
                 allow_nan: bool = False) -> None:  # fmt: skip
    """Refuse to write ``values`` unless they are finite and within ``limit``.

    Parameters
    ----------
    file : path-like
        The file about to be written (named in the message).
    name : str
        The column or array, as the file names it (``'Bx'``, ``'x_cmd'``).
    values : array_like
        Numbers about to be written; rows along the first axis.
    limit : float, optional
        Largest magnitude allowed, in ``unit``.
    unit : str, optional
        Unit of ``values`` for the message.
    allow_nan : bool
        NaN is written on purpose (a node without statistics); infinity is still refused.

    Raises
    ------
    CfmInputError
        The first value that breaks the contract, with its row (1-based, in the order written).
    """
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return
    with np.errstate(invalid="ignore"):
        bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
        if limit is not None:
            bad |= np.abs(a) > limit
    if not bad.any():
        return
    where = np.unravel_index(int(np.argmax(bad)), a.shape)
    value = float(a[where])
    row = f" (row {where[0] + 1})" if a.ndim >= 1 and a.shape[0] > 1 else ""
    within = f" within +-{limit:g} {unit}".rstrip() if limit is not None else ""
    expected = "finite values" + ("" if not allow_nan else " or NaN") + within
    raise CfmInputError(
        f"not written: '{name}' would hold {value:.4g}{' ' + unit if unit else ''}{row}; "
        f"expected {expected}: {_ADVICE}",
        file=file,
    )


def check_json_finite(file, data) -> None:
    """Refuse to write JSON ``data`` that holds NaN or infinity (not JSON), naming the key.

    Raises
    ------
    CfmInputError
        The path of the first non-finite number (``uf_units.p95[3]``).
    """
    path = _first_non_finite(data, "")
    if path is not None:
        key, value = path
        raise CfmInputError(
            f"not written: '{key or '(top)'}' would hold {value}; expected finite numbers "
            f"(JSON has no NaN or infinity): {_ADVICE}",
            file=file,
        )


def _first_non_finite(obj, key):
    """(dotted key, value) of the first NaN or infinity in nested dicts, lists and arrays."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            found = _first_non_finite(v, f"{key}.{k}" if key else str(k))
            if found:
                return found
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            found = _first_non_finite(v, f"{key}[{i}]")
            if found:
                return found
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc" and obj.size and not np.isfinite(obj).all():
            i = int(np.argmax(~np.isfinite(obj.ravel())))
            return f"{key}[{i}]", float(obj.ravel()[i])
        if obj.dtype == object:
            return _first_non_finite(obj.tolist(), key)
    elif isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        return key, float(obj)
    return None
