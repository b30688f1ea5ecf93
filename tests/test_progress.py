"""Progress of long work when stderr is a log file, not a terminal."""

from __future__ import annotations

import io
import re
import sys

from cfm_fem.cli import _progress


def test_log_progress_writes_plain_lines_with_count_percentage_and_time(monkeypatch):
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    with _progress.progress_bar(200, "nodes", interval=0.0) as bar:
        bar.update(50)
        bar.update(150)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue()
    assert re.fullmatch(r"cfm-fem: 50 / 200 nodes \(25 %\), \d+ s, about \d+ s left", lines[0])
    assert lines[1].startswith("cfm-fem: 200 / 200 nodes (100 %), ")
    assert len(lines) == 2  # the last line gave the final count: no closing line repeats it


def test_log_progress_stays_silent_for_work_shorter_than_the_interval(monkeypatch):
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    with _progress.progress_bar(None, "trials", interval=3600.0) as bar:
        bar.update(10)
    assert log.getvalue() == ""


def test_log_progress_limits_lines_to_one_per_interval(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(_progress.time, "monotonic", lambda: clock[0])
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    with _progress.progress_bar(None, "fits", interval=5.0) as bar:
        for _ in range(30):  # one fit a second: a line at 5, 10, ..., 30 s
            clock[0] += 1.0
            bar.update(1)
        bar.total = 30  # the slab sweep learns its total late
        bar.refresh()
        bar.write("cfm-fem sweep: a message", file=sys.stderr)
    lines = log.getvalue().splitlines()
    assert lines[:6] == [f"cfm-fem: {5 * k} fits, {5 * k} s" for k in range(1, 7)]
    assert lines[6:] == ["cfm-fem sweep: a message", "cfm-fem: 30 / 30 fits (100 %), 30 s"]


def test_kinematics_progress_counts_trials_not_passes():
    from cfm_fem.workflows.kinematics import _per_pass

    seen = []
    step = _per_pass(seen.append, 2)  # exact intervals: every trial runs twice
    for n in (300, 300, 250, 150, 1000):  # 2,000 draws of 1,000 trials
        step(n)
    assert sum(seen) == 1000 and all(v > 0 for v in seen)
    one = []
    step = _per_pass(one.append, 1)
    step(7)
    assert one == [7]


def test_log_progress_states_the_time_left_from_the_pace_so_far(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(_progress.time, "monotonic", lambda: clock[0])
    log = io.StringIO()
    monkeypatch.setattr(sys, "stderr", log)
    with _progress.progress_bar(1000, "trials", interval=5.0) as bar:
        clock[0] = 600.0  # 10 of 1000 trials in 10 min: 990 min to go
        bar.update(10)
    first = log.getvalue().splitlines()[0]
    assert first == "cfm-fem: 10 / 1,000 trials (1 %), 600 s, about 16.5 h left"
