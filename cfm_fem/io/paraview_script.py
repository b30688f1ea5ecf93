"""``open_in_paraview.py``: the pvpython script written beside a sweep's ``sweep.pvd``.

Run ``pvpython DIR/open_in_paraview.py`` (or, in ParaView, View > Python Shell > Run Script):
it opens the collection at the map a user looks at first (the largest U_p; mode htm: the total,
time 0; ``--up-um X``: the U_p nearest X), keeps the nodes with a U_f figure (threshold on
``complete`` = 1), cuts the plane through the magnet axis (normal y), colours it by
``U_f_units`` with the colour range set to that plane's U_f, and prints both. The script finds
``sweep.pvd`` beside itself, so the folder can be moved.
"""

from __future__ import annotations

from pathlib import Path

from ._atomic import write_text

__all__ = ["PARAVIEW_SCRIPT", "write_paraview_script"]

SCRIPT_NAME = "open_in_paraview.py"

PARAVIEW_SCRIPT = '''\
"""Open this folder's cfm-fem sweep in ParaView: U_f on the plane through the magnet axis.

Run with ``pvpython open_in_paraview.py`` (a window opens; ``--screenshot FILE.png`` saves
the view instead; ``--up-um X`` shows the map of the U_p nearest X um), or in ParaView: View >
Python Shell > Run Script. It opens at the largest U_p (mode htm: the total, time 0), with the
colour range set to U_f on the plane shown. The time slider steps through the maps of
sweep.pvd: U_p in um (mode gauss), or the columns total, geometric, vibration/delay at times
0, 1, 2 (mode htm; each map's field data ``column_utf8`` names it).
"""

import json
import os
import sys

from paraview import simple

here = os.path.dirname(os.path.abspath(globals().get("__file__", "open_in_paraview.py")))
sweep = simple.OpenDataFile(os.path.join(here, "sweep.pvd"))
try:
    with open(os.path.join(here, "summary.json"), encoding="utf-8") as f:
        mode = json.load(f).get("mode", "gauss")
except (OSError, ValueError):
    mode = "gauss"

# the time step shown: the largest U_p (htm: the total, time 0), or the one nearest --up-um
times = getattr(sweep, "TimestepValues", None)
times = [times] if isinstance(times, (int, float)) else list(times or [])
shown_time = None
if times:
    if "--up-um" in sys.argv:
        wanted = float(sys.argv[sys.argv.index("--up-um") + 1])
        shown_time = min(times, key=lambda t: abs(t - wanted))
    else:
        shown_time = times[0] if mode == "htm" else max(times)
    scene = simple.GetAnimationScene()
    scene.UpdateAnimationUsingDataTimeSteps()
    scene.AnimationTime = shown_time

# nodes whose every trial has a value: the others carry no U_f (NaN)
threshold = simple.Threshold(Input=sweep)
threshold.Scalars = ["POINTS", "complete"]
if hasattr(threshold, "LowerThreshold"):
    threshold.LowerThreshold = 1
    threshold.UpperThreshold = 1
else:
    threshold.ThresholdRange = [1, 1]
threshold.AllScalars = 1  # a cell is kept only when all its nodes are complete

# the plane through the axis (z): x = 0 and y = 0 when the map holds them, else its centre
xmin, xmax, ymin, ymax, zmin, zmax = sweep.GetDataInformation().GetBounds()
origin = [
    0.0 if xmin <= 0.0 <= xmax else 0.5 * (xmin + xmax),
    0.0 if ymin <= 0.0 <= ymax else 0.5 * (ymin + ymax),
    0.5 * (zmin + zmax),
]
cut = simple.Slice(Input=threshold)
cut.SliceType = "Plane"
cut.SliceType.Origin = origin
cut.SliceType.Normal = [0.0, 1.0, 0.0]

view = simple.GetActiveViewOrCreate("RenderView")
if shown_time is not None:
    view.ViewTime = shown_time
shown = simple.Show(cut, view)
simple.ColorBy(shown, ("POINTS", "U_f_units"))
# the colour range: U_f on the plane at the time shown (not the first step's, U_p = 0: blank)
cut.UpdatePipeline(shown_time if shown_time is not None else 0.0)
low, high = cut.PointData["U_f_units"].GetRange()
if high > low:
    simple.GetColorTransferFunction("U_f_units").RescaleTransferFunction(low, high)
shown.SetScalarBarVisibility(view, True)
if shown_time is None:
    where = "the map"
elif mode == "htm":
    where = f"time {shown_time:g} (mode htm: 0 total, 1 geometric, 2 vibration and delay)"
else:
    where = f"U_p = {shown_time:g} um"
print(f"{where}: U_f on the plane from {low:.4g} to {high:.4g} units")
view.CameraPosition = [origin[0], origin[1] + 3.0 * max(xmax - xmin, zmax - zmin), origin[2]]
view.CameraFocalPoint = origin
view.CameraViewUp = [1.0, 0.0, 0.0]
simple.ResetCamera(view)
simple.Render(view)
if "--screenshot" in sys.argv:
    simple.SaveScreenshot(sys.argv[sys.argv.index("--screenshot") + 1], view)
elif sys.argv and sys.argv[0].endswith("open_in_paraview.py"):  # pvpython, not the GUI
    simple.Interact(view)
'''


def write_paraview_script(out_dir) -> Path:
    """Write `PARAVIEW_SCRIPT` as ``out_dir/open_in_paraview.py`` (atomically); return its
    path."""
    path = Path(out_dir) / SCRIPT_NAME
    write_text(path, PARAVIEW_SCRIPT)
    return path
