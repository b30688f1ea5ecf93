"""Harmonics files: conventions, metadata, clear errors, round trip, bundled QFDp4 (Table III)."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.io.harmonics import (
    parse_harmonics,
    qfdp4_path,
    read_harmonics,
    read_qfdp4,
    write_harmonics,
)
from cfm_fem.models.multipole import Multipole

# Paper Table III, as printed: n, Bn, An (n = 1, 2 in T; n >= 3 in units of 1e-4 of B2)
TABLE_III = [
    (1, 5.80e-8, 9.11e-9),
    (2, 6.96e-2, 0.0),
    (3, 2.85e-1, 1.25),
    (4, -3.76e-1, -1.28e-1),
    (5, -7.94e-1, 6.91e-1),
    (6, -5.55, 5.61e-1),
    (7, -3.29e-2, 3.85e-2),
    (8, -8.37e-2, -7.19e-2),
    (9, -1.36e-1, 1.70e-1),
    (10, 3.60e-1, -5.59e-1),
    (11, 3.62e-2, 3.43e-2),
    (12, -1.45e-2, -1.66e-2),
    (13, -2.12e-2, -6.96e-3),
    (14, 1.96e-1, -1.29e-1),
    (15, 1.09e-2, 1.00e-2),
]


def _write(tmp_path, text, name="h.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_bundled_qfdp4_is_table_iii():
    m = read_qfdp4()
    assert m.n_orders == 15 and m.main == 2 and m.r_ref == 10.0
    b2 = 6.96e-2
    assert m.b_ref == b2
    # n = 1, 2 are in T as printed
    assert m.normal[0] == 5.80e-8 and m.skew[0] == 9.11e-9
    assert m.normal[1] == b2 and m.skew[1] == 0.0
    # n >= 3 are units of 1e-4 of B2
    for n, bn, an in TABLE_III[2:]:
        assert m.normal[n - 1] == pytest.approx(bn * 1e-4 * b2, rel=1e-14)
        assert m.skew[n - 1] == pytest.approx(an * 1e-4 * b2, rel=1e-14)
    data_rows = [ln for ln in qfdp4_path().read_text().splitlines() if ln and ln[0].isdigit()]
    assert len(data_rows) == 15
    text = qfdp4_path().read_text().lower()
    assert "r_ref" in text and "assumption" in text and "b1" in text


def test_tesla_convention_with_arguments(tmp_path):
    p = _write(tmp_path, "n,Bn,An\n1,0.001,0\n2,0.07,0.0001\n")
    m = read_harmonics(p, r_ref_mm=12.5, convention="tesla")
    np.testing.assert_array_equal(m.normal, [0.001, 0.07])
    np.testing.assert_array_equal(m.skew, [0.0, 0.0001])
    assert m.r_ref == 12.5 and m.main == 2 and m.source == str(p)


def test_header_any_order_case_and_extra_columns_and_gaps(tmp_path):
    text = (
        "# convention: tesla\n# r_ref: 1 cm\nAN , comment, bn, N\n"
        "0.5,first,0.25,1\n\n# gap\n0,x,1.0,3\n"
    )
    m = read_harmonics(_write(tmp_path, text))
    assert m.r_ref == pytest.approx(10.0)
    np.testing.assert_array_equal(m.normal, [0.25, 0.0, 1.0])  # order 2 absent -> 0
    np.testing.assert_array_equal(m.skew, [0.5, 0.0, 0.0])


def test_paper_units_with_higher_main(tmp_path):
    # a sextupole: rows n <= 3 in T, n > 3 in units of B3
    text = (
        "# r_ref_mm: 5\n# convention: paper_units\n# main: 3\n"
        "n,Bn,An\n1,1e-6,0\n2,2e-5,0\n3,0.5,0\n4,10,-20\n"
    )
    m = read_harmonics(_write(tmp_path, text))
    np.testing.assert_allclose(m.normal, [1e-6, 2e-5, 0.5, 10e-4 * 0.5])
    np.testing.assert_allclose(m.skew, [0, 0, 0, -20e-4 * 0.5])


@pytest.mark.parametrize("convention", ["tesla", "paper_units"])
def test_write_read_round_trip_is_exact(tmp_path, convention):
    m = read_qfdp4()
    p = tmp_path / "out" / f"{convention}.csv"
    write_harmonics(p, m, convention=convention, notes=["round trip"])
    back = read_harmonics(p)
    assert back.r_ref == m.r_ref and back.main == m.main
    rtol = 0 if convention == "tesla" else 1e-15
    np.testing.assert_allclose(back.normal, m.normal, rtol=rtol, atol=0)
    np.testing.assert_allclose(back.skew, m.skew, rtol=rtol, atol=0)
    assert not list(p.parent.glob(".*"))  # no temporary file left behind


def _error(tmp_path, text, **kw) -> CfmInputError:
    p = _write(tmp_path, text)
    with pytest.raises(CfmInputError) as info:
        read_harmonics(p, **kw)
    assert str(p) in str(info.value)
    return info.value


def test_missing_reference_radius(tmp_path):
    e = _error(tmp_path, "# convention: tesla\nn,Bn,An\n2,0.07,0\n")
    assert "'# r_ref_mm: <mm>' or --r-ref MM (r_ref_mm= from Python)" in e.what


def test_missing_convention(tmp_path):
    e = _error(tmp_path, "# r_ref_mm: 10\nn,Bn,An\n2,0.07,0\n")
    assert "convention" in e.what and "paper_units" in e.what


def test_paper_units_without_main(tmp_path):
    e = _error(tmp_path, "# r_ref_mm: 10\n# convention: paper_units\nn,Bn,An\n2,0.07,0\n")
    assert "main" in e.what


def test_argument_disagreeing_with_file_names_the_line(tmp_path):
    text = "# convention: tesla\n# r_ref_mm: 10\nn,Bn,An\n2,0.07,0\n"
    e = _error(tmp_path, text, r_ref_mm=11.0)
    assert e.line == 2 and "r_ref_mm" in e.what
    assert read_harmonics(_write(tmp_path, text, "ok.csv"), r_ref_mm=10.0).r_ref == 10.0
    e = _error(tmp_path, text, convention="paper_units")
    assert e.line == 1


def test_key_given_twice_differently(tmp_path):
    e = _error(
        tmp_path,
        "# main: 2\n# convention: tesla\n# main: 3\n# r_ref_mm: 10\nn,Bn,An\n2,1,0\n3,1,0\n",
    )
    assert e.line == 3 and "twice" in e.what


def test_bad_number_names_line_and_column(tmp_path):
    e = _error(tmp_path, "# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n1,0,0\n2,abc,0\n")
    assert e.line == 5 and e.column == "Bn" and "'abc'" in e.what
    assert str(e).startswith(f"{tmp_path / 'h.csv'}:5:")


def test_bad_order_duplicate_order_and_field_count(tmp_path):
    head = "# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n"
    e = _error(tmp_path, head + "1.5,0,0\n")
    assert e.line == 4 and e.column == "n"
    e = _error(tmp_path, head + "0,0,0\n")
    assert e.column == "n"
    e = _error(tmp_path, head + "2,0.07,0\n2,0.08,0\n")
    assert e.line == 5 and "also on line 4" in e.what
    e = _error(tmp_path, head + "2,0.07\n")
    assert e.line == 4 and "expected 3" in e.what


def test_header_problems(tmp_path):
    e = _error(tmp_path, "# r_ref_mm: 10\nn,Bn,Skew\n1,0,0\n")
    assert e.column == "An" and e.line == 2 and "'An' is missing" in e.what
    e = _error(tmp_path, "# r_ref_mm: 10\nn,Bn,An,bn\n1,0,0,0\n")
    assert e.column == "Bn" and "twice" in e.what
    e = _error(tmp_path, "# r_ref_mm: 10\n# only comments\n")
    assert "header" in e.what
    e = _error(tmp_path, "# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n")
    assert "no harmonics" in e.what


def test_bad_metadata_values(tmp_path):
    e = _error(tmp_path, "# convention: gauss\nn,Bn,An\n2,1,0\n")
    assert e.line == 1 and "tesla" in e.what
    e = _error(tmp_path, "# r_ref: 10\nn,Bn,An\n2,1,0\n")
    assert e.line == 1 and "unit" in e.what
    e = _error(tmp_path, "# r_ref: 10 furlongs\nn,Bn,An\n2,1,0\n")
    assert "furlongs" in e.what
    e = _error(tmp_path, "# main: quad\nn,Bn,An\n2,1,0\n")
    assert e.line == 1


def test_bad_main_argument():
    with pytest.raises(CfmInputError, match="main"):
        parse_harmonics("# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n2,1,0\n", main=0)


def test_zero_or_absent_main_harmonic(tmp_path):
    head = "# r_ref_mm: 10\n# convention: paper_units\n# main: 2\nn,Bn,An\n"
    e = _error(tmp_path, head + "1,1e-6,0\n2,0,0\n3,1,1\n")
    assert e.line == 6 and e.column == "Bn"
    e = _error(tmp_path, head + "1,1e-6,0\n")
    assert "main" in e.what


def test_free_text_comments_with_colons_are_ignored():
    text = "# Note: values from Table III\n# r_ref_mm: 10\n# convention: tesla\nn,Bn,An\n2,0.07,0\n"
    m = parse_harmonics(text, source="mem")
    assert isinstance(m, Multipole) and m.source == "mem"


def test_unreadable_file(tmp_path):
    with pytest.raises(CfmInputError, match="cannot read"):
        read_harmonics(tmp_path / "missing.csv")
