"""Recordings: round trip, optional and extra columns, bad input named precisely.

The contract (CSV, comma separated, a header row, ``#`` comment lines allowed): a laser tracker
recording has ``point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas`` (mm; commanded axis
positions and the measured probe position in the bench frame), a Hall map
``point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz`` (mm, T; magnet frame). Optional for both: ``t_s``
(s since start), ``dir_x,dir_y,dir_z`` (approach direction of the last move per axis: -1, 0,
+1), ``speed`` (mm/s at acquisition, 0 for stop-and-go), ``temp_C``. Unknown extra columns are
kept and ignored; a missing required column is a clear error.
"""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError, CfmInputWarning
from cfm_fem.io.recordings import (
    read_hall_map,
    read_recording,
    read_tracker,
    write_hall_map,
    write_tracker,
)
from cfm_fem.models.recordings import Recording

TRACKER_HEAD = "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n"
HALL_HEAD = "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n"


def _rec(kind="tracker", n_points=4, reps=3, seed=0, optional=True):
    rng = np.random.default_rng(seed)
    pid = np.repeat(np.arange(n_points), reps)
    rep = np.tile(np.arange(1, reps + 1), n_points)
    cmd = np.repeat(rng.uniform(0, 150, (n_points, 3)), reps, axis=0)
    vals = (
        cmd + rng.normal(0, 0.01, cmd.shape) if kind == "tracker" else rng.normal(0, 0.1, cmd.shape)
    )
    n = pid.size
    kw = {}
    if optional:
        kw = dict(
            t_s=np.arange(n) * 2.5,
            dir=rng.integers(-1, 2, (n, 3)),
            speed=np.zeros(n),
            temp_C=20 + rng.normal(0, 0.1, n),
            extra={"operator": np.array(["ann"] * n), "humidity": rng.uniform(30, 40, n)},
        )
    return Recording(
        kind=kind,
        point_id=pid,
        rep=rep,
        cmd=cmd,
        meas=vals if kind == "tracker" else None,
        B=vals if kind == "hall" else None,
        **kw,
    )


def _same(a: Recording, b: Recording):
    assert a.kind == b.kind
    np.testing.assert_array_equal(a.point_id, b.point_id)
    np.testing.assert_array_equal(a.rep, b.rep)
    np.testing.assert_array_equal(a.cmd, b.cmd)  # repr round trip: exact
    np.testing.assert_array_equal(a.values, b.values)
    for name in ("t_s", "dir", "speed", "temp_C"):
        va, vb = getattr(a, name), getattr(b, name)
        assert (va is None) == (vb is None), name
        if va is not None:
            np.testing.assert_array_equal(va, vb)
    assert set(a.extra) == set(b.extra)
    for k in a.extra:
        np.testing.assert_array_equal(a.extra[k], b.extra[k])


@pytest.mark.parametrize("kind", ["tracker", "hall"])
@pytest.mark.parametrize("optional", [True, False])
def test_round_trip(tmp_path, kind, optional):
    rec = _rec(kind, optional=optional)
    path = tmp_path / f"{kind}.csv"
    (write_tracker if kind == "tracker" else write_hall_map)(path, rec, comments=["made by a test"])
    back = (read_tracker if kind == "tracker" else read_hall_map)(path)
    _same(rec, back)
    assert back.source == str(path)
    assert back.lines[0] == 3  # comment line, header line, then data
    assert back.dir is None or back.dir.dtype == np.int8
    _same(rec, read_recording(path))
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind


def test_comments_order_case_partial_dir_and_extra(tmp_path):
    text = (
        "# tracker run 3\n"
        "REP,Point_ID,z_cmd,y_cmd,x_cmd,z_meas,y_meas,x_meas,dir_x,note\n"
        "1,7,3,2,1,3.001,2.002,1.003,+1,ok\n"
        "# pause\n"
        "\n"
        "2,7,3,2,1,3.004,2.005,1.006,-1,x\n"
    )
    p = tmp_path / "t.csv"
    p.write_text(text)
    rec = read_tracker(p)
    np.testing.assert_array_equal(rec.point_id, [7, 7])
    np.testing.assert_array_equal(rec.rep, [1, 2])
    np.testing.assert_allclose(rec.cmd, [[1, 2, 3], [1, 2, 3]])
    np.testing.assert_allclose(rec.meas[1], [1.006, 2.005, 3.004])
    np.testing.assert_array_equal(rec.dir, [[1, 0, 0], [-1, 0, 0]])
    np.testing.assert_array_equal(rec.lines, [3, 6])
    assert list(rec.extra["note"]) == ["ok", "x"]
    ids, cmd = rec.point_cmd()
    assert ids.tolist() == [7] and cmd.tolist() == [[1, 2, 3]]
    sub = rec.select(rec.rep == 2)
    assert len(sub) == 1 and sub.lines[0] == 6


BAD = {
    "missing column": (
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas\n1,1,0,0,0,0,0\n",
        1,
        "z_meas",
        "column 'z_meas' is missing",
    ),
    "repeated column": (
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas,X_CMD\n",
        1,
        "X_CMD",
        "appears twice",
    ),
    "text": (TRACKER_HEAD + "1,1,0,0,0,0,abc,0\n", 2, "y_meas", "must be a number; found 'abc'"),
    "empty field": (TRACKER_HEAD + "1,1,0,,0,0,0,0\n", 2, "y_cmd", "found an empty field"),
    "nan": (TRACKER_HEAD + "1,1,0,0,0,0,0,0\n2,1,0,0,0,NaN,0,0\n", 3, "x_meas", "finite"),
    "non-integer id": (TRACKER_HEAD + "1.5,1,0,0,0,0,0,0\n", 2, "point_id", "an integer"),
    "repeated point/rep": (
        TRACKER_HEAD + "1,1,0,0,0,0,0,0\n# c\n1,2,0,0,0,0,0,0\n1,1,0,0,0,0,0,0\n",
        5,
        "rep",
        "(point_id, rep) = (1, 1) appears twice (lines 2 and 5)",
    ),
    "bad direction": (
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas,dir_z\n1,1,0,0,0,0,0,0,2\n",
        2,
        "dir_z",
        "must be -1, 0 or +1",
    ),
    "negative speed": (
        "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas,speed\n1,1,0,0,0,0,0,0,-3\n",
        2,
        "speed",
        "must be a speed >= 0 mm/s; found -3\n",
    ),
    "truncated row": (TRACKER_HEAD + "1,1,0,0,0,0,0\n", 2, "z_meas", "is missing (truncated"),
    "too many fields": (TRACKER_HEAD + "1,1,0,0,0,0,0,0,9\n", 2, None, "header names only 8"),
    "header only": (TRACKER_HEAD, 1, None, "no data rows"),
    "only comments": ("# a\n# b\n", None, None, "no header row"),
    "semicolons": (
        TRACKER_HEAD.replace(",", ";") + "1;1;0;0;0;0;0;0\n",
        1,
        "point_id",
        "one field holding ';': recordings are comma-separated",
    ),
    "empty file": ("", None, None, "the file is empty; expected a recording"),
    "NUL bytes": (TRACKER_HEAD + "1,1,0,0,0,0,0,0\x00\x00\n", 2, None, "NUL bytes in the text"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_names_file_line_column(tmp_path, case):
    text, line, column, what = BAD[case]
    p = tmp_path / "rec.csv"
    p.write_text(text)
    with pytest.raises(CfmInputError) as info:
        read_tracker(p)
    err = info.value
    assert what in str(err) + "\n", str(err)
    assert str(p) in str(err)
    assert err.line == line
    assert err.column == column
    if line is not None:
        assert f"{p}:{line}:" in str(err)


@pytest.mark.parametrize("encoding, kind", [("utf-16", "UTF-16"), ("utf-32", "UTF-32")])
def test_utf16_recording_is_refused_in_words(tmp_path, encoding, kind):
    # read as UTF-8 the message quoted column names full of NUL bytes
    p = tmp_path / "rec.csv"
    p.write_text(TRACKER_HEAD + "1,1,0,0,0,0,0,0\n", encoding=encoding)
    with pytest.raises(CfmInputError) as info:
        read_tracker(p)
    assert str(info.value) == f"{p}: the file is {kind} text; save it as UTF-8 and read it again"


def test_hall_map_requires_field_columns(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text(TRACKER_HEAD + "1,1,0,0,0,0,0,0\n")
    with pytest.raises(CfmInputError, match="column 'Bx' is missing"):
        read_hall_map(p)
    p.write_text(HALL_HEAD + "1,1,0,0,0,0.1,0.2,inf\n")
    with pytest.raises(CfmInputError, match=r":2: column 'Bz' must be a finite number"):
        read_hall_map(p)


def test_missing_file(tmp_path):
    with pytest.raises(CfmInputError, match="cannot read"):
        read_tracker(tmp_path / "nope.csv")


def test_inconsistent_command_warns(tmp_path):
    p = tmp_path / "t.csv"
    p.write_text(TRACKER_HEAD + "1,1,0,0,0,0,0,0\n1,2,0,0,0.5,0,0,0\n")
    with pytest.warns(CfmInputWarning, match="point_id 1"):
        read_tracker(p)


def test_writer_rejects_wrong_kind_and_leaves_nothing(tmp_path):
    with pytest.raises(CfmInputError):
        write_hall_map(tmp_path / "x.csv", _rec("tracker"))
    assert not any(tmp_path.iterdir())


def test_recording_checks_shapes():
    with pytest.raises(CfmInputError, match="shape"):
        Recording(
            kind="tracker", point_id=[1, 2], rep=[1, 1], cmd=np.zeros((2, 3)), meas=np.zeros((3, 3))
        )
    with pytest.raises(CfmInputError, match="kind"):
        Recording(kind="laser", point_id=[1], rep=[1], cmd=np.zeros((1, 3)))
