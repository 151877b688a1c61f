"""Clearance between blocks that share no joint: the model has no contact, so a grid that folds onto itself would
pass through itself unnoticed. This measures how close it comes.

clearance = min over frames and over pairs of blocks sharing no joint (two beams without a common joint, a beam
and a joint it does not end at, two joints) of the smallest distance between their nodes (mm). It is a proxy: nodes
of two faces in contact are about one element size apart at most, so a clearance well below the thickness means
the blocks touch or overlap; a large one proves they do not. Adjacent blocks share interface nodes and are skipped.
Pure numpy/scipy: it reads the key tables of a keyed mesh or an episode.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Clearance:
    mm: float  # smallest node distance between non-adjacent blocks over all frames (inf: no such pair)
    frame: int  # where it occurs
    blocks: tuple[str, str]  # e.g. ("beam 3", "joint 7")

    def as_dict(self) -> dict:
        return {"clearance_mm": round(self.mm, 3) if np.isfinite(self.mm) else None,
                "clearance_frame": self.frame, "clearance_blocks": list(self.blocks)}


def _blocks(joint_nodes: np.ndarray, beam_nodes: np.ndarray) -> list[tuple[str, int, np.ndarray]]:
    return ([("joint", j, np.unique(joint_nodes[j])) for j in range(len(joint_nodes))] +
            [("beam", b, np.unique(beam_nodes[b])) for b in range(len(beam_nodes))])


def non_adjacent_pairs(beams: np.ndarray, n_joints: int) -> list[tuple[int, int]]:
    """Index pairs into _blocks' list (joints first, then beams) of blocks that share no joint."""
    beams = np.asarray(beams).reshape(-1, 2)
    ends = [set(map(int, e)) for e in beams]
    pairs = []
    n = n_joints + len(beams)
    for a in range(n):
        for c in range(a + 1, n):
            if a < n_joints and c < n_joints:
                pairs.append((a, c))
            elif a < n_joints <= c:
                if a not in ends[c - n_joints]:
                    pairs.append((a, c))
            elif not ends[a - n_joints] & ends[c - n_joints]:
                pairs.append((a, c))
    return pairs


def clearance(node_xyz: np.ndarray, joint_nodes: np.ndarray, beam_nodes: np.ndarray, beams: np.ndarray) -> Clearance:
    """node_xyz [F, N, 3] (or [N, 3]) positions; key tables as in fea_factory.mesh.KeyedMesh / data_schema."""
    from scipy.spatial import cKDTree

    xyz = np.asarray(node_xyz, dtype=np.float64)
    xyz = xyz[None] if xyz.ndim == 2 else xyz
    blocks = _blocks(np.asarray(joint_nodes), np.asarray(beam_nodes))
    pairs = non_adjacent_pairs(beams, len(joint_nodes))
    best = Clearance(np.inf, -1, ("", ""))
    for f, x in enumerate(xyz):
        trees = [cKDTree(x[nodes]) for _, _, nodes in blocks]
        for a, c in pairs:
            d = float(trees[c].query(x[blocks[a][2]], k=1)[0].min())
            if d < best.mm:
                best = Clearance(d, f, (f"{blocks[a][0]} {blocks[a][1]}", f"{blocks[c][0]} {blocks[c][1]}"))
    return best
