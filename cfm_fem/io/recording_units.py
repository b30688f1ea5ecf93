"""Recordings in other units: read a tracker recording or a Hall map whose columns are not in
mm and T, and convert them once, here (the CSV contract itself is mm, mm/s and T)."""

from __future__ import annotations

import dataclasses

from ..models.recordings import Recording
from ..units import field_scale, length_scale
from .recordings import read_hall_map, read_tracker

__all__ = ["read_recording_in_units", "convert_recording"]


def convert_recording(rec: Recording, length_unit=None, field_unit=None) -> Recording:
    """``rec`` with its lengths read in ``length_unit`` and its field in ``field_unit``,
    converted to mm and T.

    Parameters
    ----------
    rec : Recording
        As read: numbers in the units of the file.
    length_unit : str, optional
        Unit of ``x_cmd, ..., x_meas, ...`` and of ``speed`` (per second): mm, m, in, ...
        None: mm.
    field_unit : str, optional
        Unit of ``Bx, By, Bz`` (Hall maps): T, mT, G, kG. None: T.

    Raises
    ------
    CfmInputError
        An unknown unit, or a field unit for a tracker recording.
    """
    changes = {}
    if length_unit is not None:
        s = length_scale(length_unit, column="--recording-length-unit")
        changes["cmd"] = rec.cmd * s
        if rec.meas is not None:
            changes["meas"] = rec.meas * s
        if rec.speed is not None:
            changes["speed"] = rec.speed * s
    if field_unit is not None:
        s = field_scale(field_unit, column="--recording-field-unit")
        if rec.B is None:
            from ..errors import CfmInputError

            raise CfmInputError(
                "a field unit applies to a Hall map; a tracker recording has no field",
                file=rec.source,
            )
        changes["B"] = rec.B * s
    return dataclasses.replace(rec, **changes) if changes else rec


def read_recording_in_units(path, kind: str, length_unit=None, field_unit=None) -> Recording:
    """Read a recording (``kind`` "tracker" or "hall") and convert it to mm and T
    (`convert_recording`)."""
    rec = (read_tracker if kind == "tracker" else read_hall_map)(path)
    return convert_recording(rec, length_unit, field_unit)
