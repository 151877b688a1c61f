"""The shipped residual stress does what conf/material/pla_80c.yaml says: a free 50 mm actuator bends ~75 deg."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx")
from hydra import compose, initialize_config_dir  # noqa: E402

from fea_factory.calibrate import actuator_bend, bend_angle_deg  # noqa: E402

CONF = str(Path(__file__).resolve().parent.parent / "conf")


def cfg(overrides=()):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="calibrate", overrides=list(overrides))


def test_bend_angle_of_a_quarter_circle_is_90_degrees():
    class Mesh:  # one beam of 9 x 3 x 3 nodes on a quarter circle of radius 50 curling upward
        beam_nodes = np.arange(81).reshape(1, 9, 3, 3)
    s = np.linspace(0, np.pi / 2, 9)
    xyz = np.zeros((81, 3))
    for k, z in enumerate((-2.0, 0.0, 2.0)):  # sections stay normal to the arc (radius 50 - z)
        r = 50.0 - z
        xyz[Mesh.beam_nodes[0, :, 1, k]] = np.stack([r * np.sin(s), np.zeros(9), 50 - r * np.cos(s)], axis=1)
    assert bend_angle_deg(Mesh, xyz) == pytest.approx(-90.0, abs=1e-9)  # rotation about +y: upward is negative


def test_shipped_sigma_bends_the_calibration_actuator_by_the_documented_angle():
    """Default mesh, tolerance 1 deg: the calibration hit 75.0 deg; a few tenths move with solver tolerances, more means the
    material table, the residual-stress model or sigma changed without recalibrating."""
    c = cfg()
    up, _ = actuator_bend(c, float(c.material.residual_stress.sigma))
    c_down = cfg(["kind=down"])
    down, _ = actuator_bend(c_down, float(c.material.residual_stress.sigma))
    assert abs(up) == pytest.approx(float(c.target_deg), abs=1.0)
    assert up == pytest.approx(-down, rel=1e-3)  # up and down actuators are mirror images
