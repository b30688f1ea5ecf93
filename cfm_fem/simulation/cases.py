"""The catalogue of simulated cases and the files of one case (recording, truth, reference).

Each case: the recording kind, the concealed effects at realistic sizes (diagnosis' names and
units) and the effect name a correct diagnosis ranks first (None: a null, nothing to find).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import hall, magnet, output, tracker

__all__ = ["CASES", "write_case", "reference_grid"]

#: name -> (kind, effects, expected first effect)
CASES = {
    "null_tracker": ("tracker", {}, None),
    "null_hall": ("hall", {}, None),
    "thermal_drift": (
        "tracker", {"thermal_drift": {"drift_x": 3.0, "scale_drift_z": 5.0}}, "thermal_drift"),
    "reversal": ("tracker", {"reversal": {"backlash_x": 3.0, "backlash_z": 4.0}}, "reversal"),
    "reading_delay": ("tracker", {"reading_delay": {"tau": 2.0}}, "reading_delay"),
    "position_dependent_geometric": (
        "tracker",
        {"position_dependent_geometric": {"eps_z(z)_u1": 40.0}},
        "position_dependent_geometric",
    ),
    "arm_deflection": ("tracker", {"arm_deflection": {"sag_z": 6.0}}, "arm_deflection"),
    "parameter_bias": ("tracker", {"parameter_bias": {"alpha_xy": 200.0}}, "parameter_bias"),
    "step_event": ("tracker", {"step_event": {"dx_um": 12.0, "from_rep": 6}}, "step_event"),
    "probe_misalignment": (
        "hall", {"probe_misalignment": {"m_zx": 0.5, "m_zy": -0.3}}, "probe_misalignment"),
    "sensor_offset": ("hall", {"sensor_offset": {"d_z_z": 150.0}}, "sensor_offset"),
    "magnet_misalignment": (
        "hall",
        {"magnet_misalignment": {"magnet_dx": 200.0, "magnet_roll": 500.0}},
        "magnet_misalignment",
    ),
    "magnet_shift_z": (
        "hall", {"magnet_misalignment": {"magnet_dz": 300.0}}, "magnet_misalignment"),
    "planar_hall": ("hall", {"planar_hall": {"k_z": 0.002}}, "planar_hall"),
    "hall_offset_gain": (
        "hall", {"hall_offset_gain": {"offset_z": 20.0, "gain_y": 1.0}}, "hall_offset_gain"),
    "magnet_temperature": (
        "hall", {"magnet_temperature": {"beta": -1000.0}}, "magnet_temperature"),  # NdFeB
    "fringe_field_3d": ("hall", {"fringe_field_3d": {}}, "fringe_field_3d"),
    "sensor_volume_averaging": (
        "hall", {"sensor_volume_averaging": {"disc_mm": 2.0}}, "sensor_volume_averaging"),
}  # fmt: skip


def reference_grid(size: str) -> np.ndarray:
    """Nodes of the reference field table (magnet frame, mm): a full grid through the map's
    points, with nodes 0.5 mm either side of each (the tool's finite-difference gradient then
    reads exact node values) and one layer beyond the map."""

    def axis(g):
        g = np.asarray(g, dtype=float)
        return np.unique(np.concatenate([g, g - 0.5, g + 0.5, [g.min() - 2.0, g.max() + 2.0]]))

    gx, gy, gz = (axis(g) for g in hall.GRIDS[size])
    return np.stack(np.meshgrid(gx, gy, gz, indexing="ij"), -1).reshape(-1, 3)


def _reference(kind_ref: str, size: str, folder: Path) -> Path:
    """The reference file of a Hall map, written once per folder and size."""
    if kind_ref == "harmonics":
        path = folder / "reference_harmonics_2d.csv"
        if not path.exists():
            output.write_harmonics(
                path,
                magnet.harmonics_2d(10.0),
                10.0,
                ["2-D multipoles of the simulated quadrupole's body field (z = 0)"],
            )
        return path
    path = folder / f"reference_{size}.csv"
    if not path.exists():
        pts = reference_grid(size)
        output.write_reference_table(
            path, pts, magnet.field(pts), ["exact field of the simulated quadrupole, magnet frame"]
        )
    return path


def _bench_file(folder: Path) -> Path:
    """The bench file of a Hall map, written once per folder: the shipped reference bench with
    the survey uncertainty of the magnet's placement (:data:`.hall.SURVEY_STD`) stated in its
    ``[magnet]`` table, as a user states the survey of their magnet."""
    from importlib import resources

    path = folder / "bench_survey.toml"
    if path.exists():
        return path
    text = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()
    t_um, r_urad = hall.SURVEY_STD
    survey = (
        "# survey of the simulated magnet's placement, 1 sigma per axis\n"
        f"survey_std_um = {t_um!r}\nsurvey_std_urad = {r_urad!r}\n"
    )
    head, sep, tail = text.partition("\n[magnet]\n")
    if not sep:
        raise ValueError("the shipped reference bench has no [magnet] table")
    return output.write_text(path, head + sep + survey + tail)


def write_case(case: str, seed: int, folder, size: str = "full", velocities: bool = True,
               n_reps=None) -> dict:  # fmt: skip
    """Simulate one case and write ``<case>_<seed>.csv``, ``<case>_<seed>.truth.json`` and, for a
    Hall map, its reference file, into ``folder``.

    Returns
    -------
    dict
        ``recording``, ``truth``, ``reference`` and ``bench`` (None for the tracker) paths,
        ``kind``, ``expected`` and the ``args`` of ``cfm-fem diagnose`` (less ``--out``). A
        Hall map's bench file is the reference bench with the simulated survey uncertainty of
        the magnet (``[magnet] survey_std_um``, ``survey_std_urad``): the diagnosis's
        registration prior.
    """
    kind, effects, expected = CASES[case]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sim = tracker if kind == "tracker" else hall
    if case == "step_event" and size != "full":
        reps = sim.REPS[size] if n_reps is None else n_reps
        effects = {"step_event": {"dx_um": 12.0, "from_rep": reps // 2}}
    cols, truth = sim.simulate(seed, effects, size=size, n_reps=n_reps)
    truth |= {"case": case, "expected": expected, "velocities_written": bool(velocities)}
    stem = folder / f"{case}_{seed}"
    rec = output.write_csv(
        stem.with_suffix(".csv"),
        cols,
        [f"simulated {kind} recording, case {case}, seed {seed}, size {size}"],
        drop=() if velocities else ("v_x", "v_y", "v_z"),
    )
    tru = output.write_json(stem.with_suffix(".truth.json"), truth)
    if kind == "tracker":
        return {"recording": rec, "truth": tru, "reference": None, "bench": None, "kind": kind,
                "expected": expected, "args": ["--tracker", str(rec)]}  # fmt: skip
    ref = _reference("harmonics" if "fringe_field_3d" in effects else "map", size, folder)
    bench = _bench_file(folder)
    args = ["--hall-map", str(rec), "--reference", str(ref), "--bench", str(bench)]
    return {"recording": rec, "truth": tru, "reference": ref, "bench": bench, "kind": kind,
            "expected": expected, "args": args}  # fmt: skip
