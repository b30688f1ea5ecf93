"""Dipole trajectory (`cfm_fem.models.quality.trajectory`) against the circle of a uniform
field: a hard-edge dipole of length L deflects by asin(L B / B rho), about L B / B rho."""

from __future__ import annotations

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.models.field import FieldMap
from cfm_fem.models.quality.trajectory import rigidity_from_energy, track
from cfm_fem.workflows.quality import run_quality

B0, L = 0.8, 200.0  # T, mm


def hard_edge(points):
    p = np.asarray(points)
    b = np.zeros_like(p)
    b[:, 1] = np.where(np.abs(p[:, 2]) <= L / 2, B0, 0.0)
    return b, np.ones(len(p), dtype=bool)


def test_hard_edge_deflection_and_sagitta():
    rho_tm = 3.0
    # the entry edge lies on a step's end, the exit edge inside a step: O(step) there
    t = track(hard_edge, rho_tm, -L / 2 - 50, L / 2 + 50, step_mm=0.1)
    rho = 1000 * rho_tm / B0  # orbit radius, mm
    theta = np.arcsin(L / rho)
    assert t["deflection_mrad"] == pytest.approx(theta * 1e3, rel=5e-4)
    assert t["deflection_x_mrad"] == pytest.approx(-theta * 1e3, rel=5e-4)  # towards -x
    assert t["deflection_mrad"] == pytest.approx(L * B0 / rho_tm, rel=2e-3)  # small angle
    # exit offset: arc inside, straight line after
    x_exit = -(rho * (1 - np.cos(theta)) + 50 * np.tan(theta))
    assert t["exit_mm"][0] == pytest.approx(x_exit, rel=1e-3)
    assert t["sagitta_mm"] > 0


def test_rigidity_from_energy():
    # p c = sqrt(T (T + 2 m c^2)); B rho = p / e: 3 GeV electrons 10.0086 T m, 100 MeV protons
    # 1.4830 T m
    assert rigidity_from_energy(3.0, "electron") == pytest.approx(10.0086, rel=1e-5)
    assert rigidity_from_energy(0.1, "proton") == pytest.approx(1.4830, rel=1e-4)
    with pytest.raises(CfmInputError, match="particle"):
        rigidity_from_energy(1.0, "muon")


def test_quality_tracks_a_dipole_map():
    g = np.arange(-6.0, 6.01, 1.0)
    x, y, z = np.meshgrid(g, g, np.linspace(-L / 2, L / 2, 21), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    B = np.zeros_like(pts)
    B[:, 1] = B0
    fm = FieldMap.from_arrays(pts, B, source="dipole")
    res = run_quality(fm, 5.0, uncertainty=False, rigidity_Tm=5.0, field_model="linear",
                      trajectory_step_mm=2.0)  # fmt: skip
    t = res.summary["trajectory"]
    assert res.main_order == 1
    assert t["deflection_mrad"] == pytest.approx(np.arcsin(L * B0 / 5000.0) * 1e3, rel=1e-6)
    assert t["straight_line_deflection_mrad"] == pytest.approx(L * B0 / 5.0, rel=1e-9)
    assert t["U95_deflection_mrad"] is None  # no Monte Carlo asked
    with pytest.raises(CfmInputError, match="leaves the field map"):
        run_quality(fm, 5.0, uncertainty=False, rigidity_Tm=0.5, field_model="linear",
                    trajectory_step_mm=2.0)  # fmt: skip
