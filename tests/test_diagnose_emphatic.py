"""Diagnosis on real measurements: the EMPHATIC magnet's fringe scans against its body scan.

The owners stitch each fringe scan to the body scan with fitted offsets (``Inputs.h`` of their
analysis, in the source folder named in ``../shared/data/README.md``): "position in the file
minus offset = physical position", (-0.144, -0.411, 312.486) mm for the upstream
(small-aperture) fringe scan. Placed there, with |x|, |y| <= 10 mm, the upstream scan is read
against the body scan (the reference, whose nodes fail the harmonic fits' Laplace test: a
measured map, read by its curvature-corrected reading). The fringe readings fall midway between
the body's planes, where the field is steep along z. The diagnosis must claim no magnet
translation, and the shift and gains it calibrates must agree with a direct least-squares
stitching of the same scans (``scripts/stitch_emphatic.py``: plain numpy and scipy, the fringe
scan interpolated quadratically at the body's nodes, the same gain prior).

Placed at the nominal offset of its ``Zmagnet`` column instead (12.362 in = 313.995 mm), the
upstream scan sees the body field 1.509 mm further along z: the diagnosis must find that shift as
``magnet_misalignment`` (a reading at the nominal position p sees the body at p + delta, delta =
(0.144, 0.411, 1.509) mm: the magnet moved by t = -delta).
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.io.recordings import write_hall_map
from cfm_fem.workflows.diagnose.problem import hall_problem
from cfm_fem.workflows.diagnose.reference import reference_model
from cfm_fem.workflows.diagnose.workflow import diagnose

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "emphatic"
BODY = DATA / "EMPHATIC_body_scan_5280148.csv"

pytestmark = [
    pytest.mark.skipif(not BODY.exists(), reason="shared data folder absent"),
    pytest.mark.slow,
]

#: Magnet shift t (um) the owners' stitching implies from the nominal placement.
OWNERS_FROM_NOMINAL = {"magnet_dx": -144.0, "magnet_dy": -411.0, "magnet_dz": -1509.0}
#: Nominal placement of the upstream scan: no x, y offset, 12.362 in along z.
NOMINAL_OFFSET_MM = (0.0, 0.0, 12.362 * 25.4)


def _script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def emph():
    return _script("diagnose_emphatic")


@pytest.fixture(scope="module")
def stitching():
    return _script("stitch_emphatic")


@pytest.fixture(scope="module")
def body(emph):
    return emph.read_body(DATA)


def _cli(rec, out):
    write_hall_map(out / "upstream.csv", rec)
    args = ["diagnose", "--hall-map", str(out / "upstream.csv"), "--reference", str(BODY)]
    assert main([*args, "--length-unit", "in", "--out", str(out / "diag")]) == 0
    return json.loads((out / "diag" / "diagnosis.json").read_text())


@pytest.fixture(scope="module")
def upstream(emph, body, tmp_path_factory):
    """`cfm-fem diagnose` on the upstream fringe overlap at the owners' offset, as a user runs
    it, and the fringe scan placed there."""
    pts, B = emph.fringe_points(DATA / emph.FILES["small"], emph.OWNERS_OFFSET_MM["small"])
    rec = emph.overlap(pts, B, body)
    return _cli(rec, tmp_path_factory.mktemp("emphatic")), rec, (pts, B)


def _values(s):
    """Calibrated registration and gains, with the released ones of the effects."""
    p = {d["name"]: (d["value"], d["std"]) for d in s["calibration"]["parameters"]}
    for e in s["effects"]:
        p.update({k: (v, e["param_std"][k]) for k, v in e["params"].items()})
    return p


@pytest.fixture(scope="module")
def body_model(body):
    """The body scan as the command line reads it between its nodes."""
    model, kind, _ = reference_model(body, "auto")
    return model.curved if kind == "harmonic" else model  # no fit holds at these readings


def _diagnose(rec, body, model):
    b_ref = float(np.nanmax(np.linalg.norm(body.B, axis=1)))
    prob = hall_problem(rec, model, b_ref, None, smooth=False, ref_spacing_mm=model.spacing_mm,
                        ref_nodes=body.points, ref_error=model.error_var)  # fmt: skip
    return diagnose(prob).summary


def test_upstream_at_the_owners_fit_claims_no_translation(upstream):
    s, _, _ = upstream
    names = {e["name"] for e in s["effects"]}
    assert "magnet_misalignment" not in names, s["candidates"]
    assert not names & {"sensor_offset", "fringe_field_3d", "planar_hall"}, names


def test_upstream_shift_and_gains_agree_with_the_direct_stitching(upstream, body, stitching):
    """Within three combined standard deviations (the direct fit's own: least squares with
    its residuals' variance)."""
    s, _, (pts, B) = upstream
    d = stitching.stitch(pts, B, body.points, body.B)
    p = _values(s)
    pairs = [(f"magnet_d{c}", d["shift_um"][j], d["shift_std_um"][j]) for j, c in enumerate("xyz")]
    pairs += [(f"gain_{c}", d["gain_pct"][j], d["gain_std_pct"][j]) for j, c in enumerate("xyz")]
    for name, v, sd in pairs:
        tool, tool_sd = p[name]
        assert abs(tool - v) < 3.0 * np.hypot(tool_sd, sd), (name, tool, tool_sd, v, sd)


def test_upstream_noise_is_stated_with_the_reference_error(upstream):
    s, _, _ = upstream
    nm = s["fit"]["noise_model"]
    assert "second differences" in nm["source"]
    assert nm["reference_error_rms"] > 0
    assert any("corrected by its curvature" in n for n in s["notes"]), s["notes"]
    assert any("harmonic fits hold at none" in n for n in s["notes"]), s["notes"]
    assert 0.3 < s["fit"]["chi2_dof_after"] < 2.0


def test_upstream_verdict_on_the_translation_is_the_same_in_neighbouring_halves(
    upstream, body, body_model
):
    _, rec, _ = upstream
    x, y = rec.cmd[:, 0], rec.cmd[:, 1]
    for half in (x <= 0.2, x >= -0.2, y <= 0.5, y >= 0.3):
        sub = _diagnose(rec.select(half), body, body_model)
        assert "magnet_misalignment" not in [e["name"] for e in sub["effects"]], sub["candidates"]


def test_upstream_at_the_nominal_offset_is_the_owners_shift(emph, body, tmp_path):
    pts, B = emph.fringe_points(DATA / emph.FILES["small"], NOMINAL_OFFSET_MM)
    s = _cli(emph.overlap(pts, B, body), tmp_path)
    assert s["effects"][0]["name"] == "magnet_misalignment", s["candidates"]
    p = _values(s)
    for k, tol in (("magnet_dx", 100.0), ("magnet_dy", 100.0), ("magnet_dz", 150.0)):
        assert abs(p[k][0] - OWNERS_FROM_NOMINAL[k]) < tol, (k, p[k], OWNERS_FROM_NOMINAL[k])


def test_downstream_first_plane_is_left_out_and_the_rest_agrees_with_the_stitching(
    emph, body, body_model, stitching
):
    """The downstream fringe scan's first plane (z = 200.08 mm at the owners' offset) departs
    from its neighbours; with it left out nothing is claimed, and the shift and gains agree with
    the direct stitching (which reads the fringe scan at the body's planes 205-220 mm only)."""
    pts, B = emph.fringe_points(DATA / emph.FILES["large"], emph.OWNERS_OFFSET_MM["large"])
    s = _diagnose(emph.overlap(pts, B, body), body, body_model)
    assert [(o["axis"], round(o["position_mm"], 1)) for o in s["outliers"]] == [("z", 200.1)]
    assert s["effects"] == [], s["candidates"]
    d = stitching.stitch(pts, B, body.points, body.B)
    p = _values(s)
    for j, c in enumerate("xyz"):
        for name, v, sd in ((f"magnet_d{c}", d["shift_um"][j], d["shift_std_um"][j]),
                            (f"gain_{c}", d["gain_pct"][j], d["gain_std_pct"][j])):  # fmt: skip
            tool, tool_sd = p[name]
            assert abs(tool - v) < 3.0 * np.hypot(tool_sd, sd), (name, tool, tool_sd, v, sd)
