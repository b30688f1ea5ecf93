"""``open_in_paraview.py``: the view it builds, run against a recording stand-in of
``paraview.simple`` (ParaView itself is not a test dependency)."""

import json
import sys
import types

import numpy as np
import pytest

from cfm_fem.io.paraview_script import PARAVIEW_SCRIPT, write_paraview_script


class _Proxy(types.SimpleNamespace):
    pass


class _Plane(_Proxy):
    pass


class _Slice(_Proxy):
    def __setattr__(self, name, value):
        if name == "SliceType" and isinstance(value, str):
            value = _Plane(kind=value)
        super().__setattr__(name, value)


class _Range:
    """A point array's information: ``GetRange`` per time step (U_f grows with U_p)."""

    def __init__(self, calls):
        self.calls = calls

    def GetRange(self):
        t = self.calls["updated_at"]
        return (0.0, 0.0) if t == 0 else (0.5 * t, 2.0 * t)


def _fake_paraview(bounds, calls, modern=True, times=(0.0, 10.0, 20.0)):
    simple = types.ModuleType("paraview.simple")

    class Info:
        def GetBounds(self):
            return bounds

    def open_data_file(path):
        calls["opened"] = path
        return _Proxy(GetDataInformation=Info, TimestepValues=list(times))

    def update_pipeline(t=None):
        calls["updated_at"] = t

    def threshold(Input):
        t = _Proxy(Input=Input)
        if modern:
            t.LowerThreshold = t.UpperThreshold = None
        calls["threshold"] = t
        return t

    def slice_(Input):
        s = _Slice(Input=Input)
        s.UpdatePipeline = update_pipeline
        s.PointData = {"U_f_units": _Range(calls)}
        calls["slice"] = s
        return s

    scene = _Proxy(UpdateAnimationUsingDataTimeSteps=lambda: None)
    calls["scene"] = scene
    lut = _Proxy(RescaleTransferFunction=lambda lo, hi: calls.setdefault("range", (lo, hi)))

    def color_by(shown, what):
        calls["color"] = what

    shown = _Proxy(
        RescaleTransferFunctionToDataRange=lambda *a: None,
        SetScalarBarVisibility=lambda *a: None,
    )
    simple.OpenDataFile = open_data_file
    simple.Threshold = threshold
    simple.Slice = slice_
    simple.GetActiveViewOrCreate = lambda kind: _Proxy()
    simple.Show = lambda src, view: shown
    simple.ColorBy = color_by
    simple.GetAnimationScene = lambda: scene
    simple.GetColorTransferFunction = lambda name: calls.setdefault("lut", name) and lut
    simple.ResetCamera = lambda view: None
    simple.Render = lambda view: None
    simple.SaveScreenshot = lambda path, view: calls.setdefault("screenshot", path)
    simple.Interact = lambda view: calls.setdefault("interact", True)
    pkg = types.ModuleType("paraview")
    pkg.simple = simple
    return {"paraview": pkg, "paraview.simple": simple}


@pytest.mark.parametrize("modern", [True, False])
def test_script_opens_the_sweep_thresholds_complete_and_cuts_through_the_axis(
    tmp_path, monkeypatch, modern
):
    path = write_paraview_script(tmp_path)
    assert path.read_text() == PARAVIEW_SCRIPT
    calls = {}
    monkeypatch.setattr(sys, "argv", [str(path), "--screenshot", "shot.png"])
    for name, mod in _fake_paraview((-10, 10, 5, 25, -80, 80), calls, modern).items():
        monkeypatch.setitem(sys.modules, name, mod)
    exec(compile(path.read_text(), str(path), "exec"), {"__file__": str(path)})
    assert calls["opened"] == str(tmp_path / "sweep.pvd")
    t = calls["threshold"]
    assert t.Scalars == ["POINTS", "complete"]
    if modern:
        assert (t.LowerThreshold, t.UpperThreshold) == (1, 1)
    else:
        assert t.ThresholdRange == [1, 1]
    plane = calls["slice"].SliceType
    # x = 0 is inside the map, y = 0 is not: the centre of y; z at the centre
    np.testing.assert_allclose(plane.Origin, [0.0, 15.0, 0.0])
    assert plane.Normal == [0.0, 1.0, 0.0]
    assert calls["color"] == ("POINTS", "U_f_units")
    assert calls["screenshot"] == "shot.png" and "interact" not in calls


@pytest.mark.parametrize(
    ("argv", "mode", "shown"),
    [([], "gauss", 20.0), (["--up-um", "9"], "gauss", 10.0), ([], "htm", 0.0)],
)
def test_script_opens_at_the_largest_up_with_the_colour_range_set(
    tmp_path, monkeypatch, capsys, argv, mode, shown
):
    path = write_paraview_script(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps({"mode": mode}))
    calls = {}
    monkeypatch.setattr(sys, "argv", [str(path), *argv, "--screenshot", "s.png"])
    for name, mod in _fake_paraview((-10, 10, -10, 10, -80, 80), calls).items():
        monkeypatch.setitem(sys.modules, name, mod)
    exec(compile(path.read_text(), str(path), "exec"), {"__file__": str(path)})
    assert calls["scene"].AnimationTime == shown and calls["updated_at"] == shown
    if shown:
        assert calls["lut"] == "U_f_units" and calls["range"] == (0.5 * shown, 2.0 * shown)
    else:  # a blank plane (htm total in this stand-in): the range is left as ParaView sets it
        assert "range" not in calls
    out = capsys.readouterr().out
    assert "U_f on the plane" in out
    if mode == "gauss":
        assert f"U_p = {shown:g} um" in out
