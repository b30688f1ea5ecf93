"""An effect made of several error functions is tested one function at a time and in pairs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_diagnose_effects import run_hall

from cfm_fem.workflows.diagnose.functions import PAIR_MAX_FUNCTIONS, function_options


def test_options_are_the_functions_then_their_pairs_without_repeats():
    fams = [("a", [0]), ("b", [1]), ("ab", [0, 1]), ("c", [2])]
    opts = function_options(fams)
    assert [(lb, idx, st) for lb, idx, st in opts[:4]] == [
        (["a"], [0], 1),
        (["b"], [1], 1),
        (["ab"], [0, 1], 1),
        (["c"], [2], 1),
    ]
    pairs = {tuple(lb): idx for lb, idx, st in opts if st == 2}
    # a + b is the function ab already, and a or b with ab adds nothing to it
    assert pairs == {("a", "c"): [0, 2], ("b", "c"): [1, 2], ("ab", "c"): [0, 1, 2]}


def test_an_effect_of_many_functions_is_tested_one_function_at_a_time():
    fams = [(f"f{i}", [i]) for i in range(PAIR_MAX_FUNCTIONS + 1)]
    assert [st for _, _, st in function_options(fams)] == [1] * len(fams)


def test_a_tilt_about_two_axes_is_reported_whole():
    """A tilt about two axes, each at about 5 standard uncertainties: the effect is reported
    with both tilts, each within three standard uncertainties of the truth."""
    truth = {"m_zx": 0.04, "m_zy": -0.04}
    s, _ = run_hall({"probe_misalignment": truth})
    first = s["effects"][0]
    assert first["name"] == "probe_misalignment", s["candidates"]
    assert sorted(first["functions"]) == ["m_zx", "m_zy"]
    for p, v in truth.items():
        assert abs(first["params"][p] - v) < 3.0 * first["param_std"][p], (p, first["params"])


@pytest.mark.slow
def test_an_offset_along_two_components_neither_enough_alone_is_claimed_whole(tmp_path):
    """A permanent-magnet quadrupole through one end on circles (family seed 111262): Hall
    offsets of 1.5 and 1.7 uT along x and y, 6.9 sigma jointly, neither passing the bar alone
    once the magnet's offset is calibrated. The pair is the effect's only evidence: it is
    claimed whole, each offset within three standard uncertainties of the truth."""
    pytest.importorskip("magpylib")
    from cfm_fem.cli import main
    from cfm_fem.simulation.family import write_family_case

    files = write_family_case(111262, tmp_path / "sim", "full", role="effect")
    truth = json.loads(Path(files["truth"]).read_text())["effects"]["hall_offset_gain"]
    out = tmp_path / "d"
    assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    summary = json.loads((out / "diagnosis.json").read_text())
    first = summary["effects"][0]
    assert first["name"] == "hall_offset_gain", summary["candidates"]
    assert sorted(first["functions"]) == ["offset_x", "offset_y"]
    for p, v in truth.items():
        assert abs(first["params"][p] - v) < 3.0 * first["param_std"][p], (p, first["params"])
