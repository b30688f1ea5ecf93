"""``cfm-fem quality``: the field quality a map gives, and how well a bench determines it.

One function, `run_quality`, behind both the command line and `cfm_fem.api.run_quality`:
read the map, choose the scan (the map's nodes in its z planes, or circles read from the model
between nodes), take the harmonics, centre, roll and magnetic length
(`cfm_fem.models.quality.harmonics`), then their uncertainty by Monte Carlo with the bench
(`cfm_fem.models.quality.uncertainty`) and the budget by error group.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.spatial

from ..errors import CfmInputError
from ..io.fit_cache import cached_fit
from ..models.field import FieldMap
from ..models.harmonic import HarmonicFit
from ..models.interpolation import LinearInterpolator
from ..models.mc import symmetric_interval
from ..models.probe import HallProbe
from ..models.quality import (
    LocalField,
    McQuality,
    QualityNumbers,
    ScanPlan,
    Sources,
    analyse,
    budget_groups,
    fit_planes,
    main_order_of,
    plan_from_nodes,
    plan_on_circles,
    run_quality_mc,
)
from ..models.quality.harmonics import inscribed_radius
from ..models.quality.orbit_mc import OrbitField, deflection_deviations, orbit_response
from ..models.quality.trajectory import rigidity_from_energy, track
from ..models.quality.uncertainty import CHUNK_POINTS, trial_reader
from ..threads import check_run_time, paced

__all__ = ["QualityRun", "run_quality", "scan_plan", "SAMPLINGS", "PROBES"]

SAMPLINGS = ("auto", "nodes", "circles")
PROBES = ("exact", "paper", "table1")
#: Circle radius of the circle sampling, as a fraction of the disk the map covers.
CIRCLE_FRACTION = 0.9
#: Main harmonic at an end plane above this fraction of its peak: the map ends inside the field.
END_FIELD_FRACTION = 1e-3


@dataclass
class QualityRun:
    """Everything ``cfm-fem quality`` writes.

    Attributes
    ----------
    plan : ScanPlan
    planes : ndarray, shape (P, 15), complex, T at R_ref
        Harmonics per plane of the map.
    nominal : QualityNumbers
        Field quality of the map.
    main_order : int
    z_length : float, mm
        Plane of the magnetic length.
    mc : McQuality or None
        Monte Carlo of the whole bench (None when not asked).
    budget : list of McQuality
        One run per error group.
    tolerances : dict or None
        User tolerances (`cfm_fem.io.quality_out.read_tolerances`).
    trajectory : dict or None
    source, model_description, sources_description : str
    n_nodes : int
    notes : list of str
    provenance : dict or None
    seconds : float
    """

    plan: ScanPlan
    planes: np.ndarray
    nominal: QualityNumbers
    main_order: int
    z_length: float
    mc: McQuality | None
    budget: list
    tolerances: dict | None
    trajectory: dict | None
    source: str
    model_description: str
    sources_description: str
    n_nodes: int
    notes: list = field(default_factory=list)
    provenance: dict | None = None
    seconds: float = 0.0

    @property
    def summary(self) -> dict:
        """``quality.json``."""
        from ..io.quality_out import quality_summary

        return quality_summary(self)

    def files(self, command_line: str | None = None) -> dict:
        """``quality.json``, ``planes.csv``, ``report.html`` and its figures: name -> content."""
        from ..io.quality_out import planes_csv
        from ..report.quality import quality_report

        summary = self.summary
        rep = quality_report(self, summary, command_line)
        files = {"quality.json": summary, "planes.csv": planes_csv(self)}
        files.update(rep.images)
        files["report.html"] = rep.render()
        return files

    def write(self, out_dir, command_line: str | None = None) -> list[Path]:
        """Write the files into ``out_dir`` (created), each atomically."""
        from ..io.quality_out import write_quality

        return write_quality(out_dir, self.files(command_line))


def _read_inputs(fieldmap, bench, mode, tolerances, reader):
    from ..io import read_field
    from ..io.bench_toml import resolve_bench
    from ..io.quality_out import read_tolerances

    fm = fieldmap if isinstance(fieldmap, FieldMap) else read_field(fieldmap, **(reader or {}))
    if mode == "htm":
        bench, _ = resolve_bench(bench)
    if tolerances is not None and not isinstance(tolerances, dict):
        tolerances = read_tolerances(tolerances)
    return fm, bench, tolerances


def _circle_planes(fm: FieldMap, dz_mm, r_mm):
    """Planes k dz inside the map's z range (z = 0 among them when inside), and dz; default
    dz: the larger of the median distance between nodes and a quarter of the circle radius
    (the field changes along z over lengths of the order of the aperture)."""
    pts = fm.points
    if dz_mm is None:
        d, _ = scipy.spatial.cKDTree(pts).query(pts, 2)
        dz_mm = float(f"{max(np.median(d[:, 1]), r_mm / 4):.2g}")
    if not (np.isfinite(dz_mm) and dz_mm > 0):
        raise CfmInputError(f"--dz must be a positive length in mm; got {dz_mm}")
    z0, z1 = pts[:, 2].min(), pts[:, 2].max()
    k0, k1 = int(np.ceil(z0 / dz_mm - 1e-9)), int(np.floor(z1 / dz_mm + 1e-9))
    if k1 - k0 + 1 > 100_000:
        raise CfmInputError(f"--dz {dz_mm:g} mm asks for {k1 - k0 + 1} planes; expected fewer")
    if k1 - k0 + 1 < 2:
        raise CfmInputError(
            f"--dz {dz_mm:g} mm leaves fewer than 2 planes in the map's z range "
            f"[{z0:g}, {z1:g}] mm; expected a smaller spacing",
            file=fm.source,
        )
    return dz_mm * np.arange(k0, k1 + 1), dz_mm


def scan_plan(fm, sampling, r_ref_mm, radius_mm, dz_mm, n_angles, notes):
    """Scan plan of a map and the nominal field at its points.

    Parameters
    ----------
    fm : FieldMap
    sampling : {"auto", "nodes", "circles"}
    r_ref_mm : float, mm
    radius_mm, dz_mm : float or None, mm
        Disk or circle radius, plane spacing of the circles (None: defaults of `run_quality`).
    n_angles : int
        Points per circle.
    notes : list of str
        Receives what the sampling chose.

    Returns
    -------
    plan : ScanPlan
    B_nodes : ndarray, shape (n, 3), T, or None
        The map's values at the scan points (node sampling); None on circles.
    """
    if sampling in ("auto", "nodes"):
        try:
            plan = plan_from_nodes(fm.points, r_ref_mm, r_fit_mm=radius_mm, source=fm.source)
        except CfmInputError as exc:
            if sampling == "nodes":
                raise CfmInputError(f"--sampling nodes: {exc.what}", file=exc.file) from None
        else:
            tree = scipy.spatial.cKDTree(fm.points)
            dist, idx = tree.query(plan.points)
            if np.all(dist <= 1e-6):
                return plan, fm.B[idx]
    r_in = inscribed_radius(fm.points[:, :2])
    r = CIRCLE_FRACTION * r_in if radius_mm is None else float(radius_mm)
    if radius_mm is not None and not r <= r_in:
        raise CfmInputError(
            f"--radius {r:g} mm: circles beyond the largest disk about the axis the map covers "
            f"(r = {r_in:.6g} mm); expected a radius within it",
            file=fm.source,
        )
    if not r > 0:
        raise CfmInputError(
            "the line x = y = 0 is not inside the map; harmonics are taken about it",
            file=fm.source,
        )
    z, dz = _circle_planes(fm, dz_mm, r)
    notes.append(f"circle sampling: planes every {dz:g} mm, circle r = {r:.6g} mm "
                 f"({n_angles} points), read from the model between nodes")  # fmt: skip
    return plan_on_circles(z, r, r_ref_mm, n_angles), None


def _field_model(fm, field_model):
    if field_model == "harmonic":
        fit, _ = cached_fit(fm.points, fm.B, source=fm.source)
        lost = int((~fit.use).sum())
        return fit, (
            f"local harmonic model per node ({fit.k} nearest nodes, {lost} node(s) on the "
            "linear interpolant)"
        )
    if field_model == "linear":
        interp = LinearInterpolator(fm)
        return interp, "linear interpolant"
    raise CfmInputError(f"--field-model must be harmonic or linear; got {field_model!r}")


def _length_plane(plan, planes, main_order, notes) -> float:
    z = plan.z
    if z[0] <= 0.0 <= z[-1]:
        return 0.0
    zl = float(z[int(np.argmax(np.abs(planes[:, main_order - 1])))])
    notes.append(
        f"the map does not hold the plane z = 0: the magnetic length is referred to z = {zl:g} "
        "mm, the plane of the largest main harmonic"
    )
    return zl


def _end_notes(plan, planes, main_order, notes) -> None:
    m = np.abs(planes[:, main_order - 1])
    ends = max(m[0], m[-1]) / m.max()
    if ends > END_FIELD_FRACTION:
        notes.append(
            f"the main harmonic at an end plane of the map is {ends:.2g} of its peak: the "
            "integrals leave out the field beyond the map"
        )
    if plan.r_ref_mm > plan.r_fit_mm * (1 + 1e-9):
        notes.append(
            f"R_ref = {plan.r_ref_mm:g} mm lies beyond the sampled radius "
            f"{plan.r_fit_mm:.6g} mm: harmonics at R_ref are extrapolated"
        )


def _sources(mode, up_um, bench, probe, centre_magnet):
    if mode not in ("gauss", "htm"):
        raise CfmInputError(f"mode must be gauss or htm; got {mode!r}")
    if probe not in PROBES:
        raise CfmInputError(f"probe must be one of {', '.join(PROBES)}; got {probe!r}")
    hp = HallProbe.exact() if probe == "exact" else HallProbe(model=probe)
    if mode == "gauss":
        if up_um is None:
            raise CfmInputError("mode gauss needs --up UM")
        src = Sources("gauss", up_mm=float(up_um) * 1e-3, probe=hp)
        return src, f"scan points moved by N(0, ({float(up_um):g} um)^2) per axis and point; " \
            f"probe {probe}"  # fmt: skip
    if centre_magnet:
        from .coupled import centred_on_travel

        bench = centred_on_travel(bench)
    src = Sources("htm", bench=bench, probe=hp)
    return src, (
        f"bench model (21 HTM errors, vibration, reading delay) of {bench.name}"
        if hasattr(bench, "name") else "bench model (21 HTM errors, vibration, reading delay)"
    ) + f"; probe {probe}, one calibration per scan"  # fmt: skip


def run_quality(fieldmap, r_ref_mm: float, *, up_um=None, mode: str | None = None, bench=None,
                trials: int | None = None, seed: int = 0, main_order: int | None = None,
                probe: str = "paper", field_model: str = "harmonic", sampling: str = "auto",
                radius_mm: float | None = None, dz_mm: float | None = None, n_angles: int = 64,
                centre_magnet: bool = False, tolerances=None, budget: bool = True,
                budget_trials: int = 200, digits: int = 1, batch_trials: int = 500,
                max_trials: int = 20_000, uncertainty: bool = True,
                rigidity_Tm: float | None = None, energy_gev: float | None = None,
                particle: str = "electron",
                trajectory_step_mm: float = 0.5, reader: dict | None = None,
                provenance: dict | None = None, progress=None,
                progress_total=None) -> QualityRun:  # fmt: skip
    """Field quality of a map and its uncertainty from a bench (``cfm-fem quality``).

    Parameters
    ----------
    fieldmap : path-like or FieldMap
    r_ref_mm : float, mm
        Reference radius of the harmonics.
    up_um : float, optional, um
        Standard deviation per axis of the scan points (mode gauss).
    mode : {"gauss", "htm"}, optional
        Default gauss when ``up_um`` is given, else htm.
    bench : Bench or path-like, optional
        Mode htm: the bench (default the CFM reference bench).
    trials : int, optional
        Fixed number of trials; default adaptive (JCGM 101 7.9.4) up to ``max_trials``.
    seed : int
    main_order : int, optional
        Default the order of the largest integrated harmonic.
    probe : {"exact", "paper", "table1"}
        Hall probe errors, one draw per trial (`cfm_fem.models.probe`).
    field_model : {"harmonic", "linear"}
        The model between nodes for displaced readings (and the circle sampling).
    sampling : {"auto", "nodes", "circles"}
        ``nodes``: the map's nodes in its z planes (maps on a grid); ``circles``: circles read
        from the model between nodes (any map); ``auto``: nodes when the map allows.
    radius_mm : float, optional, mm
        Disk (nodes) or circle radius; default the largest disk about the axis the map covers
        (nodes) or 0.9 of it (circles).
    dz_mm : float, optional, mm
        Plane spacing of the circle sampling; default the larger of the median distance
        between nodes and a quarter of the circle radius.
    n_angles : int
        Points per circle.
    centre_magnet : bool
        Mode htm: move the magnet to mid-travel of X and Y.
    tolerances : dict or path-like, optional
        Tolerance table (`cfm_fem.io.quality_out.read_tolerances`).
    budget : bool
        Run the budget (one error group at a time, ``budget_trials`` trials each).
    digits, batch_trials, max_trials
        The adaptive procedure (`run_quality_mc`).
    uncertainty : bool
        False: the map's numbers only.
    rigidity_Tm : float, optional, T m
        Track a particle of this rigidity through the map (`track`).
    energy_gev, particle
        Or its kinetic energy (GeV) and kind (``"electron"``, ``"proton"``).
    trajectory_step_mm : float, mm
        Runge-Kutta step of the trajectory.
    reader : dict, optional
        Reader options of `cfm_fem.io.read_field`.
    provenance : dict, optional
        Recorded in ``quality.json``.
    progress : callable(int), optional
        Called with the trials finished (the budget's included).
    progress_total : callable(int), optional
        Called once with the trials the run will do, when ``trials`` fixes them.

    Returns
    -------
    QualityRun
    """
    t0 = time.perf_counter()
    if not (np.isfinite(r_ref_mm) and r_ref_mm > 0):
        raise CfmInputError(f"--r-ref must be a positive radius in mm; got {r_ref_mm}")
    if sampling not in SAMPLINGS:
        raise CfmInputError(f"sampling must be one of {', '.join(SAMPLINGS)}; got {sampling!r}")
    mode = mode or ("gauss" if up_um is not None else "htm")
    if mode == "htm" and up_um is not None:
        raise CfmInputError("--up applies to mode gauss; mode htm takes its errors from the bench")
    fm, bench, tolerances = _read_inputs(fieldmap, bench, mode, tolerances, reader)
    with _naming(fm.source):  # a refusal of the analysis names the map
        notes = list(fm.notes)
        plan, b_nodes = scan_plan(
            fm, sampling, float(r_ref_mm), radius_mm, dz_mm, int(n_angles), notes
        )
        notes += plan.notes
        if rigidity_Tm is not None and energy_gev is not None:
            raise CfmInputError("give --rigidity or --energy, not both")
        if energy_gev is not None:
            rigidity_Tm = rigidity_from_energy(float(energy_gev), particle)
        needs_model = uncertainty or b_nodes is None or rigidity_Tm is not None
        model, model_desc = _field_model(fm, field_model) if needs_model else (None, "none")
        local = LocalField(model, plan.points, b_nodes) if model is not None else None
        b_nom = b_nodes if b_nodes is not None else local.B_nominal
        planes = fit_planes(plan, b_nom)
        integ = np.einsum("pn,p->n", planes, plan.weights_mm)
        n_main = main_order_of(integ) if main_order is None else int(main_order)
        if not 1 <= n_main <= plan.n_orders:
            raise CfmInputError(f"--main-order must be 1 .. {plan.n_orders}; got {main_order}")
        z_len = _length_plane(plan, planes, n_main, notes)
        _end_notes(plan, planes, n_main, notes)
        nominal = analyse(plan, b_nom, n_main, z_len)
        planes = fit_planes(plan, b_nom, on_circle=True)  # planes.csv: C_n on r = R_ref
        mc, groups, src_desc, src = None, [], "none", None
        if uncertainty:
            src, src_desc = _sources(mode, up_um, bench, probe, centre_magnet)
            kw = dict(seed=seed, digits=digits, progress=progress)
            vec = nominal.vector()
            n_pts, most = len(plan.points), trials if trials is not None else max_trials
            option = "--trials" if trials is not None else "--max-trials"
            check_run_time(option, most, n_pts, "trials")
            groups_src = budget_groups(src) if budget else []
            if budget:
                check_run_time("--budget-trials", budget_trials, n_pts * len(groups_src),
                               "trials")  # fmt: skip
            if progress_total is not None and trials is not None:
                progress_total(trials + budget_trials * len(groups_src))
            kw["progress"] = paced(option, most, "trials", progress)
            mc = run_quality_mc(plan, local, src, vec, n_main, z_len, trials=trials,
                                batch_trials=batch_trials, max_trials=max_trials, **kw)  # fmt: skip
            if not mc.converged and trials is None:
                notes.append(f"the adaptive Monte Carlo stopped at {mc.trials} trials before the "
                             f"numerical tolerance of {digits} digit(s) was reached")  # fmt: skip
            if mc.lost:
                notes.append(f"{mc.lost} trial(s) moved a scan point outside the field model and "
                             "were left out")  # fmt: skip
            if budget:
                kw["progress"] = paced("--budget-trials", budget_trials * len(groups_src),
                                       "trials", progress)  # fmt: skip
                groups = [run_quality_mc(plan, local, g, vec, n_main, z_len, trials=budget_trials,
                                         **kw) for g in groups_src]  # fmt: skip
        traj = None
        if rigidity_Tm is not None:
            traj = _trajectory(model, fm, plan, nominal, mc, src, seed,
                               rigidity=float(rigidity_Tm), step=trajectory_step_mm,
                               energy=energy_gev, particle=particle)  # fmt: skip
            linear, reads = traj["linear_reads"] or (0, 0)
            if linear:
                notes.append(
                    f"the trajectory read {linear} of its {reads} field values from the linear "
                    "interpolant, where the harmonic model of the nearest node does not reach "
                    "(map planes further apart than twice the models' reach)"
                )
        return QualityRun(plan, planes, nominal, n_main, z_len, mc, groups, tolerances, traj,
                          fm.source, model_desc, src_desc, fm.n_nodes, notes, provenance,
                          time.perf_counter() - t0)  # fmt: skip


@contextmanager
def _naming(source):
    """Re-raise a `CfmInputError` that names no file as one naming ``source``: the analysis of
    that map is what could not go on."""
    try:
        yield
    except CfmInputError as exc:
        if exc.file is not None:
            raise
        raise CfmInputError(exc.what, line=exc.line, column=exc.column, file=source) from None


def _trajectory(model, fm, plan, nominal, mc, src, seed, *, rigidity, step, energy,
                particle) -> dict:  # fmt: skip
    """The ``trajectory`` entry of quality.json: an orbit along the axis through the map, and
    the U95 of its deflection from the Monte Carlo's trials (`orbit_mc`)."""
    orbit_field = OrbitField(model, fm) if isinstance(model, HarmonicFit) else model
    t = track(orbit_field.field_at, rigidity, float(plan.z[0]), float(plan.z[-1]), step_mm=step)
    straight = float(nominal.integrated[0].real) / (1000.0 * rigidity) * 1e3
    out = {
        "rigidity_Tm": rigidity, "energy_GeV": energy,
        "particle": particle if energy is not None else None,
        "step_mm": t["step_mm"], "z_range_mm": [float(plan.z[0]), float(plan.z[-1])],
        "deflection_mrad": t["deflection_mrad"], "deflection_x_mrad": t["deflection_x_mrad"],
        "deflection_y_mrad": t["deflection_y_mrad"], "sagitta_mm": t["sagitta_mm"],
        "exit_mm": t["exit_mm"].tolist(),
        "straight_line_deflection_mrad": straight, "U95_deflection_mrad": None,
        "trials": None, "linear_reads": None,
        "definition": "RK4 orbit from (0, 0, z_min) along +z to the plane z_max through the "
        "model between nodes (harmonic: each point from the model of its nearest node, the "
        "linear interpolant where that model does not reach: linear_reads of the orbit's "
        "field readings), positive charge (B_y > 0 bends towards -x); "
        "straight_line_deflection_mrad: integrated B_1 at R_ref over B rho (small angles); "
        "U95_deflection_mrad: U95 of the deflection through the measured map, trial by trial: "
        "the reading errors of the nodes whose values the orbit's field uses, moved and read "
        "as the Monte Carlo's scan points, carried to the exit direction to first order",
    }  # fmt: skip
    if isinstance(orbit_field, OrbitField):
        out["linear_reads"] = [orbit_field.linear_reads, orbit_field.reads]
    if mc is not None:
        resp = orbit_response(orbit_field, t)
        trials = mc.trials + mc.lost
        pts = fm.points[resp.nodes]
        chunk = max(1, CHUNK_POINTS // max(len(pts), 1))
        dev = deflection_deviations(resp, model, fm.points, fm.B, trial_reader(src, pts, seed),
                                    trials, chunk)  # fmt: skip
        dev = dev[np.isfinite(dev)]
        if dev.size >= 2:
            low, high = symmetric_interval(dev, 0.95)
            out["U95_deflection_mrad"] = float(max(abs(low), abs(high)))
            out["trials"] = int(dev.size)
    return out
