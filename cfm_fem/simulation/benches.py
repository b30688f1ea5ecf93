"""A family of three-axis benches: carriages stacked in any order, their own strokes, tool
offsets, vibration and Table II error draws, and the bench file a user would write for each.

The HTM chain is that of :mod:`.bench` generalised to any stack (foundation first): body ``a``
sits in its parent by M_a = Trans(q_a d_a + delta(a)) . Rot(eps(a)), Rot = Rz Ry Rx, and the
probe is P = M_1 M_2 M_3 [tool; 1]. Squareness: of each pair the upper carriage (later in the
stack) is the one tilted, leaning towards the positive direction of the lower one, so that
``alpha_ab > 0`` closes the angle between +a and +b to 90 deg - alpha_ab.

A bench is a plain dict (written into the truth): ``stack``, ``strokes_mm``, ``tool_mm``,
``vibration_um``, ``reading_um``, ``pdf_scale`` (Table II widths times this), ``pdfs``
(name -> Table II tuple, scaled), ``errors`` (name -> drawn value, um or urad),
``magnet_mm`` (nominal magnet centre in the bench frame: mid-stroke of every axis plus the
tool), ``survey_std`` (um, urad).
"""

from __future__ import annotations

import itertools

import numpy as np

from . import bench as B

__all__ = [
    "STACKS",
    "stack_label",
    "draw_bench",
    "probe_position",
    "axis_noise",
    "travel_offset",
    "bench_toml",
]

#: Every order of the three carriages, foundation first; the reference bench's first.
STACKS = (B.STACK,) + tuple(s for s in itertools.permutations("xyz") if s != B.STACK)


def stack_label(stack) -> str:
    """'Z-X-Y' for ('z', 'x', 'y')."""
    return "-".join(a.upper() for a in stack)


def _scaled(pdf, f):
    kind, a, b = pdf
    if kind == "uniform":
        return (kind, a * f, b * f)
    return (kind, a * f, b * f)


def draw_bench(rng: np.random.Generator, strokes_min_mm=(100.0, 100.0, 600.0)) -> dict:
    """One bench of the family.

    Parameters
    ----------
    rng : numpy.random.Generator
    strokes_min_mm : sequence of 3 float, mm
        Least stroke of the x, y and z axes (the scan must fit).

    Returns
    -------
    dict
        The bench (module docstring).
    """
    stack = STACKS[0] if rng.uniform() < 0.35 else STACKS[int(rng.integers(1, len(STACKS)))]
    strokes = {
        "x": float(max(strokes_min_mm[0], rng.choice([100.0, 150.0, 200.0, 300.0]))),
        "y": float(max(strokes_min_mm[1], rng.choice([100.0, 150.0, 200.0]))),
        "z": float(max(strokes_min_mm[2], rng.choice([600.0, 800.0, 1000.0, 1200.0]))),
    }
    tool = [
        float(rng.uniform(-20.0, 20.0)),
        float(-rng.uniform(30.0, 100.0)),
        float(rng.uniform(200.0, 600.0)),
    ]
    scale = float(rng.uniform(0.5, 2.0))
    pdfs = {k: _scaled(v, scale) for k, v in B.TABLE_II.items()}
    errors = {}
    for name in B.NAMES:
        kind, a, b = pdfs[name]
        errors[name] = float(rng.uniform(a, b) if kind == "uniform" else rng.normal(a, b))
    mid = np.array([strokes[a] for a in "xyz"]) / 2.0
    return {
        "stack": list(stack),
        "stack_label": stack_label(stack),
        "strokes_mm": strokes,
        "tool_mm": tool,
        "vibration_um": float(rng.uniform(1.0, 4.0)),
        "reading_um": float(rng.uniform(0.5, 1.5)),
        "pdf_scale": scale,
        "pdfs": {k: list(v) for k, v in pdfs.items()},
        "errors": errors,
        "magnet_mm": (mid + np.asarray(tool)).tolist(),
        "survey_std": [float(rng.uniform(10.0, 50.0)), float(rng.uniform(20.0, 100.0))],
    }


def travel_offset(bench: dict) -> np.ndarray:
    """Axis travel minus map point (mm): the magnet centre at mid-stroke of every axis."""
    return np.asarray(bench["magnet_mm"]) - np.asarray(bench["tool_mm"])


def axis_noise(bench: dict, rng: np.random.Generator, n: int) -> np.ndarray:
    """Vibration and position-reading error of the axes, shape (n, 3), mm."""
    vib = rng.normal(0.0, bench["vibration_um"] * 1e-3, (n, 3))
    return vib + rng.normal(0.0, bench["reading_um"] * 1e-3, (n, 3))


def _directions(stack, errors) -> dict:
    """Unit travel direction of each axis in its parent frame (squareness: upper leans to
    +lower)."""
    d = {a: np.eye(3)["xyz".index(a)].copy() for a in "xyz"}
    for pair in ("xy", "xz", "yz"):
        a, b = pair
        upper, lower = (a, b) if stack.index(a) > stack.index(b) else (b, a)
        d[upper]["xyz".index(lower)] += np.sin(float(errors.get(f"alpha_{pair}", 0.0)) * 1e-6)
    for a in "xyz":
        k = "xyz".index(a)
        others = sum(d[a][j] ** 2 for j in range(3) if j != k)
        d[a][k] = np.sqrt(1.0 - others)
    return d


def probe_position(q_mm, errors: dict, bench: dict) -> np.ndarray:
    """Actual probe position in the bench frame.

    Parameters
    ----------
    q_mm : ndarray, shape (n, 3), mm
        Actual travel of the x, y and z axes.
    errors : dict
        name -> um or urad, a scalar or an array of shape (n,); missing names are zero.
    bench : dict

    Returns
    -------
    ndarray, shape (n, 3), mm
    """
    q = np.atleast_2d(np.asarray(q_mm, dtype=float))
    n = len(q)
    stack = tuple(bench["stack"])
    d = _directions(stack, errors)
    v = np.broadcast_to(np.asarray(bench["tool_mm"], dtype=float), (n, 3)).copy()

    def val(name):
        return np.broadcast_to(np.asarray(errors.get(name, 0.0), dtype=float), (n,))

    for a in reversed(stack):
        k = "xyz".index(a)
        eps = [val(f"eps_{c}({a})") * 1e-6 for c in "xyz"]
        delta = np.stack([val(f"delta_{c}({a})") * 1e-3 for c in "xyz"], -1)
        v = np.einsum("nij,nj->ni", B.rotation(*eps), v) + q[:, k : k + 1] * d[a] + delta
    return v


def _pdf_lines(pdf) -> list:
    kind, a, b = pdf
    if kind == "uniform":
        return ['pdf = "uniform"', f"low = {a!r}", f"high = {b!r}"]
    return ['pdf = "normal"', f"mean = {a!r}", f"std = {b!r}"]


def bench_toml(bench: dict, grid=None, comment: str = "") -> str:
    """The bench file (``cfm-bench`` TOML, version 1) of a bench of the family.

    Parameters
    ----------
    bench : dict
    grid : sequence of 3 (start, stop, num), optional
        The ``[grid]`` table (default: the strokes in 5 x 5 x 7 points).
    comment : str
        A first comment line.
    """
    st = bench["strokes_mm"]
    grid = grid or [(0.0, st["x"], 5), (0.0, st["y"], 5), (0.0, st["z"], 7)]
    lines = [
        f"# {comment}" if comment else "# simulated bench",
        'format = "cfm-bench"',
        "version = 1",
        f'name = "simulated bench {bench["stack_label"]}"',
        "",
        "[frame]",
        "stack = [" + ", ".join(f'"{a}"' for a in bench["stack"]) + "]",
        "tool_offset_mm = [" + ", ".join(repr(float(v)) for v in bench["tool_mm"]) + "]",
    ]
    for a in "xyz":
        lines += ["", f"[axes.{a}]", f"stroke_mm = {st[a]!r}", "mount_offset_mm = [0.0, 0.0, 0.0]"]
    lines += ["", "[grid]"]
    for a, (lo, hi, num) in zip("xyz", grid, strict=True):
        lines.append(
            f"{a}_mm = {{ start = {float(lo)!r}, stop = {float(hi)!r}, num = {int(num)} }}"
        )
    for name in B.NAMES:
        if name.startswith("alpha"):
            table = f"squareness.{name}"
        else:
            kind, rest = name.split("(")
            table = f"{rest[0]}.{kind}"
        unit = "um" if name.startswith("delta") else "urad"
        lines += ["", f"[errors.{table}]", *_pdf_lines(bench["pdfs"][name]), f'unit = "{unit}"']
    t_um, r_urad = bench["survey_std"]
    lines += [
        "",
        "[vibration]",
        f"std_um = {bench['vibration_um']!r}",
        "",
        "[reading_delay]",
        'model = "normal"',
        f"std_um = {bench['reading_um']!r}",
        "",
        "[magnet]",
        "rotation_deg = [0.0, 0.0, 0.0]",
        "translation_mm = [" + ", ".join(repr(float(v)) for v in bench["magnet_mm"]) + "]",
        f"survey_std_um = {t_um!r}",
        f"survey_std_urad = {r_urad!r}",
        "",
        "[assumptions]",
        'notes = ["simulated bench: the magnet centre at mid-stroke of every axis"]',
        "",
    ]
    return "\n".join(lines)
