"""The rebuilt points as a coarse hex mesh (one hexahedron per joint, two per beam), for ParaView and volumes.

Points are indexed as learn.features.rebuild_all_points orders them: every joint's JOINT_POINTS, then every beam's
BEAM_POINTS. Vertices follow the hex8 (gmsh/VTK) order of data_schema: bottom quad counter-clockwise seen from
above in the block's (i, j) axes, then the top quad, so a flat, unmorphed block has a positive volume.
"""
from __future__ import annotations

import numpy as np

from learn.features import BEAM_POINTS, HEX8_REF, JOINT_POINTS
from learn.graph import JOINT_CORNER_IJ, JOINT_CORNERS, SECTION_CORNER_JK, SECTION_CORNERS, SECTIONS

_JOINT_NAMES = [p[0] for p in JOINT_POINTS]
_BEAM_NAMES = [p[0] for p in BEAM_POINTS]
_VERTICES = HEX8_REF.astype(int)  # [8, (i, j, k)] hex8 vertex order, reference coordinates in {0, 1}


def _joint_hex() -> list[int]:
    """Indices into one joint's JOINT_POINTS of its box: vertex (i, j, k) is the corner (i, j) at the bottom
    (k = 0) or top (k = 1) face."""
    corner = {ij: c for c, ij in zip(JOINT_CORNERS, JOINT_CORNER_IJ)}
    return [_JOINT_NAMES.index(f"{corner[(i, j)]}_{('bottom', 'top')[k]}") for i, j, k in _VERTICES]


def _beam_hexes() -> list[list[int]]:
    """Indices into one beam's BEAM_POINTS of its two hexahedra (start-middle, middle-end): vertex (i, j, k) is
    the section corner (j, k) (SECTION_CORNER_JK: j across to the left, k up) of the first (i = 0) or second
    section."""
    corner = {jk: c for c, jk in zip(SECTION_CORNERS, SECTION_CORNER_JK)}
    return [[_BEAM_NAMES.index(f"{(a, b)[i]}_{corner[(j, k)]}") for i, j, k in _VERTICES]
            for a, b in zip(SECTIONS[:-1], SECTIONS[1:])]


def block_hexahedra(n_joints: int, n_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """Hex8 cells [J + 2B, 8] over the rebuilt points and the block index of each cell (joints 0..J-1, then
    beams J..J+B-1, as data_schema numbers blocks)."""
    pj, pb = len(JOINT_POINTS), len(BEAM_POINTS)
    joints = np.arange(n_joints)[:, None] * pj + np.asarray(_joint_hex())[None]
    beams = n_joints * pj + np.arange(n_beams)[:, None, None] * pb + np.asarray(_beam_hexes())[None]
    cells = np.concatenate([joints, beams.reshape(-1, 8)])
    block = np.concatenate([np.arange(n_joints), n_joints + np.repeat(np.arange(n_beams), 2)])
    return cells.astype(np.int64), block.astype(np.int32)


def hex_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed volume of each hex8 cell [..., C] from points [..., P, 3]: the six tetrahedra around the diagonal
    v0-v6 (exact for planar faces; negative when inverted)."""
    v = points[..., cells, :]  # [..., C, 8, 3]
    tets = ((0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6))
    vol = 0.0
    for a, b, c, d in tets:
        vol = vol + np.einsum("...i,...i->...", np.cross(v[..., b, :] - v[..., a, :], v[..., c, :] - v[..., a, :]),
                              v[..., d, :] - v[..., a, :]) / 6.0
    return vol
