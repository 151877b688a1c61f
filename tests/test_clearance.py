"""Clearance between blocks sharing no joint (fea_factory/clearance.py): the self-contact proxy."""
import numpy as np

from data_schema.testing import synthetic_episode
from fea_factory.clearance import clearance, non_adjacent_pairs


def test_non_adjacent_pairs_skip_blocks_that_share_a_joint():
    # path 0 - 1 - 2 with beams b0 = (0, 1), b1 = (1, 2); blocks: joints 0..2, then beams 3, 4
    pairs = non_adjacent_pairs(np.array([[0, 1], [1, 2]]), 3)
    assert sorted(pairs) == [(0, 1), (0, 2), (0, 4), (1, 2), (2, 3)]


def test_clearance_of_a_flat_grid_is_a_beam_length_and_drops_when_a_block_is_moved_onto_another():
    ep = synthetic_episode(3, 3, 5, 3, 3, 5, seed=0)
    flat = clearance(ep.node_xyz0, ep.joint_nodes, ep.beam_nodes, ep.beams)
    assert flat.mm > 5.0 and flat.frame == 0
    # fold: move the nodes only joint 8 owns onto joint 0's centre in a second frame
    moved = ep.node_xyz0.copy()
    own = np.setdiff1d(np.unique(ep.joint_nodes[8]), np.unique(ep.beam_nodes))
    target = ep.node_xyz0[np.unique(ep.joint_nodes[0])].mean(axis=0)
    moved[own] += target - moved[own].mean(axis=0)
    c = clearance(np.stack([ep.node_xyz0, moved]), ep.joint_nodes, ep.beam_nodes, ep.beams)
    assert c.frame == 1 and c.mm < 3.0 < flat.mm and set(c.blocks) == {"joint 0", "joint 8"}
    assert c.as_dict()["clearance_blocks"] == list(c.blocks)
