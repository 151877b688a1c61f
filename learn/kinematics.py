"""Kinematic update: every block moves with the block it hangs from, outward from the fixed joint.

The additive update G(t+1) = G(t) + dG predicts every block's global displacement on its own, so translations that
are really the sum of the rotations along the path to the fixed joint are guessed independently per block and
adjacent blocks drift apart. Here the graph is a tree rooted at the fixed joint(s): every beam hangs from one of its
joints (the one nearer the root), every other joint from the beam that reached it first. A block's geometry is
described in its parent's frame (learn/frames.py; points relative to the parent's origin point):

    rel_x = R_p^T (geometry_x - o_p)            (o_p subtracted from point fields only)

The network predicts d rel_x (a local quantity: how a beam bends relative to the joint it leaves, where a joint sits
at the end of its beam), and the new geometry is rebuilt from the root outward with the parents' new frames:

    geometry_x(t+1) = o_p(t+1) + R_p(t+1) (rel_x(t) + d rel_x)

Beams closing a loop of the grid hang from their nearer joint like the others; their far end is free, so a mismatch
there shows up in the dislocation validity check instead of being hidden.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from learn import frames
from learn.graph import BEAM, JOINT, Block, GraphIndex


@dataclass
class Tree:
    """Parents and placement order of a graph's blocks (a forest when several graphs share one union graph)."""

    beam_parent: torch.Tensor  # [B] joint each beam hangs from
    joint_parent: torch.Tensor  # [J] beam each joint hangs from (-1: a root, i.e. a fixed joint)
    levels: list[tuple[str, torch.Tensor]]  # ("beam" | "joint", indices) placed in this order after the roots


def tree(index: GraphIndex, fixed: np.ndarray) -> Tree:
    """Breadth-first tree from every joint flagged fixed; raises if a joint cannot be reached from one."""
    senders, receivers = (x.cpu().numpy() for x in index.beam_ends())
    J = index.n_joints
    touching: list[list[int]] = [[] for _ in range(J)]
    for b, (a, c) in enumerate(zip(senders, receivers)):
        touching[a].append(b)
        touching[c].append(b)
    depth = np.full(J, -1)
    joint_parent = np.full(J, -1)
    roots = np.flatnonzero(np.asarray(fixed).reshape(-1) > 0.5)
    depth[roots] = 0
    queue = deque(roots.tolist())
    while queue:
        j = queue.popleft()
        for b in touching[j]:
            other = receivers[b] if senders[b] == j else senders[b]
            if depth[other] < 0:
                depth[other], joint_parent[other] = depth[j] + 1, b
                queue.append(other)
    if (depth < 0).any():
        raise ValueError(f"joints {np.flatnonzero(depth < 0)[:10].tolist()} are not connected to a fixed joint: "
                         "a kinematic update needs every block attached to the support")
    beam_parent = np.where(depth[senders] <= depth[receivers], senders, receivers)
    levels = []
    for d in range(int(depth.max()) if J else 0):
        beams = np.flatnonzero(depth[beam_parent] == d)
        joints = np.flatnonzero(depth == d + 1)
        levels += [(BEAM.name, torch.as_tensor(beams)), (JOINT.name, torch.as_tensor(joints))]
    return Tree(torch.as_tensor(beam_parent), torch.as_tensor(joint_parent), levels)


def parent_pose(joint_state, beam_state, t: Tree) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """{block: (parent origins [..., n, 3], parent frames [..., n, 3, 3])} from current states (roots: their own)."""
    Rj, Rb = frames.frame(joint_state, JOINT), frames.frame(beam_state, BEAM)
    oj, ob = joint_state[..., JOINT.origin_slice], beam_state[..., BEAM.origin_slice]
    jp = t.joint_parent.clamp_min(0)
    is_root = (t.joint_parent < 0)[:, None]
    joint_o = torch.where(is_root, oj, ob.index_select(-2, jp))
    joint_R = torch.where(is_root[:, None], Rj, Rb.index_select(-3, jp))
    return {JOINT.name: (joint_o, joint_R),
            BEAM.name: (oj.index_select(-2, t.beam_parent), Rj.index_select(-3, t.beam_parent))}


def _point_mask(block: Block) -> torch.Tensor:
    """[n_fields, 1] 1 for point fields of the geometry (every geometry field is 3 wide)."""
    return torch.tensor([[1.0 if f.kind == "point" else 0.0] for f in block.geometry.fields])


POINTS = {JOINT.name: _point_mask(JOINT), BEAM.name: _point_mask(BEAM)}


def relative_to(geometry: torch.Tensor, origin: torch.Tensor, block: Block) -> torch.Tensor:
    """[..., n, G] geometry with its point fields taken relative to origin [..., n, 3] (vectors unchanged)."""
    fields = geometry.unflatten(-1, (-1, 3)) - POINTS[block.name].to(geometry) * origin[..., None, :]
    return fields.flatten(-2)


def placed_at(rel: torch.Tensor, origin: torch.Tensor, block: Block) -> torch.Tensor:
    """Inverse of relative_to: the point fields moved back by origin [..., n, 3]."""
    fields = rel.unflatten(-1, (-1, 3)) + POINTS[block.name].to(rel) * origin[..., None, :]
    return fields.flatten(-2)


def to_parent(geometry: torch.Tensor, origin: torch.Tensor, R: torch.Tensor, block: Block) -> torch.Tensor:
    """[..., n, G] global geometry -> the same in the parent frames R [..., n, 3, 3] with origins [..., n, 3]."""
    return frames.rotate_vectors(relative_to(geometry, origin, block), R, to_local=True)


def from_parent(rel: torch.Tensor, origin: torch.Tensor, R: torch.Tensor, block: Block) -> torch.Tensor:
    """Inverse of to_parent."""
    return placed_at(frames.rotate_vectors(rel, R, to_local=False), origin, block)


def relative(joint_state, beam_state, t: Tree) -> tuple[torch.Tensor, torch.Tensor]:
    """Geometry of every block in its parent's frame: [..., J, JOINT.geometry.size], [..., B, BEAM.geometry.size]
    (a root joint's in its own frame)."""
    pose = parent_pose(joint_state, beam_state, t)
    return (to_parent(joint_state[..., JOINT.geometry_slice], *pose[JOINT.name], JOINT),
            to_parent(beam_state[..., BEAM.geometry_slice], *pose[BEAM.name], BEAM))


def place(root_geometry: torch.Tensor, joint_rel: torch.Tensor, beam_rel: torch.Tensor,
          t: Tree) -> tuple[torch.Tensor, torch.Tensor]:
    """Global geometry of every block from the roots' geometry [..., J, Gj] (only root rows are read) and every
    block's geometry in its parent's frame, placing the tree level by level outward from the roots."""
    joints = root_geometry
    beams = torch.zeros_like(beam_rel)
    for kind, idx in t.levels:
        if idx.numel() == 0:
            continue
        if kind == BEAM.name:
            parents = joints.index_select(-2, t.beam_parent.index_select(0, idx))  # [..., n, Gj]
            R, o = frames.frame(parents, JOINT), parents[..., JOINT.origin_slice]
            beams = beams.index_copy(-2, idx, from_parent(beam_rel.index_select(-2, idx), o, R, BEAM))
        else:
            parents = beams.index_select(-2, t.joint_parent.index_select(0, idx))
            R, o = frames.frame(parents, BEAM), parents[..., BEAM.origin_slice]
            joints = joints.index_copy(-2, idx, from_parent(joint_rel.index_select(-2, idx), o, R, JOINT))
    return joints, beams
