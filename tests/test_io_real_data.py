"""Every real field-map file in ../shared/data loads with the right units and orientation.

The files are read in place (never copied into the project); the tests skip when the folder is
absent. Expected numbers come from the files' own rows and from data/README.md.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA

from cfm_fem.errors import CfmInputError, CfmInputWarning
from cfm_fem.io import read_field

DATA = SHARED_DATA
MF_MAP = DATA / "emphatic" / "mfMapMeasured_5mm.txt"
CYLINDER = DATA / "emphatic" / "CylinderGrid_Section1_231025-112209.txt"
BODY_SCAN = DATA / "emphatic" / "EMPHATIC_body_scan_5280148.csv"
PROBE_CAL = DATA / "emphatic" / "Probe_calibration_Mar2023.csv"
OPERA = DATA / "cctpy" / "test_opera_field_table.table"
OPERA_INFO = DATA / "cctpy" / "info_test_opera_field_table.txt"


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real data file not available: {path}")
    return path


def _distinct(values):
    return np.unique(values)


def test_measured_comsol_map_7x7x160_grid_in_mm_and_t():
    path = _need(MF_MAP)
    with pytest.warns(CfmInputWarning) as record:
        fm = read_field(path)
    messages = [str(w.message) for w in record]
    assert any(":5: header says '% Nodes: 53742' but 7840 data rows" in m for m in messages)
    assert any(
        "640 row(s)" in m and "--zero-rows drop (zero_rows='drop' from Python)" in m
        for m in messages
    )
    assert fm.n_nodes == 7840
    np.testing.assert_array_equal(fm.points.min(axis=0), [-15, -15, -315])
    np.testing.assert_array_equal(fm.points.max(axis=0), [15, 15, 480])
    axes = [_distinct(fm.points[:, k]) for k in range(3)]
    assert [a.size for a in axes] == [7, 7, 160]
    for a in axes:
        np.testing.assert_array_equal(np.diff(a), 5.0)  # 5 mm step
    # line 3585: "10 15 45 0.105414 -1.65769 0.0218514" (the strongest By)
    i = int(np.flatnonzero(fm.lines == 3585)[0])
    np.testing.assert_array_equal(fm.points[i], [10, 15, 45])
    np.testing.assert_array_equal(fm.B[i], [0.105414, -1.65769, 0.0218514])
    assert fm.b_max == pytest.approx(np.linalg.norm([0.105414, -1.65769, 0.0218514]), rel=0.05)
    assert any("53742" in n for n in fm.notes) and any("640 row(s)" in n for n in fm.notes)


def test_measured_comsol_map_placeholders_are_the_grid_corners():
    path = _need(MF_MAP)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CfmInputWarning)
        fm = read_field(path, zero_rows="drop")
    assert fm.n_nodes == 7840 - 640
    # the 4 corner columns (|x| = |y| = 15 mm) lie outside the probed cylinder: all dropped
    corners = (np.abs(fm.points[:, 0]) == 15) & (np.abs(fm.points[:, 1]) == 15)
    assert not corners.any()
    assert not np.all(fm.B == 0, axis=1).any()


def test_cylinder_section_maps_bz_by_bx_columns_by_name():
    path = _need(CYLINDER)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # % Nodes: 2700 matches, no zero rows
        fm = read_field(path)
    assert fm.n_nodes == 2700
    np.testing.assert_array_equal(fm.points.min(axis=0), [-15, -15, 0])
    np.testing.assert_array_equal(fm.points.max(axis=0), [15, 15, 70])
    assert np.hypot(fm.points[:, 0], fm.points[:, 1]).max() < 15.04  # inside the cylinder
    # line 10: "-1 -15 0 -0.2481 -0.36107 0.00912" with columns Bz, By, Bx
    assert fm.lines[0] == 10
    np.testing.assert_array_equal(fm.points[0], [-1, -15, 0])
    np.testing.assert_array_equal(fm.B[0], [0.00912, -0.36107, -0.2481])
    # every row: the file's 4th column is Bz and the 6th is Bx
    raw = np.loadtxt(path, comments="%", encoding="utf-8")
    np.testing.assert_array_equal(fm.B, raw[:, [5, 4, 3]])


def test_body_scan_csv_needs_the_length_unit():
    path = _need(BODY_SCAN)
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    message = str(info.value)
    assert message.startswith(f"{path}:1: no length unit for columns 'X', 'Y', 'Zmagnet'")
    assert "--length-unit mm (length_unit='mm' from Python)" in message


def test_body_scan_csv_in_inches_with_quoted_thousands():
    path = _need(BODY_SCAN)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fm = read_field(path, length_unit="in")  # the field columns say (T)
    assert fm.n_nodes == 2565
    # X, Y within +-0.5905512 in = +-15 mm; z from 'Zmagnet' (stage z - 2.362 in)
    np.testing.assert_allclose(fm.points.min(axis=0), [-15.0, -15.0, -2.3618 * 25.4], atol=1e-6)
    np.testing.assert_allclose(fm.points.max(axis=0), [14.98, 15.0, 8.66140031 * 25.4], atol=1e-6)
    # line 2: -0.5905512,-0.39370078,0.0002,-2.3618,-0.00404704,0.07173827,0.02571564,90.9561,
    assert fm.lines[0] == 2
    np.testing.assert_allclose(fm.points[0], np.array([-0.5905512, -0.39370078, -2.3618]) * 25.4)
    np.testing.assert_array_equal(fm.B[0], [-0.00404704, 0.07173827, 0.02571564])
    # last line holds the quoted "6,858.51" in the ignored t_hall_begin column
    assert fm.lines[-1] == 2566
    np.testing.assert_array_equal(fm.B[-1], [-0.00432224, 0.07139636, 0.02643054])
    assert any("'Zmagnet'" in n and "'Z(stage)'" in n for n in fm.notes)
    z_step = np.diff(_distinct(fm.points[:, 2]))
    assert np.median(z_step) == pytest.approx(5.0, abs=0.01)  # 0.1968 in


def _opera_info():
    lines = _need(OPERA_INFO).read_text().split("\n")
    corner = np.array(lines[1].split(), dtype=float)
    step = np.array(lines[3].split(), dtype=float)
    counts = [int(v) for v in lines[5].split()]
    return corner, step, counts


def test_opera_table_21x11x41_metres_to_mm():
    path = _need(OPERA)
    corner, step, counts = _opera_info()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # counts "41 11 21" match 21 x 11 x 41 as a multiset
        fm = read_field(path)
    assert counts == [21, 11, 41]
    assert fm.n_nodes == 21 * 11 * 41
    axes = [_distinct(fm.points[:, k]) for k in range(3)]
    assert [a.size for a in axes] == counts
    np.testing.assert_allclose([a[0] for a in axes], corner * 1000, atol=1e-9)
    np.testing.assert_allclose(fm.points.min(axis=0), [-200, -50, -200], atol=1e-9)
    for a, s in zip(axes, step, strict=True):
        np.testing.assert_allclose(np.diff(a), s * 1000, atol=1e-9)
    # line 9, first data row; line 2528, the strongest field
    assert fm.lines[0] == 9
    np.testing.assert_allclose(fm.points[0], [-200, -50, -200], atol=1e-12)
    np.testing.assert_array_equal(
        fm.B[0], [-0.824103277846e-05, 0.131599781246e-04, -0.824103277846e-05]
    )
    i = int(np.flatnonzero(fm.lines == 2528)[0])
    np.testing.assert_allclose(fm.points[i], [-100, 10, -20], atol=1e-12)
    np.testing.assert_array_equal(
        fm.B[i], [-0.308261609895e-02, -0.177084782016e-02, -0.616523219790e-03]
    )


def test_probe_calibration_is_not_a_field_map():
    path = _need(PROBE_CAL)
    with pytest.raises(CfmInputError) as info:
        read_field(path)
    message = str(info.value)
    assert message.startswith(f"{path}:1: missing column(s) 'x', 'y', 'z'")
    assert "found 'Bx (T)', '%err Bx', 'By (T)'" in message
    assert info.value.column == "x"
