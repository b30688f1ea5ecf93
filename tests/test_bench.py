"""Bench files: the shipped reference bench, round trip, and clear errors for bad input."""

import numpy as np
import pytest

from cfm_fem import _kernels as K
from cfm_fem.errors import CfmInputError
from cfm_fem.io.bench_toml import bench_to_toml, parse_bench, read_bench, read_reference_bench
from cfm_fem.models.bench import ERROR_NAMES, error_index
from cfm_fem.models.mc import KERNEL_PDF_CODES, Pdf, ppf_numpy


@pytest.fixture(scope="module")
def ref():
    return read_reference_bench()


@pytest.fixture(scope="module")
def ref_text():
    from importlib import resources

    return resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()


def test_reference_bench_is_design_section_5_with_table_ii(ref):
    assert ref.stack == ("z", "x", "y")
    np.testing.assert_array_equal(ref.tool_offset_mm, [0, -60, 500])
    np.testing.assert_array_equal(ref.strokes_mm, [150, 150, 800])
    assert ref.grid_points().shape == (936, 3)
    assert tuple(e.name for e in ref.errors) == ERROR_NAMES
    # Table II in internal units (mm, rad): uniform for the stages, N(mean, std) for Z, squareness
    assert ref.errors[error_index("delta_x(x)")].pdf == Pdf.uniform(-1.5e-3, 1.5e-3)
    assert ref.errors[error_index("eps_x(x)")].pdf.params == pytest.approx((-18.5e-6, 18.5e-6))
    z = ref.errors[error_index("delta_x(z)")].pdf
    assert z.kind == "normal" and z.params == pytest.approx((5.5e-3, 7.8e-3))
    a = ref.errors[error_index("alpha_xz")].pdf
    assert a.kind == "normal" and a.params == pytest.approx((51.4e-6, 11.0e-6))
    np.testing.assert_allclose(ref.noise_std_mm(), np.hypot(2.5e-3, 1e-3))
    assert len(ref.assumptions) >= 5 and any("N(a, b)" in n for n in ref.assumptions)


def test_round_trip(ref):
    back = parse_bench(bench_to_toml(ref))
    assert back.stack == ref.stack and back.name == ref.name
    for e1, e2 in zip(ref.errors, back.errors, strict=True):
        assert e1.name == e2.name and e1.pdf.kind == e2.pdf.kind and e1.unit == e2.unit
        np.testing.assert_allclose(e1.pdf.params, e2.pdf.params, rtol=1e-14)
    np.testing.assert_array_equal(back.grid_points(), ref.grid_points())
    assert back.assumptions == ref.assumptions


def _bad(tmp_path, text, *fragments):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(CfmInputError) as info:
        read_bench(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    for f in fragments:
        assert f in msg, msg
    return info.value


def test_unknown_key_names_file_line_and_key(tmp_path, ref_text):
    text = ref_text.replace("stroke_mm = 150.0\nmount", "stroke_mm = 150.0\nstrok_mm = 3\nmount", 1)
    err = _bad(tmp_path, text, "'axes.x.strok_mm'", "not a known key", "stroke_mm")
    assert text.splitlines()[err.line - 1].startswith("strok_mm")


@pytest.mark.parametrize(
    "old, new, fragments",
    [
        ("stroke_mm = 800.0", "stroke_mm = -800.0", ["axes.z.stroke_mm", "> 0"]),
        ("low = -1.5\nhigh = 1.5", "low = 1.5\nhigh = -1.5", ["errors.x.delta_x", "low < high"]),
        ("mean = 5.5\nstd = 7.8", "mean = 5.5\nstd = -7.8", ["errors.z.delta_x", "std >= 0"]),
        ('stack = ["z", "x", "y"]', 'stack = ["z", "x", "x"]', ["frame.stack"]),
        ("num = 13 }", "num = 0 }", ["grid.z_mm.num", ">= 1"]),
        ("stop = 150.0, num = 9", "stop = 160.0, num = 9", ["grid.x_mm", "stroke"]),
        (
            'pdf = "uniform"\nlow = -18.5',
            'pdf = "cauchy"\nlow = -18.5',
            ["errors.x.eps_x.pdf", "one of"],
        ),
        ('unit = "urad"', 'unit = "furlong"', ["unit", "angle"]),
        ("std_um = 2.5", 'std_um = "big"', ["vibration.std_um", "number"]),
        (
            "tool_offset_mm = [0.0, -60.0, 500.0]",
            "tool_offset_mm = [0.0, -60.0]",
            ["frame.tool_offset_mm", "3"],
        ),
        ('model = "normal"', 'model = "psychic"', ["reading_delay.model"]),
        (
            "[errors.squareness.alpha_yz]",
            "[errors.squareness.alpha_zz]",
            ["alpha_zz", "not a known key"],
        ),
    ],
)
def test_impossible_values_name_the_key(tmp_path, ref_text, old, new, fragments):
    assert old in ref_text
    err = _bad(tmp_path, ref_text.replace(old, new, 1), *fragments)
    assert err.line is not None


def test_missing_error_and_profile_on_squareness(tmp_path, ref_text):
    i = ref_text.index("[errors.y.eps_z]")
    j = ref_text.index("# Z axis: in-house")
    _bad(tmp_path, ref_text[:i] + ref_text[j:], "errors.y.eps_z", "missing")
    text = ref_text.replace(
        'note = "orthogonality X and Y', 'profile = [1.0, 2.0]\nnote = "orthogonality X and Y'
    )
    _bad(tmp_path, text, "errors.squareness.alpha_xy.profile", "position independent")


def test_not_toml_and_not_a_file(tmp_path):
    _bad(tmp_path, "name = [unclosed\n", "not valid TOML")
    with pytest.raises(CfmInputError, match="cannot read"):
        read_bench(tmp_path / "nope.toml")


def test_bench_with_a_utf8_bom_is_read(tmp_path, ref_text, ref):
    path = tmp_path / "bom.toml"
    path.write_text(ref_text, encoding="utf-8-sig")  # what Windows Notepad writes
    assert read_bench(path).strokes_mm.tolist() == ref.strokes_mm.tolist()


def test_truncated_bench_names_its_last_line(tmp_path, ref_text):
    lines = ref_text.splitlines()
    i = next(k for k, s in enumerate(lines) if s.startswith("pdf ") and k > 20)
    err = _bad(tmp_path, "\n".join(lines[:i] + ["pdf "]), "not valid TOML", "end of document")
    assert err.line == i + 1


def test_speed_tau_delay_and_profiles_read(tmp_path, ref_text):
    text = ref_text.replace(
        'model = "normal"\nstd_um = 1.0',
        'model = "speed_tau"\nspeed_mm_s = [0.0, 0.0, 10.0]\n'
        'tau = { pdf = "uniform", low = 0.0, high = 0.2, unit = "ms" }',
    ).replace(
        'note = "linear positioning error, Table II N(8.4, 9.6)"',
        'profile = [0.0, 1.0]\nnote = "x"',
    )
    path = tmp_path / "b.toml"
    path.write_text(text)
    b = read_bench(path)
    assert b.delay.model == "speed_tau" and b.delay.tau_pdf == Pdf.uniform(0.0, 2e-4)
    assert b.position_dependent
    assert parse_bench(bench_to_toml(b)).delay.tau_pdf.params == pytest.approx((0.0, 2e-4))


PDFS = [
    Pdf.constant(0.3),
    Pdf.uniform(-1.5, 2.5),
    Pdf.normal(1.0, 2.0),
    Pdf.triangular(-1.0, 0.5, 2.0),
    Pdf.arcsine(-0.5, 0.5),
    Pdf.trapezoidal(-2.0, 2.0, 0.4),
    Pdf.student_t(1.0, 0.5, 5.0),
    Pdf.curvilinear_trapezoidal(-1.0, 1.0, 0.1),
]


@pytest.mark.parametrize("pdf", PDFS, ids=lambda p: p.kind)
def test_pdf_sampling_has_the_stated_moments(pdf):
    m = 200_000
    x = pdf.sample(np.random.default_rng(1), m)
    se = max(pdf.std, 1e-300) / np.sqrt(m)
    assert abs(x.mean() - pdf.mean) <= 5 * se + 1e-15
    # std of the sample std ~ std * sqrt((kurtosis - 1) / (4 m)); kurtosis < 10 here
    assert abs(x.std() - pdf.std) <= 5 * pdf.std * np.sqrt(9 / (4 * m)) + 1e-15


@pytest.mark.parametrize(
    "pdf", [p for p in PDFS if p.kind in KERNEL_PDF_CODES], ids=lambda p: p.kind
)
def test_kernel_ppf_matches_numpy_twin(pdf):
    code, par = pdf.kernel_code()
    u = np.linspace(1e-9, 1 - 1e-9, 2001)
    mine = np.array([K.pdf_ppf(code, par, x) for x in u])
    np.testing.assert_allclose(mine, ppf_numpy(code, par, u), rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize(
    "kind, params",
    [
        ("uniform", {"low": 1.0, "high": 1.0}),
        ("normal", {"mean": 0.0, "std": -1.0}),
        ("triangular", {"low": 0.0, "mode": 3.0, "high": 2.0}),
        ("trapezoidal", {"low": 0.0, "high": 1.0, "beta": 1.5}),
        ("student_t", {"loc": 0.0, "scale": 1.0, "dof": 2.0}),
        ("uniform", {"low": 0.0}),
        ("normal", {"mean": "a", "std": 1.0}),
    ],
)
def test_impossible_pdfs_raise(kind, params):
    with pytest.raises(CfmInputError):
        Pdf.from_params(kind, **params)


def test_magnet_placement_round_trip(ref):
    from dataclasses import replace

    from cfm_fem.models.bench import MagnetPlacement
    from cfm_fem.models.rotations import rotation_zyx

    b = replace(
        ref, magnet=MagnetPlacement(np.array([0.01, -0.02, 0.5]), np.array([75.0, -60, 900]))
    )
    p_mag = np.random.default_rng(0).normal(0, 10, (20, 3))
    q = b.axis_positions_for(p_mag)
    r = rotation_zyx(*b.magnet.rotation_rad)
    np.testing.assert_allclose(b.nominal_probe_mm(q), p_mag @ r.T + [75.0, -60, 900], atol=1e-12)
    # a bench-frame error vector seen in the magnet frame
    np.testing.assert_allclose(b.bench_to_magnet_rotation() @ r, np.eye(3), atol=1e-15)
    assert not b.outside_stroke(q[:1] * 0 + 10).any() and b.outside_stroke(q[:1] * 0 - 1).all()


def test_resolve_bench_says_what_was_assumed(tmp_path):
    """One choice of bench for every command: the model given, a file, or the packaged
    reference bench, with the sentence the outputs print about it."""
    from importlib import resources

    from cfm_fem.io.bench_toml import DEFAULT_NOTE, resolve_bench

    bench, sentence = resolve_bench(None)
    assert sentence == "bench model (packaged CFM reference bench)"
    assert bench.name == read_reference_bench().name
    same, said = resolve_bench(bench)
    assert same is bench and bench.name in said
    text = (resources.files("cfm_fem.data") / "cfm_reference_bench.toml").read_text()
    given = tmp_path / "full.toml"
    given.write_text(text)
    assert resolve_bench(given).sentence == f"bench model {given}"
    start = text.index("[grid]")
    end = text.index("\n# ----", start)
    short = tmp_path / "no_grid.toml"
    short.write_text(text[:start] + text[end:])
    bench, sentence = resolve_bench(str(short))
    assert sentence.startswith(f"bench model {short}; not in the file, defaults taken: [grid] x_mm")
    assert sum(n.startswith(DEFAULT_NOTE) for n in bench.assumptions) == 3
    assert sentence.count("[grid]") == 3
    assert len(bench.grid_points()) == 9 * 8 * 13  # the reference bench's point counts
