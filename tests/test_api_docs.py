"""docs/api.md runs: its ```python blocks, in order, in one namespace; and the API's labels."""

import re
from pathlib import Path

import numpy as np
import pytest

import cfm_fem

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "api.md"


def _blocks(text):
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_api_doc_examples_run(tmp_path, monkeypatch, capsys):
    blocks = _blocks(DOC.read_text())
    assert len(blocks) >= 8
    (tmp_path / "meshes").symlink_to(ROOT / "meshes")
    (tmp_path / "results").mkdir()
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "api_doc"}
    for k, code in enumerate(blocks):
        exec(compile(code, f"{DOC}:block{k + 1}", "exec"), namespace)
    printed = capsys.readouterr().out
    assert "keeps U_f <= 15 units over 95 % of the nodes" in printed
    maps = namespace["maps"]
    assert maps.percentile(95, up_um=20) == maps.summary["uf_units"]["p95"][2]


def test_labels_pick_the_same_numbers_as_the_arrays():
    ax = np.linspace(-2.0, 2.0, 5)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    fm = cfm_fem.FieldMap(points=pts, B=np.c_[0.1 * pts[:, 1], 0.1 * pts[:, 0], np.ones(125)])
    maps = cfm_fem.run_sweep(fm, up_um=[5, 15], trials=300, seed=2)
    res = maps.result
    k, c = 1, 0  # up_um=15, Bx
    keep = res.complete()[:, k]
    st = res.stats[:, k, c]
    np.testing.assert_array_equal(
        maps.uf("Bx", up_um=15)[keep],
        res.to_units(np.maximum(np.abs(st[:, 2]), np.abs(st[:, 3])))[keep],
    )
    np.testing.assert_array_equal(maps.uf(column="up15um"), maps.uf("absB", up_um=15))
    np.testing.assert_array_equal(maps.stat("u", "Bx", up_um=15)[keep], res.to_units(st[keep, 1]))
    assert np.isnan(maps.uf(up_um=15)[~keep]).all()
    for bad, message in (
        (lambda: maps.uf(up_um=10), "U_p = 10 um is not in this sweep"),
        (lambda: maps.uf("Bq", up_um=5), "component 'Bq' unknown"),
        (lambda: maps.uf(), "give up_um= or column="),
        (lambda: maps.stat("median", up_um=5), "statistic 'median' unknown"),
    ):
        with pytest.raises(cfm_fem.CfmInputError, match=message):
            bad()


def test_api_uses_the_command_lines_defaults():
    import inspect

    from cfm_fem.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices
    pairs = {
        "sweep": cfm_fem.run_sweep,
        "kinematics": cfm_fem.run_kinematics,
        "coupled": cfm_fem.run_coupled,
        "compare": cfm_fem.run_compare,
    }
    for name, func in pairs.items():
        default = inspect.signature(func).parameters["trials"].default
        assert default == sub[name].get_default("trials"), name
