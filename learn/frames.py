"""Block-attached frames: each block's own axes from its current geometry, and terms rotated into and out of them.

A frame R [..., 3, 3] holds the block's axes as columns (e1 along, e2 across to the left, e3 up), so R^T v expresses
a global vector v in the block's frame. Joint: e1 from its W side to its E side, e3 along its extrusion. Beam: e1
from the start to the end cross-section centre, e3 along the middle cross-section's height vector.
"""
from __future__ import annotations

import torch

from learn.graph import BEAM, JOINT, Block, GraphIndex

_TENSOR_ROWS, _TENSOR_COLS = torch.tensor([0, 1, 2, 0, 0, 1]), torch.tensor([0, 1, 2, 1, 2, 2])  # Voigt xx yy zz xy xz yz


def _voigt_pairs() -> torch.Tensor:
    """[81, 36]: (R_ac R_bd over a, b, c, d) @ it = stress_rotation(R) flattened; row (a, b) of Q picks R_ac R_bd,
    plus R_ad R_bc where c != d (one matrix product instead of a dozen gathers per call)."""
    P = torch.zeros(3, 3, 3, 3, 6, 6)
    for i, (a, b) in enumerate(zip(_TENSOR_ROWS.tolist(), _TENSOR_COLS.tolist())):
        for j, (c, d) in enumerate(zip(_TENSOR_ROWS.tolist(), _TENSOR_COLS.tolist())):
            P[a, b, c, d, i, j] += 1.0
            if c != d:
                P[a, b, d, c, i, j] += 1.0
    return P.reshape(81, 36)


_VOIGT_PAIRS = _voigt_pairs()


def orthonormal(along: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """[..., 3] x 2 -> [..., 3, 3]: e1 = along, e3 = up made orthogonal to e1, e2 = e3 x e1."""
    e1 = along / along.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    e3 = up - (up * e1).sum(-1, keepdim=True) * e1
    e3 = e3 / e3.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.stack([e1, torch.linalg.cross(e3, e1), e3], dim=-1)


def frame(state: torch.Tensor, block: Block) -> torch.Tensor:
    """[..., n, S] states -> [..., n, 3, 3] block frames."""
    g = block.geometry
    if block is JOINT:
        return orthonormal(joint_axis(state), state[..., g.slice("extrusion")])
    along = state[..., g.slice("end_center")] - state[..., g.slice("start_center")]
    return orthonormal(along, state[..., g.slice("middle_height")])


def joint_axis(state: torch.Tensor) -> torch.Tensor:
    """[..., n, S] joint states -> [..., n, 3] each joint's W -> E axis (the mean of its two S and N edges)."""
    g = JOINT.geometry
    return (state[..., g.slice("corner_se")] - state[..., g.slice("corner_sw")]
            + state[..., g.slice("corner_ne")] - state[..., g.slice("corner_nw")])


def design_frame(joint_state: torch.Tensor, fixed: torch.Tensor,
                 index: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame per design, given to every joint [..., J, 3, 3] and beam [..., B, 3, 3]: e3 = +z, e1 = the fixed
    joint's W -> E axis projected on the xy plane (fixed: [..., J, 1] flags; several fixed joints: their mean axis).
    The fixed joint is glued to the support, so the frame turns with the design about z and with nothing else:
    inputs expressed in it are invariant to rotations of the design about z (gravity is along z), exactly."""
    axis = joint_axis(joint_state) * fixed
    if index.joint_graph is None:
        axis = axis.sum(-2, keepdim=True)  # [..., 1, 3]
    else:
        axis = axis.new_zeros(*axis.shape[:-2], index.n_graphs, 3).index_add_(-2, index.joint_graph, axis)
    c, s = axis[..., 0], axis[..., 1]
    norm = torch.sqrt(c * c + s * s).clamp_min(1e-9)
    c, s = c / norm, s / norm
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    R = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                     torch.stack([zero, zero, one], -1)], -2)  # [..., G, 3, 3], columns e1, e2, e3
    if index.joint_graph is None:
        return (R.expand(*R.shape[:-3], index.n_joints, 3, 3), R.expand(*R.shape[:-3], index.n_beams, 3, 3))
    return R.index_select(-3, index.joint_graph), R.index_select(-3, index.beam_graph)


def rotate_vectors(x: torch.Tensor, R: torch.Tensor, to_local: bool) -> torch.Tensor:
    """[..., n, 3k] stacked 3-vectors, R [..., n, 3, 3] -> R^T v (to_local) or R v."""
    v = x.unflatten(-1, (-1, 3))  # [..., n, k, 3]: rows, so R^T v is v @ R and R v is v @ R^T
    return blocks_times(v, R if to_local else R.transpose(-1, -2)).flatten(-2)


def blocks_times(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a [..., p, q] @ b [..., q, r] per block; when both have the same leading axes, as one bmm over them (a few
    operations, not the dozen of a broadcasting matmul: the rollout's cost is the count of small operations)."""
    if a.shape[:-2] != b.shape[:-2]:
        return a @ b
    return torch.bmm(a.reshape(-1, *a.shape[-2:]), b.reshape(-1, *b.shape[-2:])).view(*a.shape[:-1], b.shape[-1])


def stress_rotation(R: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotations -> [..., 6, 6] Q with Voigt(R s R^T) = Q Voigt(s): row (a, b), column (c, d) holds
    R_ac R_bd + R_ad R_bc (the second term only for c != d, whose entry stands for both s_cd and s_dc)."""
    pairs = (R.unsqueeze(-1).unsqueeze(-3) * R.unsqueeze(-2).unsqueeze(-4)).flatten(-4)  # [..., 81]: R_ac R_bd
    return (pairs @ _VOIGT_PAIRS.to(R.dtype)).unflatten(-1, (6, 6))


def rotate_stresses(x: torch.Tensor, R: torch.Tensor, to_local: bool) -> torch.Tensor:
    """[..., n, 6k] stacked Voigt stresses -> R^T s R (to_local) or R s R^T."""
    Q = stress_rotation(R.transpose(-1, -2) if to_local else R)  # [..., n, 6, 6]
    return blocks_times(x.unflatten(-1, (-1, 6)), Q.transpose(-1, -2)).flatten(-2)


def rotate_state(x: torch.Tensor, block: Block, R: torch.Tensor, to_local: bool) -> torch.Tensor:
    """A state or state update [..., n, S] (geometry fields all 3-vectors, then stresses) into or out of frames R."""
    return torch.cat([rotate_vectors(x[..., block.geometry_slice], R, to_local),
                      rotate_stresses(x[..., block.stress_slice], R, to_local)], dim=-1)


def gravity(R: torch.Tensor) -> torch.Tensor:
    """[..., n, 3] the unit downward vector -z in each block's frame (R^T (0, 0, -1))."""
    return -R[..., 2, :]


def relative_rotation(R_from: torch.Tensor, R_to: torch.Tensor) -> torch.Tensor:
    """[..., 6] the first two columns of R_from^T R_to (the third follows from them)."""
    return blocks_times(R_from.transpose(-1, -2), R_to)[..., :2].flatten(-2)


