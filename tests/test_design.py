"""The design question: the largest U_p with U_f <= X over a share of the nodes, with its Monte
Carlo uncertainty (cfm_fem.workflows.design and `cfm-fem design`)."""

import json

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.errors import CfmInputError
from cfm_fem.workflows.design import admissible_up, parse_region, region_mask

UP = [0.0, 10.0, 20.0, 30.0]


def _noisy_ends(slope, r, rng):
    """Interval ends of nodes whose true U_f is slope * U_p, each end with relative noise r
    (the same standard normals for every U_p, as the sweep's common random numbers)."""
    z = rng.standard_normal((2, len(slope), 1))
    true = slope[:, None] * np.asarray(UP)[None, :]
    return -true * (1 + r * z[0]), true * (1 + r * z[1])


def test_answer_is_exact_without_noise_and_interpolates_the_percentile():
    slope = np.linspace(0.5, 2.0, 1001)  # U_f = slope * U_p: p95 of the slopes is 1.925
    low, high = -slope[:, None] * UP, slope[:, None] * np.asarray(UP)
    ans = admissible_up(UP, low, high, np.ones_like(low, bool), 30.0, rel_mc_std=0.0)
    assert ans.up_max_um == pytest.approx(30.0 / np.quantile(slope, 0.95), rel=1e-12)
    assert ans.u_up_max_um < 1e-12 and ans.method == "interpolated"
    # beyond the largest U_p: the proportional law, and said so
    far = admissible_up(UP, low, high, np.ones_like(low, bool), 100.0, rel_mc_std=0.0)
    assert far.method == "extrapolated"
    assert far.up_max_um == pytest.approx(100.0 / np.quantile(slope, 0.95), rel=1e-12)


def test_uncertainty_matches_the_spread_of_repeated_runs_and_errs_on_the_safe_side():
    rng = np.random.default_rng(7)
    slope = rng.lognormal(0.0, 0.3, 2000)  # no hard edge near the 95th percentile
    truth = 40.0 / np.quantile(slope, 0.95)
    r = 0.05  # about 740 trials per node
    answers, u = [], []
    for _ in range(60):
        low, high = _noisy_ends(slope, r, rng)
        a = admissible_up(UP, low, high, np.ones_like(low, bool), 40.0, rel_mc_std=r,
                          seed=int(rng.integers(1 << 30)), n_boot=200)  # fmt: skip
        answers.append(a.up_max_um)
        u.append(a.u_up_max_um)
    answers = np.array(answers)
    spread = answers.std(ddof=1)
    assert 0.7 < np.mean(u) / spread < 1.4  # the stated u is the actual scatter
    # max(|low|, |high|) biases U_f up, so the answer is low: by less than the stated bound
    assert truth - a.low_bias_bound_um < answers.mean() < truth - 3 * spread / np.sqrt(60)


def test_incomplete_nodes_are_left_out():
    slope = np.ones(100)
    low, high = -slope[:, None] * UP, slope[:, None] * np.asarray(UP)
    high[:10] *= 50  # nodes without a U_f figure carry half-space numbers: not used
    complete = np.ones_like(low, bool)
    complete[:10, 1:] = False
    ans = admissible_up(UP, low, high, complete, 20.0, rel_mc_std=0.0)
    assert ans.up_max_um == pytest.approx(20.0) and ans.nodes == [100, 90, 90, 90]


def test_region_parsing_and_selection():
    box = parse_region("-1:1,:0,5:")
    pts = np.array([[0.0, -3.0, 6.0], [0.0, 1.0, 6.0], [2.0, -1.0, 9.0], [1.0, 0.0, 5.0]])
    assert region_mask(pts, box).tolist() == [True, False, False, True]
    cyl = parse_region("cylinder:1.5,5:")
    assert region_mask(pts, cyl).tolist() == [False, True, False, True]
    for bad in (
        "1:0,:,:",
        "a:1,:,:",
        "1:2,3:4",
        "1,2,3",
        "cylinder:0,:",
        "cylinder:1",
        "cylinder:x,:",
    ):
        with pytest.raises(CfmInputError, match="--region must be"):
            parse_region(bad)


@pytest.fixture(scope="module")
def grid_csv(tmp_path_factory):
    ax = np.arange(-3.0, 4.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = pts @ np.diag([0.2, -0.2, 0.05]).T + [0.0, 0.0, 1.0]
    path = tmp_path_factory.mktemp("m") / "map.csv"
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


def test_cli_design_answers_with_its_uncertainty_and_writes_the_report(grid_csv, tmp_path, capsys):
    out = tmp_path / "d"
    argv = ["design", str(grid_csv), "--uf-max", "100", "--up", "0:100:50", "--trials", "2000",
            "--seed", "4", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    d = json.loads((out / "design.json").read_text())
    s = json.loads((out / "summary.json").read_text())
    # design counts nodes: the summary's per-node figures (its uf_units weigh node volumes)
    assert d["percentile_units"] == pytest.approx(s["uf_units_per_node"]["p95"], rel=1e-12)
    p = d["percentile_units"]
    assert p[1] < 100 < p[2] and 50 < d["up_max_um"] < 100
    # the linear interpolation between the sweep values that bracket 100 units
    assert d["up_max_um"] == pytest.approx(50 + 50 * (100 - p[1]) / (p[2] - p[1]))
    assert 0 < d["u_up_max_um"] < 0.05 * d["up_max_um"]
    printed = capsys.readouterr().out
    assert f"U_p <= {d['up_max_um']:.4g} +- " in printed
    html = (out / "report.html").read_text()
    assert "Design answer" in html and 'id="design"' in html
    # a region: the inner nodes only
    assert main([*argv[:-1], str(tmp_path / "r"), "--region", "-1:1,-1:1,-1:1"]) == 0
    r = json.loads((tmp_path / "r" / "design.json").read_text())
    assert r["region_nodes"] == 27 and r["nodes"] == [27, 27, 27]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--uf-max", "-1"], "--uf-max must be > 0"),
        (["--uf-max", "5", "--coverage", "1.5"], "--coverage must be in (0, 1]"),
        (["--uf-max", "5", "--region", "0:1"], "argument --region: must be XMIN:XMAX"),
        (["--uf-max", "5", "--region", "50:60,:,:"], "--region holds none of the 343 nodes"),
        (["--uf-max", "5", "--up", "10,5"], "--up values must increase"),
    ],
)
def test_cli_design_bad_input_exits_2_and_writes_nothing(grid_csv, tmp_path, capsys, extra,
                                                         message):  # fmt: skip
    out = tmp_path / "o"
    assert main(["design", str(grid_csv), "--trials", "100", *extra, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not (out / "design.json").exists() and not (out / "summary.json").exists()


def test_design_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["design", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--uf-max X" in out and "--coverage P" in out and "--region" in out


def test_cli_design_under_the_harmonic_model_answers_for_every_node(tmp_path):
    """`--field-model harmonic`: a field that is exactly a harmonic potential's gradient keeps
    its model at every node, border nodes included, where the linear model loses trials."""
    ax = np.arange(-3.0, 4.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = pts @ np.diag([0.2, -0.25, 0.05]).T + [0.0, 0.0, 1.0]  # div B = curl B = 0
    path = tmp_path / "harmonic.csv"
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    docs = {}
    for model in ("linear", "harmonic"):
        out = tmp_path / model
        argv = ["design", str(path), "--uf-max", "100", "--up", "0:100:50", "--trials", "500",
                "--out", str(out), "--field-model", model]  # fmt: skip
        assert main(argv) == 0
        docs[model] = json.loads((out / "design.json").read_text())
    assert docs["harmonic"]["field_model"] == "harmonic"
    assert docs["harmonic"]["nodes"][1:] == [343, 343]
    assert docs["linear"]["nodes"][1] < 343
    s = json.loads((tmp_path / "harmonic" / "summary.json").read_text())
    assert s["harmonic"]["linear_fallback_nodes"] == 0
