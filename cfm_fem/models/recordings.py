"""Recordings of a real bench: laser-tracker positions or Hall-probe field maps (no I/O here).

The file contract (CSV columns, units, what is refused) is given and enforced by
:mod:`cfm_fem.io.recordings`, which reads and writes it. A
`Recording` holds one row per acquisition (one point, one repetition) with the commanded axis
positions and either the measured probe position (``kind="tracker"``) or the measured field
(``kind="hall"``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import CfmInputError, CfmInputWarning

__all__ = ["KINDS", "Recording", "check_hall_scale", "check_tracker_scale"]

KINDS = ("tracker", "hall")


def _vec(a, name, n, dtype=np.float64):
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.shape != (n, 3):
        raise CfmInputError(f"Recording.{name} must have shape ({n}, 3); instead {a.shape}")
    return a


def _col(a, name, n, dtype=np.float64):
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.shape != (n,):
        raise CfmInputError(f"Recording.{name} must have shape ({n},); instead {a.shape}")
    return a


@dataclass
class Recording:
    """Rows of a tracker recording or a Hall map, converted to mm, T, s.

    Attributes
    ----------
    kind : {"tracker", "hall"}
    point_id : ndarray, shape (n,), int64
        Target point of each row; rows of one point share ``cmd``.
    rep : ndarray, shape (n,), int64
        Repetition number; (point_id, rep) is unique.
    cmd : ndarray, shape (n, 3), mm
        Commanded axis positions (tracker: bench axis frame; Hall map: magnet frame).
    meas : ndarray, shape (n, 3), mm, or None
        Measured probe (reflector) position in the bench frame; tracker recordings only.
    B : ndarray, shape (n, 3), T, or None
        Measured field (Bx, By, Bz); Hall maps only.
    t_s : ndarray, shape (n,), s, or None
        Time since the start of the recording.
    dir : ndarray, shape (n, 3), int8, or None
        Approach direction of each axis's own last move: -1, +1 (an axis that stood still
        keeps the direction of its earlier move), 0 when unknown.
    speed : ndarray, shape (n,), mm/s, or None
        Speed at acquisition, 0 for stop-and-go.
    vel : ndarray, shape (n, 3), mm/s, or None
        Signed axis velocities at acquisition (``v_x, v_y, v_z``); None when not recorded
        (the diagnosis then infers them from ``cmd``, ``t_s`` and ``speed``).
    temp_C : ndarray, shape (n,), degC, or None
    extra : dict of str to ndarray, shape (n,)
        Other columns, kept (float64 when every value is a number, else str) and ignored.
    source : str
        Where the rows came from (file path or a description).
    lines : ndarray, shape (n,), int64
        1-based source line of each row (0 when not read from a file).
    """

    kind: str
    point_id: np.ndarray
    rep: np.ndarray
    cmd: np.ndarray
    meas: np.ndarray | None = None
    B: np.ndarray | None = None
    t_s: np.ndarray | None = None
    dir: np.ndarray | None = None
    speed: np.ndarray | None = None
    vel: np.ndarray | None = None
    temp_C: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    source: str = "<memory>"
    lines: np.ndarray | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise CfmInputError(f"Recording.kind must be one of {KINDS}; instead {self.kind!r}")
        self.point_id = np.ascontiguousarray(self.point_id, dtype=np.int64).reshape(-1)
        n = self.point_id.shape[0]
        self.rep = _col(self.rep, "rep", n, np.int64)
        self.cmd = _vec(self.cmd, "cmd", n)
        if self.kind == "tracker":
            if self.meas is None or self.B is not None:
                raise CfmInputError("a tracker Recording needs meas (mm) and no B")
            self.meas = _vec(self.meas, "meas", n)
        else:
            if self.B is None or self.meas is not None:
                raise CfmInputError("a hall Recording needs B (T) and no meas")
            self.B = _vec(self.B, "B", n)
        for name in ("t_s", "speed", "temp_C"):
            if getattr(self, name) is not None:
                setattr(self, name, _col(getattr(self, name), name, n))
        if self.vel is not None:
            self.vel = _vec(self.vel, "vel", n)
        if self.dir is not None:
            d = _vec(self.dir, "dir", n, np.int64)
            if np.any(np.abs(d) > 1):
                raise CfmInputError("Recording.dir values must be -1, 0 or +1")
            self.dir = d.astype(np.int8)
        self.extra = {k: np.asarray(v) for k, v in self.extra.items()}
        for k, v in self.extra.items():
            if v.shape != (n,):
                raise CfmInputError(f"Recording.extra[{k!r}] must have shape ({n},); {v.shape}")
        self.lines = (
            np.zeros(n, dtype=np.int64)
            if self.lines is None
            else _col(self.lines, "lines", n, np.int64)
        )

    # ------------------------------------------------------------------ views

    def __len__(self) -> int:
        return int(self.point_id.shape[0])

    @property
    def values(self) -> np.ndarray:
        """``meas`` (mm) for a tracker recording, ``B`` (T) for a Hall map; shape (n, 3)."""
        return self.meas if self.kind == "tracker" else self.B

    def point_ids(self) -> np.ndarray:
        """Distinct point ids, sorted; shape (m,), int64."""
        return np.unique(self.point_id)

    def point_index(self) -> tuple[np.ndarray, np.ndarray]:
        """Distinct point ids and, per row, the index of its point in them.

        Returns
        -------
        ids : ndarray, shape (m,), int64
        index : ndarray, shape (n,), int64
        """
        ids, index = np.unique(self.point_id, return_inverse=True)
        return ids, index.astype(np.int64)

    def point_cmd(self) -> tuple[np.ndarray, np.ndarray]:
        """Commanded position of every distinct point (the mean over its rows).

        Returns
        -------
        ids : ndarray, shape (m,), int64
        cmd : ndarray, shape (m, 3), mm
        """
        ids, index = self.point_index()
        cmd = np.zeros((ids.size, 3))
        np.add.at(cmd, index, self.cmd)
        cmd /= np.bincount(index, minlength=ids.size)[:, None]
        return ids, cmd

    def select(self, mask) -> Recording:
        """The rows where ``mask`` (bool (n,) or integer indices) holds, as a new Recording."""
        idx = np.arange(len(self))[mask]

        def take(a):
            return None if a is None else a[idx]

        return Recording(
            kind=self.kind,
            point_id=self.point_id[idx],
            rep=self.rep[idx],
            cmd=self.cmd[idx],
            meas=take(self.meas),
            B=take(self.B),
            t_s=take(self.t_s),
            dir=take(self.dir),
            speed=take(self.speed),
            vel=take(self.vel),
            temp_C=take(self.temp_C),
            extra={k: v[idx] for k, v in self.extra.items()},
            source=self.source,
            lines=self.lines[idx],
        )


#: Powers of ten of (recorded |B|) / (reference |B|) that a unit slip produces, and the slip.
_UNIT_SLIPS = {
    1: "kG (kilogauss)",
    3: "mT",
    4: "G (gauss)",
    6: "uT",
}


def check_hall_scale(B_meas, B_ref, *, source, reference: str | None = None) -> list:
    """Refuse a Hall map whose field is a power of ten off the reference field (a unit slip).

    The median of |B_meas| / |B_ref| over the readings where neither field is small (each above
    1 % of its largest value) is compared with the ratios a unit slip produces:
    1e4 for gauss, 1e3 for mT, 10 for kG, 1e6 for uT (and their inverses for a reference in the
    wrong unit). Within 12 % of one of them it is an error: no magnet or bench effect scales the
    whole map by a power of ten, and every number downstream (millions of units) would be
    meaningless. Any other median ratio outside [0.5, 2] gives a warning and a note: a gross
    mismatch, but one that a wrong excitation current or the wrong reference could explain.

    Parameters
    ----------
    B_meas, B_ref : ndarray, shape (n, 3), T
        Recorded field of each reading and the reference field at its commanded point.
    source : str
        The recording, for messages.
    reference : str, optional
        How to name the reference field in messages.

    Returns
    -------
    list of str
        Notes (empty when the scales agree).

    Raises
    ------
    CfmInputError
        The ratio is a unit slip; the message names the likely unit.
    """
    bm = np.linalg.norm(np.asarray(B_meas, dtype=float), axis=1)
    br = np.linalg.norm(np.asarray(B_ref, dtype=float), axis=1)
    # readings where both fields are not small: a scan that runs out of a magnet the
    # reference does not end (a 2-D reference) reads ~0 there, which is no unit slip
    if not (br.size and br.max() > 0 and bm.max() > 0):
        return []
    use = (br > 0.01 * br.max()) & (bm > 0.01 * bm.max())
    if not use.any():
        return []
    ratio = float(np.median(bm[use] / br[use]))
    if 0.5 <= ratio <= 2.0:
        return []
    k = round(np.log10(ratio)) if ratio > 0 else 0
    what = (
        f"the recorded |B| is {ratio:.4g} times the reference |B|"
        f"{f' ({reference})' if reference else ''} at the same points (median over "
        f"{int(use.sum())} reading(s))"
    )
    if ratio > 0 and abs(np.log10(ratio) - k) < 0.05 and abs(k) in _UNIT_SLIPS:
        unit = _UNIT_SLIPS[abs(k)]
        if k > 0:
            hint = (
                f"the Bx, By, Bz columns look like {unit}, not T; a Hall map is in T "
                f"(the recording format's unit): divide them by {10.0**k:g}"
            )
        else:
            hint = (
                f"the reference looks 1e{-k} times too large: check the unit of its field "
                f"columns (a file in {unit} read as T?)"
            )
        raise CfmInputError(f"{what}; {hint}", file=source)
    msg = f"{source}: {what}; check the units and that the reference is the right field"
    warnings.warn(msg, CfmInputWarning, stacklevel=3)
    return [msg]


#: Length units a tracker recording may have been written in by mistake, and their size in mm.
_LENGTH_SLIPS = {"m": 1000.0, "cm": 10.0, "in": 25.4, "um": 1e-3}
#: Median distance (mm) of the measured probe positions from their nominal ones above which a
#: tracker recording is a gross mismatch: bench errors are micrometres, at most a few tenths.
TRACKER_GROSS_MM = 1.0


def check_tracker_scale(cmd, meas, nominal, *, source) -> list:
    """Refuse a tracker recording written in another length unit than mm (a unit slip).

    The measured probe positions are compared with the nominal ones the bench gives for the
    commanded positions (``nominal(cmd)``: commanded positions plus the tool offset, in mm).
    Bench errors are micrometres; when the median distance exceeds `TRACKER_GROSS_MM`, the
    recording is read again as if in each unit of `_LENGTH_SLIPS` (m, cm, in, um): if one of
    them brings the median distance under `TRACKER_GROSS_MM` and to a hundredth of what it was,
    it is an error naming that unit. Any other gross mismatch gives a warning and a note (a
    wrong tool offset or magnet placement could explain it).

    Parameters
    ----------
    cmd, meas : ndarray, shape (n, 3), mm
        Commanded axis positions and measured probe positions, as read.
    nominal : callable
        ``nominal(cmd)`` -> ndarray, shape (n, 3), mm: the bench's nominal probe positions.
    source : str
        The recording, for messages.

    Returns
    -------
    list of str
        Notes (empty when the positions agree within `TRACKER_GROSS_MM`).

    Raises
    ------
    CfmInputError
        The positions fit in another unit; the message names it and the option to pass.
    """
    cmd = np.asarray(cmd, dtype=float)
    meas = np.asarray(meas, dtype=float)
    if not len(cmd):
        return []
    gap = float(np.median(np.linalg.norm(meas - nominal(cmd), axis=1)))
    if not gap > TRACKER_GROSS_MM:
        return []
    for unit, mm in _LENGTH_SLIPS.items():
        other = float(np.median(np.linalg.norm(meas * mm - nominal(cmd * mm), axis=1)))
        if other < TRACKER_GROSS_MM and other < 0.01 * gap:
            raise CfmInputError(
                f"the measured positions are {gap:.4g} mm from their nominal ones (median), "
                f"{other:.3g} mm if the recording is in {unit}: its positions look like {unit}, "
                f"not mm; the recording format is in mm: pass --recording-length-unit {unit} "
                "(length_unit= from Python) or convert the file",
                file=source,
            )
    msg = (
        f"{source}: the measured positions are {gap:.4g} mm from their nominal ones (median); "
        "bench errors are micrometres: check the recording's length unit, the bench's tool "
        "offset ([frame] tool_offset_mm) and the axis order"
    )
    warnings.warn(msg, CfmInputWarning, stacklevel=3)
    return [msg]
