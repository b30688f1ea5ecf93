"""The Python API: what the command line does, for a notebook, with the command line's defaults.

Every function takes paths or objects already read, returns a labelled result
(`cfm_fem.workflows.results`) or the documented result object, and writes nothing unless asked
(``.write(out_dir)``). Numerics are imported when a function runs: ``import cfm_fem`` stays
fast. The names say ``run_*`` because ``cfm_fem.workflows.sweep.problem``,
``cfm_fem.models.kinematics``, ... are the modules behind them.

Examples
--------
>>> import cfm_fem
>>> maps = cfm_fem.run_sweep("meshes/quadrupole.vtu", up_um=[10, 20])  # doctest: +SKIP
>>> maps.uf("absB", up_um=20)  # U_f per node, NaN where the node has none  # doctest: +SKIP
"""

from __future__ import annotations

from .errors import CfmInputError

__all__ = [
    "read_map",
    "read_bench",
    "read_recording",
    "run_sweep",
    "run_kinematics",
    "run_coupled",
    "run_compare",
    "run_diagnose",
    "run_design",
    "run_design_quality",
    "run_quality",
    "run_fig4",
    "run_tolerance",
    "SWEEP_TRIALS",
]

#: Trials per node and U_p of `sweep`, as ``cfm-fem sweep`` (U_f of a node to +-1.4 %).
SWEEP_TRIALS = 10_000
#: Trials of the kinematic Monte Carlo, as ``cfm-fem kinematics`` (the paper's 1e6).
KINEMATICS_TRIALS = 1_000_000
#: Trials of the coupled and comparison Monte Carlo, as ``cfm-fem coupled`` / ``compare``.
COUPLED_TRIALS = 100_000


def read_map(path, **options):
    """Read a field map (VTU/VTK/MSH..., COMSOL text, Opera .table, CSV) into a `FieldMap`.

    ``options``: ``fmt``, ``length_unit``, ``field_unit``, ``zero_rows``, ``solution``, as the
    command line's ``--format``, ``--length-unit``, ... (`cfm_fem.io.read_field`).
    """
    from .io import read_field

    return read_field(path, **options)


def read_bench(path=None):
    """A bench description (TOML); None: the packaged CFM reference bench."""
    from .io.bench_toml import resolve_bench

    return resolve_bench(path).bench


def read_recording(path, kind: str | None = None, *, length_unit=None, field_unit=None):
    """A tracker recording or Hall map (CSV contract), converted to mm and T.

    Parameters
    ----------
    path : path-like
    kind : {"tracker", "hall"}, optional
        Default: told by the columns.
    length_unit, field_unit : str, optional
        Units of the file when not mm and T (``--recording-length-unit`` ...).
    """
    from .io.recording_units import convert_recording
    from .io.recordings import read_hall_map, read_tracker
    from .io.recordings import read_recording as read_any

    readers = {None: read_any, "tracker": read_tracker, "hall": read_hall_map}
    if kind not in readers:
        raise CfmInputError(f"kind must be 'tracker' or 'hall'; got {kind!r}")
    return convert_recording(readers[kind](path), length_unit, field_unit)


def run_sweep(field, up_um=(0, 10, 20, 30, 40, 50), *, trials: int | None = None, seed: int = 0,
          mode: str = "gauss", bench=None, progress=None, **options):  # fmt: skip
    """U_f maps for a sweep of U_p (``cfm-fem sweep``), in memory unless ``out_dir`` is given.

    Parameters
    ----------
    field : path-like or FieldMap
    up_um : sequence of float
        U_p values, um (mode gauss).
    trials : int or None
        Plain Monte Carlo with this many trials per node and U_p; None (default): the
        adaptive estimator where it applies (`cfm_fem.models.sweep.ESTIMATORS`), else
        `SWEEP_TRIALS` plain trials.
    seed : int
    mode : {"gauss", "htm"}
    bench : Bench or path-like, optional
        Mode htm: the bench (default the reference bench).
    progress : callable(int), optional
        Called with the nodes finished.
    **options
        Other arguments of `cfm_fem.workflows.sweep.run.run_sweep`: the
        `cfm_fem.models.sweep.SweepConfig` fields (``b_ref_T``, ``axis_scale``, ``outside``,
        ``interpolation``, ``hull_slivers``, ``chunk_nodes``, ``field_model``, ``region`` as a
        `cfm_fem.models.region.Region` or its text, as ``--region``: ``"cylinder:7,-30:30"``),
        ``reader`` (`read_map` options), and with ``out_dir`` the command line's ``pieces``,
        ``slabs``, ``resume``, ``table``, ...

    Returns
    -------
    cfm_fem.workflows.sweep.run.SweepRun
        A `cfm_fem.workflows.results.SweepMaps` (``result`` None after a run by slabs).
    """
    from .workflows.sweep.run import run_sweep as run

    trials = None if trials is None else int(trials)
    return run(field, up_um, trials=trials, seed=int(seed), mode=mode, bench=bench,
               progress=progress, **options)  # fmt: skip


def run_kinematics(bench=None, *, trials: int = KINEMATICS_TRIALS, seed: int = 0, progress=None,
               **options):  # fmt: skip
    """Probe positioning error over the scan grid (``cfm-fem kinematics``, Table IV).

    ``bench``: a `Bench`, a path, or None (the reference bench); ``options``: other arguments
    of `cfm_fem.workflows.kinematics.run_kinematics` (``adaptive_digits``, ``fast_intervals``,
    ``workers``, ``q_cmd``, ...).

    Returns
    -------
    cfm_fem.workflows.kinematics.KinematicsRun
        A `cfm_fem.workflows.results.KinematicsTable`; ``.summary`` is ``summary.json`` and
        ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.kinematics import run_kinematics as run

    return run(bench, trials=int(trials), seed=int(seed), progress=progress, **options)


def run_coupled(points=None, field=None, bench=None, *, trials: int = COUPLED_TRIALS,
                seed: int = 0, progress=None, **options):  # fmt: skip
    """Coupled Monte Carlo of the field error at scan points (``cfm-fem coupled``, Table V).

    Parameters
    ----------
    points : ndarray, shape (n, 3), mm, optional
        Scan points, magnet frame (e.g. `cfm_fem.workflows.coupled.default_region`); None: the
        command line's region (``radius_mm``, ``step_mm``, ``z_mm`` options).
    field : FieldMap, path-like or None
        Harmonics file or field map; None: the paper's QFDp4.
    bench : Bench, path-like or None
    **options
        Other arguments of `cfm_fem.workflows.coupled_run.run_coupled`: ``probe``, ``align``,
        ``centre_magnet``, ``b_ref_T``, ``r_ref_mm``, ``field_model``, ``budget`` (the
        positioning-only / probe-only split, default True as the command line), ...

    Returns
    -------
    cfm_fem.workflows.coupled_run.CoupledRun
        A `cfm_fem.workflows.results.CoupledTable`; ``.summary`` is ``summary.json`` and
        ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.coupled_run import run_coupled as run

    return run(field, bench, points, trials=int(trials), seed=int(seed), progress=progress,
               **options)  # fmt: skip


def _recording(recording):
    from .models.recordings import Recording

    return recording if isinstance(recording, Recording) else read_recording(recording)


def run_compare(recording, reference=None, bench=None, *, trials: int = COUPLED_TRIALS,
            seed: int = 0, progress=None, **options):  # fmt: skip
    """A recording against the simulation (``cfm-fem compare``).

    A tracker recording is compared with the kinematic Monte Carlo (Table IV both sides,
    ``pooled_exp`` / ``pooled_sim`` per axis); a Hall map, with ``reference`` (harmonics file,
    field map or FieldMap; None: QFDp4), with the coupled Monte Carlo (Table V).

    ``options``: other arguments of `cfm_fem.workflows.compare_run.run_compare`
    (``tracker_u_um``, ``probe``, ``align``, ``centre_magnet``, ``budget``, ...).

    Returns
    -------
    cfm_fem.workflows.compare_run.CompareRun
        The comparison's attributes (``pooled_exp``, ...) are the run's; ``.summary`` is
        ``compare.json`` and ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.compare_run import run_compare as run

    return run(_recording(recording), reference, bench, trials=int(trials), seed=int(seed),
               progress=progress, **options)  # fmt: skip


def run_diagnose(recording, reference=None, bench=None, *, b_ref_T=None, r_ref_mm=None,
                 field_model: str = "auto", progress=None, **reader):  # fmt: skip
    """What the simulation leaves out of a recording (``cfm-fem diagnose``).

    Parameters
    ----------
    recording : Recording or path-like
        A tracker recording or a Hall map (`read_recording`).
    reference : str, path-like, FieldMap or None
        Hall maps: a harmonics file, a field map, ``fit:DEG`` / ``fitz:DEG``; None: QFDp4.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    b_ref_T, r_ref_mm, field_model
        As ``--b-ref``, ``--r-ref``, ``--field-model``.
    **reader
        How a field map reference is read (``fmt``, ``length_unit``, ... of `read_map`).

    Returns
    -------
    cfm_fem.workflows.diagnose.run.DiagnoseRun
        ``.summary`` is ``diagnosis.json``; ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.diagnose.run import run_diagnose as run

    return run(_recording(recording), reference, bench, b_ref_T=b_ref_T, r_ref_mm=r_ref_mm,
               field_model=field_model, reader=reader or None, progress=progress)  # fmt: skip


def run_design(maps, uf_max: float, *, coverage: float = 0.95, region=None, seed: int = 0,
               **options):  # fmt: skip
    """Largest U_p that keeps U_f <= ``uf_max`` units over ``coverage`` of the nodes of a
    sweep (``cfm-fem design``), with its Monte Carlo standard uncertainty.

    Parameters
    ----------
    maps : cfm_fem.workflows.results.SweepMaps, path-like or FieldMap
        A mode-gauss sweep with increasing U_p; or a field map, swept first as the command
        line does (``options``: ``up_um``, ``trials`` (default 10,000), ``b_ref_T``,
        ``outside``, ``field_model``, ``reader``, ``progress`` of
        `cfm_fem.workflows.design_run.run_design`).
    uf_max : float
        Units of 1e-4 B_ref.
    coverage : float
    region : str or Region, optional
        ``"xmin:xmax,ymin:ymax,zmin:zmax"`` or ``"cylinder:R,zmin:zmax"`` (mm); default every
        node.
    seed : int

    Returns
    -------
    cfm_fem.workflows.design.DesignAnswer or cfm_fem.workflows.design_run.DesignRun
        The answer for a sweep given; for a map, the run (``.write(out_dir)`` writes the
        command's files; the answer's attributes are the run's).
    """
    from .workflows.results import SweepMaps

    if isinstance(maps, SweepMaps):
        from .workflows.design_run import design_answer

        if options:
            raise CfmInputError(f"{', '.join(options)}: for a field map, not for a sweep")
        return design_answer(maps, uf_max, coverage=coverage, region=region, seed=seed)
    from .workflows.design_run import run_design as run

    options.setdefault("trials", SWEEP_TRIALS)
    return run(maps, uf_max, coverage=coverage, region=region, seed=seed, **options)


def run_quality(field, r_ref_mm: float, *, up_um=None, mode=None, bench=None, trials=None,
                seed: int = 0, progress=None, **options):  # fmt: skip
    """Field quality of a map and its uncertainty from a bench (``cfm-fem quality``).

    Parameters
    ----------
    field : path-like or FieldMap
    r_ref_mm : float, mm
        Reference radius of the harmonics.
    up_um : float, optional, um
        Mode gauss: standard deviation per axis of the scan points.
    mode : {"gauss", "htm"}, optional
        Default gauss with ``up_um``, else htm.
    bench : Bench or path-like, optional
        Mode htm (default the reference bench).
    trials : int, optional
        Fixed trial count; default adaptive (JCGM 101 7.9.4).
    seed : int
    progress : callable(int), optional
    **options
        Other arguments of `cfm_fem.workflows.quality.run_quality` (``probe``, ``sampling``,
        ``main_order``, ``tolerances``, ``centre_magnet``, ``budget``, ...).

    Returns
    -------
    cfm_fem.workflows.quality.QualityRun
        ``.summary`` is ``quality.json``; ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.quality import run_quality as run

    return run(field, r_ref_mm, up_um=up_um, mode=mode, bench=bench, trials=trials, seed=seed,
               progress=progress, **options)  # fmt: skip


def run_design_quality(field, r_ref_mm: float, quantity: str, max_value: float, *,
                       trials: int = 2000, seed: int = 0, progress=None, **options):  # fmt: skip
    """Largest U_p that keeps U95 of a field-quality figure within ``max_value``
    (``cfm-fem design FIELD --quantity Q --max X --r-ref MM``).

    Parameters
    ----------
    field : path-like or FieldMap
    r_ref_mm : float, mm
        Reference radius of the harmonics.
    quantity : str
        ``b1`` .. ``b15``, ``a1`` .. ``a15`` (units), ``centre_x_um``, ``centre_y_um``,
        ``roll_mrad`` or ``magnetic_length_mm``.
    max_value : float
        Limit of its U95, in the quantity's unit.
    trials : int
        Trials of the quality Monte Carlo per U_p, as the command line's default.
    seed : int
    progress : callable(int), optional
    **options
        Other arguments of `cfm_fem.workflows.design_quality.quality_up_max` (``probe``,
        ``field_model``, ``sampling``, ``reader``, ...).

    Returns
    -------
    cfm_fem.workflows.design_quality.QualityDesign
        ``.summary()`` is ``design.json``; ``.write(out_dir)`` writes it.
    """
    from .workflows.design_quality import quality_up_max

    return quality_up_max(field, r_ref_mm, quantity, max_value, trials=trials, seed=seed,
                          progress=progress, **options)  # fmt: skip


def run_fig4(field, up_um=(0, 10, 20, 30, 40, 50), *, trials: int = 2000, seed: int = 0,
             b_ref_T=None, field_model: str = "linear", progress=None, **reader):  # fmt: skip
    """U_f (95 %) against U_p over a magnet's body, as the paper's Fig. 4 (``cfm-fem fig4``).

    Parameters
    ----------
    field : path-like or FieldMap
    up_um : sequence of float, um
        U_p values, as ``--up``.
    trials : int
        Trials per node and U_p, as the command line's default.
    seed : int
    b_ref_T : float, optional, T
        B_ref (default max |B| of the map).
    field_model : {"linear", "harmonic"}
        As ``--field-model``.
    progress : callable(int), optional
        Called with the nodes finished.
    **reader
        How the map is read (``fmt``, ``length_unit``, ... of `read_map`).

    Returns
    -------
    cfm_fem.workflows.fig4_run.Fig4Run
        ``.summary`` is ``fig4.json``; ``.write(out_dir)`` writes the command's files.
    """
    from .workflows.fig4_run import run_fig4 as run

    return run(field, up_um, trials=int(trials), seed=int(seed), b_ref_T=b_ref_T,
               field_model=field_model, reader=reader or None, progress=progress)  # fmt: skip


def run_tolerance(target_um, bench=None, *, check_trials: int = 0, seed: int = 0,
                  progress=None):  # fmt: skip
    """How far each of a bench's 21 tolerances may go for a target U_p (``cfm-fem tolerance``).

    Parameters
    ----------
    target_um : float or sequence of 3 float, um
        Target U_p, one value for every axis or X, Y, Z, as ``--target``.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    check_trials : int
        As ``--check``: verify the plan with a Monte Carlo of this many trials (0: no check).
    seed : int
        Of the check.
    progress : callable(int), optional
        Called with the trials of the check finished.

    Returns
    -------
    cfm_fem.workflows.tolerance.ToleranceRun
        ``.design`` is ``tolerance.json``'s content; ``.write(out_dir)`` writes the command's
        files.
    """
    import numpy as np

    from .workflows.tolerance import run_tolerance as run

    target = np.atleast_1d(np.asarray(target_um, dtype=float)).tolist()
    if len(target) == 1:
        target = target * 3
    return run(target, bench, check_trials=int(check_trials), seed=int(seed), progress=progress)
