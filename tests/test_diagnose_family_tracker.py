"""Tracker recordings of the randomized family (simulated apart from the diagnosis) that
need each of the tracker tests' conditions: an error function quadratic along the axis a
half splits, a step from the second of three repetitions on, a drift of one axis against a
one-parameter step, an effect whose signature the baseline reproduces in large part; and
nulls. Each case replays from its seed (`cfm_fem.simulation.family.write_family_case`)."""

from __future__ import annotations

import json

import pytest

from cfm_fem.cli import main
from cfm_fem.simulation.family import write_family_case


def _diagnose(seed, role, tmp_path):
    files = write_family_case(seed, tmp_path / "sim", "small", role=role, kind="tracker")
    out = tmp_path / "diag"
    assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    truth = json.loads((tmp_path / "sim" / f"family_{seed}.truth.json").read_text())
    return json.loads((out / "diagnosis.json").read_text()), truth


@pytest.mark.parametrize(
    "seed",
    [
        1044,  # delta_x(x) quadratic along x, 6.8 sigma: each x half sees it nearly linear
        1069,  # delta_x(z) quadratic, 7.1 sigma, 84 % of it reproduced by the baseline
        1116,  # a step along x from the second of three repetitions on, 7.5 sigma
        1243,  # drift_y alone, 7.8 sigma, against a one-parameter step
    ],
)
def test_concealed_tracker_effect_ranked_first(seed, tmp_path):
    s, truth = _diagnose(seed, "effect", tmp_path)
    assert truth["significance"]["sigma_drawn"] >= 6.0
    assert s["effects"], s["candidates"]
    assert s["effects"][0]["name"] == truth["expected"], s["candidates"]


@pytest.mark.parametrize("seed", [4, 9, 13, 16, 19])
def test_tracker_null_claims_nothing(seed, tmp_path):
    s, truth = _diagnose(seed, "null", tmp_path)
    assert truth["expected"] is None
    assert s["effects"] == [] and s["mismatch"] is False, s["candidates"]
