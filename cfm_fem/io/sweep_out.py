"""Write a sweep: one ``.vtu`` per U_p value, ``sweep.pvd`` (U_p as ParaView's time) and
``summary.json``."""

from __future__ import annotations

import json
import re
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from ..models.sweep import COMPONENTS, SweepResult, summarize
from ..threads import map_threads, map_threads_widening
from ._atomic import TEMPORARY_AGE_S, remove_old_temporaries, write_json
from .lock import locks_output
from .paraview_script import write_paraview_script
from .pvtu import GHOST_ARRAY, ghost_flags, write_pvtu
from .vtk import read_text_field, write_pvd, write_vtu
from .vtu_stream import EncodedArray, MeshBlock, write_mesh_vtu

__all__ = [
    "write_sweep",
    "write_sweep_pieces",
    "vtu_name",
    "provenance_text",
    "read_provenance",
    "map_field_data",
    "remove_stale_maps",
    "remove_leftover_temporaries",
    "remove_earlier_outputs",
]


def vtu_name(label: str) -> str:
    """File name of the map of one column, e.g. ``uf_up20um.vtu`` or ``uf_htm_total.vtu``."""
    return f"uf_{label}.vtu"


def provenance_text(provenance: dict | None) -> str:
    """The provenance as JSON text: the field data ``provenance_utf8`` of every map (its UTF-8
    bytes, `cfm_fem.io.vtk.write_vtu`; `read_provenance` turns it back)."""
    return json.dumps(provenance or {}, sort_keys=True)


def read_provenance(field_data) -> dict:
    """Inverse of `provenance_text`: the provenance of a map, as a dict, from its field data
    (the mapping meshio's or pyvista's reader gives, holding ``provenance_utf8``), or from the
    JSON text itself."""
    if isinstance(field_data, str):
        return json.loads(field_data)
    return json.loads(read_text_field(field_data, "provenance"))


def _shared_values(res: SweepResult) -> dict:
    """The point data that is the same in every map of a sweep: the nominal field, its
    gradient, the nodes' volumes and what the field model is worth at each node."""
    f32 = np.float32
    n = len(res.fieldmap.B)
    data = {
        "B_nominal_T": res.fieldmap.B,
        "absB_nominal_T": np.sqrt((res.fieldmap.B**2).sum(axis=1)),
        "grad_B_T_per_mm": res.gradient.reshape(n, 9),
        "node_volume_mm3": res.node_volumes().astype(f32),
        "linear_in_up": res.linear_in_up.astype(np.uint8),
    }
    if res.config.region is not None:  # the nodes of the summary's percentiles
        data["in_region"] = res.config.region.mask(res.fieldmap.points).astype(np.uint8)
    if res.field_fit is not None:  # harmonic model: what each node's fit is worth
        data["field_fit_degree"] = res.field_fit["degree"].astype(np.uint8)
        residual = res.to_units(res.field_fit["residual_T"])
        data["field_fit_residual_units"] = residual.astype(f32)
    return data


def shared_point_data(res: SweepResult, pool=None) -> dict:
    """The point data every map of a sweep holds alike (`_shared_values`), each array encoded
    once (`cfm_fem.io.vtu_stream.EncodedArray`; ``pool`` compresses their blocks side by
    side)."""
    return {k: EncodedArray(k, v, pool) for k, v in _shared_values(res).items()}


def _point_data(res: SweepResult, k: int, shared: dict | None = None) -> dict:
    """Per-node arrays for column ``k``; names say the quantity and the unit.

    A statistic of the error is a node's figure only where every trial has a value
    (``complete`` = 1); elsewhere (a node on the map's surface whose perturbed positions partly
    left the map) the per-component statistics are NaN, and the |B| figures of the trials that
    stayed inside are kept apart, under ``absB_*_inside_trials_units``. ``shared``
    (`shared_point_data`) holds the arrays every map has alike (computed here without it).
    """
    const = _shared_values(res) if shared is None else shared
    st = res.stats[:, k]  # (n, 4, 6)
    units = res.to_units
    U95 = res.expanded_95(k)  # one column at a time: no map-sized temporaries per column
    _, _, disagree = res.gum_check(k)
    complete = res.complete()[:, k]
    partial = ~complete & np.isfinite(st[:, 3, 1])  # truncated sample: not a U_f
    f32 = np.float32  # Monte Carlo noise is ~1e-2 relative: float32 loses nothing, halves the files

    def only(mask, values):
        return np.where(mask, values, np.nan).astype(f32)

    data = {name: const[name] for name in ("B_nominal_T", "absB_nominal_T", "grad_B_T_per_mm")}
    data |= {
        "U_f_units": only(complete, units(U95[:, 3])),
        "absB_U95_inside_trials_units": only(partial, units(U95[:, 3])),
        "absB_systematic_inside_trials_units": only(partial, units(st[:, 3, 0])),
        "outside_fraction": (res.n_outside[:, k] / res.config.trials).astype(f32),
        "walk_failed_fraction": (res.n_walk_failed[:, k] / res.config.trials).astype(f32),
        "complete": complete.astype(np.uint8),
    }
    rest = ("node_volume_mm3", "linear_in_up", "in_region", "field_fit_degree",
            "field_fit_residual_units")  # fmt: skip
    data |= {name: const[name] for name in rest if name in const}
    if res.positioning is not None:
        data["positioning_mean_um"] = (res.positioning[:, k, 0] * 1e3).astype(f32)
        data["positioning_std_um"] = (res.positioning[:, k, 1] * 1e3).astype(f32)
        data["positioning_corr_xy_xz_yz"] = res.positioning[:, k, 2].astype(f32)
        gum_mean = res.gum_mean[:, k]
    for c, name in enumerate(COMPONENTS):
        per = {
            "systematic_units": units(st[:, c, 0]),
            "u_units": units(st[:, c, 1]),
            "sym95_low_units": units(st[:, c, 2]),
            "sym95_high_units": units(st[:, c, 3]),
            "short95_low_units": units(st[:, c, 4]),
            "short95_high_units": units(st[:, c, 5]),
        }
        if c != 3:  # |B|: its U95 is U_f_units
            per["U95_units"] = units(U95[:, c])
        for key, values in per.items():
            data[f"{name}_{key}"] = only(complete, values)
        # the GUM figures come from the gradient, not from the trials: defined at every node
        data[f"{name}_gum_U95_units"] = units(1.959963984540054 * res.gum_u[:, k, c]).astype(f32)
        if res.positioning is not None:  # GUM interval: systematic +- gum_U95
            data[f"{name}_gum_systematic_units"] = units(gum_mean[:, c]).astype(f32)
        data[f"{name}_gum_disagree"] = (disagree[:, c] & complete).astype(np.uint8)
    return data


def map_field_data(
    up_um: float, label: str, b_ref_T: float, config, provenance: dict | None, **extra
) -> dict:
    """Field data of one map: U_p (um), the column's name (``up20um``, ``htm_geometric``: mode
    htm's time steps 0, 1, 2 are its columns), B_ref (T), trials, seed, ``extra`` (``piece``)
    and the provenance as JSON text; the texts are written as UTF-8 bytes, ``column_utf8`` and
    ``provenance_utf8`` (`cfm_fem.io.vtk.write_vtu`, `cfm_fem.io.vtk.read_text_field`)."""
    return {
        "U_p_um": float(up_um),
        "column": str(label),
        "B_ref_T": float(b_ref_T),
        "trials": int(config.trials),
        "seed": int(config.seed),
        **extra,
        "provenance": provenance_text(provenance),
    }


#: Memory that maps written side by side may take in all (each map: its point data, and
#: the points and cells encoded once for all of them).
_WRITE_BYTES = 1 << 30
#: Point-data values per node of one map (float32-equivalent, `_point_data`; an estimate).
_POINT_VALUES = 110


def retire_index(out: Path) -> None:
    """Remove the ``summary.json`` and ``sweep.pvd`` an earlier run left in ``out``; called
    before the first new map is written. A run stopped while writing then leaves new maps and
    no summary, not new maps under the old run's summary and index."""
    for name in ("summary.json", "sweep.pvd"):
        path = out / name
        if path.is_file() and not path.is_symlink():
            path.unlink()


def _most_writers(res: SweepResult) -> int:
    """Most maps written side by side: one per core, as many as fit `_WRITE_BYTES` (each
    writer holds its map's point data; zlib compresses without the GIL)."""
    n = len(res.fieldmap.points)  # its point data, and the encoding of the shared cells
    per_map = max(1, n * (24 + 4 * _POINT_VALUES) + res.mesh.simplices.size * 16)
    return max(1, min(_WRITE_BYTES // per_map, numba.get_num_threads()))


def encode_shared(res: SweepResult, writers: int | None = None) -> tuple:
    """What every map of ``res`` holds alike, encoded once: (the points and cells,
    `cfm_fem.io.vtu_stream.MeshBlock`; the shared point data, `shared_point_data`), their
    blocks compressed side by side on up to ``writers`` threads (default: `_most_writers`)."""
    most = _most_writers(res)
    with ThreadPoolExecutor(max(1, min(writers or most, most))) as pool:
        mesh = MeshBlock(res.fieldmap.points, res.mesh.simplices, pool)
        return mesh, shared_point_data(res, pool)


@locks_output  # one run at a time in out_dir (cfm_fem.io.lock)
def write_sweep(
    out_dir, res: SweepResult, provenance: dict | None = None, *, remove_stale: bool = True,
    summary: dict | None = None, writers: int | None = None, widen_after=None, encoded=None,
) -> dict:  # fmt: skip
    """Write every output of a sweep into ``out_dir``; return the summary that was written.

    The maps are written first, then ``sweep.pvd``, then ``summary.json``: each file atomically,
    so an interrupted run never leaves a partial file and a present summary means a complete run
    (an earlier run's summary and index are removed first, `retire_index`).

    Parameters
    ----------
    out_dir : path-like
    res : SweepResult
    provenance : dict, optional
    remove_stale : bool
        Once the new outputs are complete, remove what an earlier sweep left in ``out_dir``
        that they do not use (`remove_earlier_outputs`: its maps that ``sweep.pvd`` does not
        name, the temporaries of a killed run); False leaves them (``cfm-fem sweep`` removes
        them itself and names them).
    summary : dict, optional
        ``summarize(res)``, when the caller made it already (its provenance is set here).
    writers : int, optional
        Most maps written at once (default: numba's threads, one per core; fewer if their
        memory would exceed `_WRITE_BYTES`): each writer holds its map's point data, so more
        writers than cores only add memory. The points and cells are encoded once for all
        maps (`cfm_fem.io.vtu_stream.MeshBlock`).
    widen_after : concurrent.futures.Future, optional
        Another task sharing the cores (the report's figures): ``writers`` maps are written
        at once until it is done, then as many as the default allows.
    encoded : tuple, optional
        `encode_shared` of ``res``, when the caller made it already (before starting a task
        that holds the GIL, which the encoding's threads would wait for).

    Raises
    ------
    CfmInputError
        Another run writes into ``out_dir`` (the call holds its lock, `cfm_fem.io.lock`):
        nothing is written or removed.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(res) if summary is None else summary
    retire_index(out)
    summary["provenance"] = provenance or {}
    ups = res.column_up_um()
    most = _most_writers(res)
    mesh, shared = encode_shared(res, writers) if encoded is None else encoded

    def write_map(k):
        path = out / vtu_name(res.labels[k])
        fields = map_field_data(
            ups[k], res.labels[k], res.b_ref_T, res.config, summary["provenance"]
        )
        write_mesh_vtu(path, mesh, _point_data(res, k, shared), fields)
        return (ups[k] if res.config.mode == "gauss" else float(k), path)

    first = most if writers is None else max(1, min(writers, most))
    if widen_after is None:
        entries = map_threads(write_map, range(len(res.labels)), first)
    else:
        entries = map_threads_widening(write_map, range(len(res.labels)), first, most,
                                       widen_after)  # fmt: skip
    write_pvd(out / "sweep.pvd", entries, provenance=summary["provenance"])
    write_paraview_script(out)
    write_json(out / "summary.json", summary)
    if remove_stale:
        remove_earlier_outputs(out)
    return summary


def pieces_name(up_um: float) -> str:
    """Index file of the pieces of one U_p value, e.g. ``uf_up20um.pvtu``."""
    return f"uf_up{up_um:g}um.pvtu"


@locks_output  # one run at a time in out_dir (cfm_fem.io.lock)
def write_sweep_pieces(
    out_dir, compact, n_pieces: int, load, provenance: dict | None = None, *, remove_stale=True
):
    """Write a sweep as ``n_pieces`` ``.vtu`` pieces per U_p value, a ``.pvtu`` index each, the
    ``sweep.pvd`` over the indices and ``summary.json``; only one piece in memory at a time.

    Parameters
    ----------
    out_dir : path-like
    compact : cfm_fem.models.sweep.CompactSweep
    n_pieces : int
    load : callable(nodes) -> (stats, n_outside, n_walk_failed, linear_in_up)
        Reads back the statistics of the sorted node indices ``nodes`` (e.g. from the chunk
        store: `cfm_fem.workflows.sweep.resume.ResumableRun.gather`).
    provenance : dict, optional
    remove_stale : bool
        As in `write_sweep`: an earlier sweep's maps this one does not use (e.g. its one-file
        maps, or pieces beyond ``n_pieces``) are removed once the new outputs are complete.

    Returns
    -------
    dict
        The summary written (the same as `write_sweep` gives for the same run).

    Raises
    ------
    CfmInputError
        Another run writes into ``out_dir``, as in `write_sweep`.

    Notes
    -----
    Pieces are node ranges; each cell belongs to the piece of its highest node, and a piece
    also holds the nodes of its cells that lie in earlier ranges (their data are repeated), so
    every cell is drawn once and ParaView shows one continuous map. The repeated copies are
    flagged as VTK ghost points (``vtkGhostType`` = 1; the piece whose range holds a node owns
    it), so that VTK and ParaView count every node once.
    """
    from ..models.sweep import partition, piece_bounds, piece_result

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(compact)
    summary["provenance"] = provenance or {}
    summary["pieces"] = int(n_pieces)
    retire_index(out)
    # columns by label, so that mode htm (3 columns, no U_p list) works as gauss does
    labels = compact.labels
    ups = compact.column_up_um()
    names = {}
    written = {k: [] for k in range(len(labels))}
    fm = compact.fieldmap
    bounds = piece_bounds(fm.n_nodes, n_pieces)
    for p, (nodes, cells) in enumerate(partition(compact.mesh.simplices, fm.n_nodes, n_pieces)):
        res = piece_result(compact, nodes, load(nodes))
        ghost = ghost_flags((nodes >= bounds[p]) & (nodes < bounds[p + 1]))
        for k, label in enumerate(labels):
            folder = out / vtu_name(label).removesuffix(".vtu")
            path = folder / f"piece_{p:04d}.vtu"
            fields = map_field_data(
                ups[k], label, compact.b_ref_T, compact.config, summary["provenance"], piece=p
            )
            data = dict(_point_data(res, k), **{GHOST_ARRAY: ghost})
            write_vtu(path, res.fieldmap.points, cells, data, fields)
            written[k].append(path)
            names[k] = {name: values[:1] for name, values in data.items()}
        del res
    entries = []
    for k, label in enumerate(labels):
        path = out / vtu_name(label).replace(".vtu", ".pvtu")
        write_pvtu(path, written[k], names[k], provenance=summary["provenance"])
        entries.append((ups[k] if compact.config.mode == "gauss" else float(k), path))
    write_pvd(out / "sweep.pvd", entries, provenance=summary["provenance"])
    write_paraview_script(out)
    write_json(out / "summary.json", summary)
    if remove_stale:
        remove_earlier_outputs(out)
    return summary


#: Bytes read from the head of a file to tell whether a sweep wrote it (`_written_by_sweep`).
_HEAD_BYTES = 1 << 20


def _written_by_sweep(path: Path) -> bool:
    """True for a map a sweep writes (`write_sweep`, `write_sweep_pieces`,
    `cfm_fem.workflows.sweep.slabs`), told by its contents, not only by its name: a ``.vtu``
    whose field data (written before the points) hold ``U_p_um`` and the provenance
    (``provenance_utf8``, or ``provenance`` as a VTK string array), or a ``.pvtu`` index of
    ``U_f_units``."""
    try:
        with open(path, "rb") as f:
            head = f.read(_HEAD_BYTES)
    except OSError:
        return False
    if path.suffix == ".pvtu":
        return b'<VTKFile type="PUnstructuredGrid"' in head and b'Name="U_f_units"' in head
    return (
        b'<VTKFile type="UnstructuredGrid"' in head
        and b'Name="U_p_um"' in head
        and (b'Name="provenance"' in head or b'Name="provenance_utf8"' in head)
    )


def _current_maps(out: Path) -> set[Path] | None:
    """The files named by ``out/sweep.pvd`` and the pieces of its ``.pvtu`` indices (resolved);
    None when the collection cannot be read (then nothing is stale)."""
    import xml.etree.ElementTree as ET

    try:
        files = set()
        for ds in ET.parse(out / "sweep.pvd").getroot().iter("DataSet"):
            f = (out / ds.get("file")).resolve()
            files.add(f)
            if f.suffix == ".pvtu":
                for piece in ET.parse(f).getroot().iter("Piece"):
                    files.add((f.parent / piece.get("Source")).resolve())
    except (OSError, ET.ParseError, TypeError):
        return None
    return files


def remove_stale_maps(out_dir) -> tuple[list[str], list[str]]:
    """Remove the maps an earlier sweep left in ``out_dir`` that the sweep just written there
    does not use; call it after the new outputs are written (they are then complete).

    A map is stale when its name is one a sweep gives (``uf_*.vtu``, ``uf_*.pvtu`` and
    ``uf_*/piece_*.vtu``), ``sweep.pvd`` (and its ``.pvtu`` indices) do not name it, and its
    contents show that a sweep wrote it (`_written_by_sweep`): e.g. ``uf_up50um.vtu`` after a
    re-run without 50 um, ``uf_up20um.vtu`` after a re-run with pieces, piece files beyond the
    new piece count. A piece folder left empty is removed. Anything else (symbolic links, other
    files, a folder with other files in it) is never deleted.

    Returns
    -------
    removed : list of str
        Paths relative to ``out_dir`` of the files (and emptied piece folders, ending in ``/``)
        removed.
    kept : list of str
        Files with a map's name that are neither this run's nor recognised as a sweep's: left.
    """
    out = Path(out_dir)
    current = _current_maps(out)
    removed, kept = [], []
    if current is None:
        return removed, kept

    def visit(f: Path):
        if f.resolve() in current:
            return
        rel = f.relative_to(out).as_posix()
        if f.is_file() and not f.is_symlink() and _written_by_sweep(f):
            f.unlink()
            removed.append(rel)
        else:
            kept.append(rel)

    for entry in sorted(out.glob("uf_*")):
        if entry.suffix in (".vtu", ".pvtu") and not entry.is_dir():
            visit(entry)
        elif entry.is_dir() and not entry.is_symlink():
            n = len(removed)
            for piece in sorted(entry.glob("piece_*.vtu")):
                visit(piece)
            if len(removed) > n and not any(entry.iterdir()):
                entry.rmdir()
                removed.append(entry.relative_to(out).as_posix() + "/")
    return removed, kept


#: Files of a sweep's output folder, and of its piece folders (``uf_*/``), that are written
#: through a temporary (`cfm_fem.io._atomic.atomic_path`).
_OUTPUT_NAME = re.compile(r"uf_[^/]+\.(vtu|pvtu)|sweep\.pvd|summary\.json")
_PIECE_NAME = re.compile(r"piece_[0-9]+\.vtu")


def remove_leftover_temporaries(out_dir, min_age_s: float = TEMPORARY_AGE_S) -> list[str]:
    """Remove the temporaries of sweep outputs that a killed run left in ``out_dir``.

    A run killed while writing leaves the hidden temporary of the file it was writing, named
    ``.<output>.<8 random characters>.<suffix>`` (e.g. ``.uf_up20um.vtu.k3x_9abq.vtu``). Only
    regular files (no symbolic link) named so for one of a sweep's outputs (``uf_*.vtu``,
    ``uf_*.pvtu``, ``sweep.pvd``, ``summary.json``) in ``out_dir``, or for a piece
    (``piece_<k>.vtu``) in one of its piece folders ``uf_*/``, and last modified at least
    ``min_age_s`` seconds ago, are removed; call it once the run's own outputs are written
    (its own temporaries are renamed by then).

    A younger temporary is left (`TEMPORARY_AGE_S`): another run writing into the same folder
    at the same time would otherwise lose the file it is writing. A later run removes it.

    Returns
    -------
    list of str
        Paths relative to ``out_dir`` of the files removed.
    """
    out = Path(out_dir)
    if not out.is_dir():
        return []
    now = time.time()
    removed = remove_old_temporaries(out, _OUTPUT_NAME, min_age_s, now)
    for folder in sorted(out.glob("uf_*")):
        if folder.is_dir() and not folder.is_symlink():
            removed += remove_old_temporaries(folder, _PIECE_NAME, min_age_s, now)
    return [f.relative_to(out).as_posix() for f in removed]


def remove_earlier_outputs(out_dir) -> tuple[list[str], list[str], list[str]]:
    """After a sweep was written into ``out_dir`` (its ``sweep.pvd`` and ``summary.json`` are
    in place): remove the temporaries a killed run left (`remove_leftover_temporaries`), then
    the maps of an earlier sweep that this one does not use (`remove_stale_maps`). Never call
    it before the new outputs are complete: the earlier maps are then all stale.

    Returns
    -------
    temporaries, removed, kept : list of str
        The temporaries removed, and `remove_stale_maps`'s two lists.
    """
    temporaries = remove_leftover_temporaries(out_dir)
    removed, kept = remove_stale_maps(out_dir)
    return temporaries, removed, kept
