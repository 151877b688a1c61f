"""scripts/roll_direction.py: a grid shrunk along i over a longer i span is counted as rolled along its longer span;
one shrunk alike both ways is not rolled."""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts"))
from roll_direction import roll_of  # noqa: E402

from data_schema.testing import synthetic_episode  # noqa: E402
from learn.features import extract  # noqa: E402
from learn.roll import lattice_directions  # noqa: E402


def test_a_grid_curled_along_its_longer_span_is_rolled_that_way_and_a_bowl_is_not():
    f = extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=1), name="ep.h5")
    ui, uj = lattice_directions(f)
    assert abs(np.linalg.norm(ui) - 1) < 1e-9 and abs(ui @ uj) < 0.5  # unit, and i and j far from parallel
    flat = f.fea_points[0]
    r = roll_of(f)
    longer = ui if r["span_ratio"] > 1 else uj
    shrunk = flat.copy()
    shrunk[:, :2] -= 0.5 * np.outer(flat[:, :2] @ longer, longer)  # half the extent along the longer span
    rolled = roll_of(replace(f, fea_points=np.stack([flat, shrunk])))
    assert rolled["rolled"] and rolled["along_longer"]
    assert min(rolled["s_i"], rolled["s_j"]) < 0.6
    bowl = roll_of(replace(f, fea_points=np.stack([flat, flat * np.array([0.7, 0.7, 1.0])])))
    assert not bowl["rolled"] and abs(bowl["s_i"] - 0.7) < 1e-6 and abs(bowl["s_j"] - 0.7) < 1e-6
