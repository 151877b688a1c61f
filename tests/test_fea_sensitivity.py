"""scripts/fea_sensitivity.py: the jitter stays within its disk and keeps the design valid; the shape change is
measured node by node and refuses episodes of different topology."""
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))
from fea_sensitivity import failed, final_shape_change, jittered  # noqa: E402

from fea_factory.design import lattice_design, validate  # noqa: E402
from fea_factory.sample import lattice  # noqa: E402


def test_jitter_moves_every_joint_within_its_disk_and_nothing_else():
    d = lattice_design(lattice(3, 3, 70.0, 70.0), "up", (1, 1))
    moved = jittered(d, 0.1, seed=7)
    step = np.linalg.norm(moved.joint_xy - d.joint_xy, axis=1)
    assert (step > 0).all() and (step <= 0.1 + 1e-12).all()
    assert np.array_equal(np.asarray(moved.beams), np.asarray(d.beams)) and moved.fixed_joint == d.fixed_joint
    validate(moved)
    assert np.array_equal(jittered(d, 0.1, seed=7).joint_xy, moved.joint_xy)  # seeded


def _episode(xyz0, xyz1, keys):
    return SimpleNamespace(node_key=np.asarray(keys), node_xyz=np.stack([xyz0, xyz1]), design_size=100.0)


def test_final_shape_change_is_the_largest_node_distance():
    keys = [[0, 0, 0, 0], [0, 1, 0, 0]]
    a = _episode(np.zeros((2, 3)), np.array([[0.0, 0, 10], [0, 0, 20]]), keys)
    b = _episode(np.array([[0.1, 0, 0], [0, 0, 0]]), np.array([[0.0, 0, 10.5], [0, 0, 20]]), keys)
    c = final_shape_change(a, b)
    assert c["input_change_mm"] == pytest.approx(0.1) and c["output_change_mm"] == pytest.approx(0.5)
    assert c["output_change_rel"] == pytest.approx(0.005) and c["amplification"] == pytest.approx(5.0)
    assert c["fea_motion_rel"] == pytest.approx(0.2)
    with pytest.raises(ValueError, match="node keys"):
        final_shape_change(a, _episode(np.zeros((2, 3)), np.zeros((2, 3)), [[0, 0, 0, 0], [0, 2, 0, 0]]))


def test_a_diverged_perturbation_says_where_it_stopped_and_how_close_the_grid_came_to_itself():
    assert failed({"status": "error"}) == "error"
    cell = failed({"status": "diverged", "last_t": 0.8361, "last_clearance_mm": 12.93, "last_clearance_blocks": [1, 4]})
    assert cell == "diverged at t = 0.836, clearance 12.93 mm (blocks [1, 4])"
