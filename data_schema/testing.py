"""Synthetic episodes for tests: a tiny, geometrically consistent grid built without fea_factory or a solver."""
from __future__ import annotations

import json
import sys

import h5py
import numpy as np

from data_schema.checks import corner_nodes
from data_schema.episode import Episode
from data_schema.fields import BEAM_KINDS, FIELDS, SCHEMA_VERSION

PRESTRESS = 0.05  # MPa, magnitude of the synthetic residual stress along each print direction


def _lattice(nx: int, ny: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joints of an axis-aligned nx x ny grid with random column/row spacing, numbered j-major (n = j nx + i);
    beams first along i row by row, then along j (the order of fea_factory.design.lattice_design)."""
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(30.0, 50.0, nx - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(30.0, 50.0, ny - 1))])
    ij = np.array([(i, j) for j in range(ny) for i in range(nx)])
    xy = np.stack([xs[ij[:, 0]], ys[ij[:, 1]]], axis=1)
    beams = [(j * nx + i, j * nx + i + 1) for j in range(ny) for i in range(nx - 1)]
    beams += [(j * nx + i, (j + 1) * nx + i) for j in range(ny - 1) for i in range(nx)]
    return ij, xy, np.array(beams, dtype=np.int64)


def _bend(xyz0: np.ndarray, centre: np.ndarray, half: float, thickness: float, t: float,
          curvature: float, sag: float) -> np.ndarray:
    """Smooth morph at pseudo-time t: the grid rolls up along x about the fixed joint (a circular arc of
    curvature t * curvature outside the joint's footprint) and sags quadratically along y.
    The fixed joint block stays exactly in place."""
    x, y, z = xyz0.T
    dx, dy = x - centre[0], y - centre[1]
    s = np.sign(dx) * np.maximum(np.abs(dx) - half, 0.0)  # arc length from the fixed joint's side
    r = np.sign(dy) * np.maximum(np.abs(dy) - half, 0.0)
    k = t * curvature
    zeta = z - 0.5 * thickness  # distance above the mid-surface
    ks = k * s
    sin_k = s * np.sinc(ks / np.pi)  # sin(k s) / k, exact at k = 0
    one_minus_cos_k = s * np.sin(ks / 2) * np.sinc(ks / (2 * np.pi))  # (1 - cos(k s)) / k
    out = np.empty_like(xyz0)
    out[:, 0] = centre[0] + (dx - s) + sin_k - zeta * np.sin(ks)
    out[:, 1] = y
    out[:, 2] = 0.5 * thickness + one_minus_cos_k + zeta * np.cos(ks) - t * sag * r ** 2
    return out


def synthetic_episode(nx: int = 2, ny: int = 2, nl: int = 5, nw: int = 3, nh: int = 3, frames: int = 3,
                      seed: int = 0) -> Episode:
    """A valid nx x ny grid episode: joint blocks beam_width square, beams between them, hex8 cells with keys in
    lexicographic order, beam end faces aliasing the joints' side nodes, frames of a smooth bending morph and a
    finite stress field relaxing from the residual prestress. Deterministic in `seed`."""
    rng = np.random.default_rng(seed)
    width, thickness = 7.2, 4.0
    half = width / 2
    ij, xy, beams = _lattice(nx, ny, rng)
    J, B = len(xy), len(beams)
    kinds = rng.integers(0, len(BEAM_KINDS), B).astype(np.int8)
    fixed = int(rng.integers(0, J))
    across = np.linspace(-half, half, nw)
    up = np.linspace(0.0, thickness, nh)

    # ---- nodes in key order: joints (block n), then the interior nodes of beams (block J + b)
    joint_xyz = np.zeros((J, nw, nw, nh, 3))
    joint_xyz[..., 0] = xy[:, 0, None, None, None] + across[None, :, None, None]
    joint_xyz[..., 1] = xy[:, 1, None, None, None] + across[None, None, :, None]
    joint_xyz[..., 2] = up[None, None, None, :]
    axis = xy[beams[:, 1]] - xy[beams[:, 0]]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    left = np.stack([-axis[:, 1], axis[:, 0]], axis=1)
    start, end = xy[beams[:, 0]] + half * axis, xy[beams[:, 1]] - half * axis
    along = np.linspace(0.0, 1.0, nl)
    beam_xyz = np.zeros((B, nl, nw, nh, 3))
    beam_xyz[..., :2] = (start[:, None, None, None] + (end - start)[:, None, None, None] * along[None, :, None, None, None]
                         + left[:, None, None, None] * across[None, None, :, None, None])
    beam_xyz[..., 2] = up
    joint_nodes = np.arange(J * nw * nw * nh).reshape(J, nw, nw, nh)
    n_joint_nodes = joint_nodes.size
    beam_nodes = np.zeros((B, nl, nw, nh), dtype=np.int64)
    beam_nodes[:, 1:-1] = n_joint_nodes + np.arange(B * (nl - 2) * nw * nh).reshape(B, nl - 2, nw, nh)
    for b in range(B):  # end faces alias the nodes of the joint side they touch
        for face, joint in ((0, beams[b, 0]), (-1, beams[b, 1])):
            side = joint_xyz[joint].reshape(-1, 3)
            dist = np.linalg.norm(beam_xyz[b, face][:, :, None] - side, axis=-1)  # [nw, nh, nw*nw*nh]
            assert dist.min(axis=-1).max() < 1e-9, "beam face does not meet its joint"
            beam_nodes[b, face] = joint_nodes[joint].ravel()[dist.argmin(axis=-1)]
    node_xyz0 = np.concatenate([joint_xyz.reshape(-1, 3), beam_xyz[:, 1:-1].reshape(-1, 3)])
    jk = np.indices((J, nw, nw, nh)).reshape(4, -1).T
    bk = np.indices((B, nl - 2, nw, nh)).reshape(4, -1).T + [J, 1, 0, 0]
    node_key = np.concatenate([jk, bk]).astype(np.int32)

    # ---- cells in key order, hex8 from the block tables
    joint_cells = np.arange(J * (nw - 1) ** 2 * (nh - 1)).reshape(J, nw - 1, nw - 1, nh - 1)
    beam_cells = joint_cells.size + np.arange(B * (nl - 1) * (nw - 1) * (nh - 1)).reshape(B, nl - 1, nw - 1, nh - 1)
    cell_key = np.concatenate([np.indices(joint_cells.shape).reshape(4, -1).T,
                               np.indices(beam_cells.shape).reshape(4, -1).T + [J, 0, 0, 0]]).astype(np.int32)

    cell_nodes = np.concatenate([corner_nodes(joint_nodes).reshape(-1, 8), corner_nodes(beam_nodes).reshape(-1, 8)])
    cell_layer = (cell_key[:, 3] >= (nh - 1) // 2).astype(np.int8)
    # print directions: joints alternate 0 / 90 deg; "up" beams print the top layer along the axis, "down"
    # beams the bottom layer, "passive" beams print both layers across it
    axis_deg = np.degrees(np.arctan2(axis[:, 1], axis[:, 0]))
    along_layer = np.array([1, 0, -1])[kinds]  # layer printed along the axis (-1: none)
    is_joint = cell_key[:, 0] < J
    b_of = np.where(is_joint, 0, cell_key[:, 0] - J)
    beam_angle = axis_deg[b_of] + np.where(cell_layer == along_layer[b_of], 0.0, 90.0)
    cell_print_angle = np.where(is_joint, 90.0 * cell_layer, beam_angle) % 180.0

    # ---- frames
    t = np.linspace(0.0, 1.0, frames)
    curvature = rng.choice([-1, 1]) * rng.uniform(0.01, 0.02)  # 1/mm at t = 1
    sag = rng.uniform(0.002, 0.004)  # 1/mm at t = 1
    node_xyz = np.stack([_bend(node_xyz0, xy[fixed], half, thickness, ti, curvature, sag) for ti in t])
    g = 0.5 + 0.5 / np.sqrt(3.0)
    quad_points = np.array([[a, b, c] for c in (1 - g, g) for b in (1 - g, g) for a in (1 - g, g)])
    quad_weights = np.full(8, 1 / 8)
    alpha = np.radians(cell_print_angle)
    prestress = np.zeros((len(cell_key), 6))
    prestress[:, 0], prestress[:, 1] = PRESTRESS * np.cos(alpha) ** 2, PRESTRESS * np.sin(alpha) ** 2
    prestress[:, 3] = PRESTRESS * np.sin(alpha) * np.cos(alpha)
    through = 1.0 + 0.2 * (quad_points[:, 2] - 0.5)  # a gradient through each cell's height
    bending = np.zeros(6)
    bending[0] = 0.01 * np.sign(curvature)
    stress = ((1 - t)[:, None, None, None] * prestress[None, :, None, :] * through[None, None, :, None]
              + t[:, None, None, None] * bending * (2 * quad_points[None, None, :, 2, None] - 1))

    n_inc = 2 * max(frames - 1, 1)
    increment_t = np.arange(1, n_inc + 1) / n_inc
    newton = rng.integers(2, 6, n_inc).astype(np.int32)
    design = {
        "format": "morphsim.design/1",
        "joints": [{"ij": p.tolist(), "xy": q.tolist()} for p, q in zip(ij, xy)],
        "beams": [[int(a), int(c), BEAM_KINDS[k]] for (a, c), k in zip(beams, kinds)],
        "fixed_joint": fixed, "beam_width": width, "thickness": thickness,
        "meta": {"generator": "data_schema.testing.synthetic_episode", "seed": seed},
    }
    stats = {"increments": n_inc, "newton_iterations": int(newton.sum()), "cutbacks": 0,
             "wall_s": {"mesh": 0.0, "jit": 0.0, "solve": 0.0, "total": 0.0}}
    return Episode(
        joint_ij=ij.astype(np.int64), joint_xy=xy, beams=beams, beam_kind=kinds, fixed_joint=fixed,
        beam_width=width, thickness=thickness, family="synthetic", design_json=json.dumps(design),
        node_key=node_key, node_xyz0=node_xyz0, cell_key=cell_key, cell_nodes=cell_nodes, cell_layer=cell_layer,
        cell_print_angle=cell_print_angle.astype(np.float32), joint_nodes=joint_nodes, beam_nodes=beam_nodes,
        joint_cells=joint_cells, beam_cells=beam_cells, nodes_length=nl, nodes_width=nw, nodes_height=nh,
        preset="synthetic",
        t=t, node_xyz=node_xyz.astype(np.float32), stress=stress.astype(np.float32),
        quad_points=quad_points, quad_weights=quad_weights,
        config_yaml=f"synthetic:\n  nx: {nx}\n  ny: {ny}\n  seed: {seed}\n", seed=seed, git_rev="synthetic",
        versions_json=json.dumps({"numpy": np.__version__, "h5py": h5py.__version__,
                                  "python": sys.version.split()[0], "schema": SCHEMA_VERSION}),
        mpi_size=1, solver_stats_json=json.dumps(stats),
        scene_terms_json=json.dumps({"prestress": True, "body_force": True, "fixed_face": True}),
        increment_t=increment_t, newton_iterations=newton,
    )


def assert_episodes_equal(a: Episode, b: Episode) -> None:
    """AssertionError naming the first field where two episodes differ in value, dtype or type."""
    for f in FIELDS:
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.is_attr:
            assert type(x) is type(y) and x == y, f"{f.name}: {x!r} != {y!r}"
        else:
            assert x.dtype == y.dtype, f"{f.name}: dtype {x.dtype} != {y.dtype}"
            np.testing.assert_array_equal(x, y, err_msg=f.name)
