"""Keyed structured hexahedral meshes of grid designs, handed to gmsh for export and dolfinx.

Each joint and each beam is one block of structured hexahedra built by transfinite (bilinear in the
print plane, linear through the thickness) interpolation of the block corners from `geometry` — the
same construction gmsh's transfinite meshing performs — so that every node and cell carries its tuple
key (block, i, j, k) exactly, by construction, with no geometric search. Blocks 0..J-1 are joints,
J..J+B-1 beams. A node on a joint/beam interface belongs to the joint (its key is the joint's); the
beam's block table `beam_nodes` points at that same node, so blocks conform without duplicate nodes.
Nodes and cells are numbered in key order; gmsh tags are ids + 1.

CLI: python -m fea_factory.mesh design=FILE out=DIR [mesh=coarse|default|fine]
Units: mm, degrees.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fea_factory.design import Design, DesignError
from fea_factory.geometry import CORNER_UNIT_IJ, block_geometry, joint_quad

log = logging.getLogger(__name__)

LAYER_BOTTOM, LAYER_TOP = 0, 1
GMSH_HEX8 = 5  # gmsh element type of the 8-node hexahedron


@dataclass(frozen=True)
class MeshPreset:
    """Node counts per block (conf/mesh/*.yaml); all odd so mid-planes carry nodes."""

    nodes_length: int = 9
    nodes_width: int = 3
    nodes_height: int = 3
    name: str = "default"

    def __post_init__(self) -> None:
        for f in ("nodes_length", "nodes_width", "nodes_height"):
            n = getattr(self, f)
            if int(n) != n or n < 3 or n % 2 == 0:
                raise DesignError(f"mesh.{f} = {n}: must be an odd integer >= 3 (a node plane at the middle)")

    @classmethod
    def from_mapping(cls, m) -> "MeshPreset":
        return cls(int(m["nodes_length"]), int(m["nodes_width"]), int(m["nodes_height"]), str(m.get("name", "custom")))

    def counts(self, n_joints: int, n_beams: int) -> tuple[int, int]:
        """(nodes, cells) of a design: joints own their nodes, beams their interior length planes."""
        nl, nw, nh = self.nodes_length, self.nodes_width, self.nodes_height
        nodes = n_joints * nw * nw * nh + n_beams * (nl - 2) * nw * nh
        cells = (n_joints * (nw - 1) ** 2 + n_beams * (nl - 1) * (nw - 1)) * (nh - 1)
        return nodes, cells


@dataclass
class KeyedMesh:
    """A conforming hex8 mesh of a design with tuple keys for every node and cell (ids in key order).

    node_key [N, 4] int32, node_xyz [N, 3] float64 mm, cell_key [C, 4] int32, cell_nodes [C, 8] int64
    (gmsh/VTK hex8 order: bottom quad counter-clockwise, then top), cell_layer [C] int8,
    cell_print_angle [C] float64 deg (counter-clockwise from +x, modulo 180),
    joint_nodes [J, nw, nw, nh], beam_nodes [B, nl, nw, nh], joint_cells [J, nw-1, nw-1, nh-1],
    beam_cells [B, nl-1, nw-1, nh-1] (int64 ids).
    """

    preset: MeshPreset
    node_key: np.ndarray
    node_xyz: np.ndarray
    cell_key: np.ndarray
    cell_nodes: np.ndarray
    cell_layer: np.ndarray
    cell_print_angle: np.ndarray
    joint_nodes: np.ndarray
    beam_nodes: np.ndarray
    joint_cells: np.ndarray
    beam_cells: np.ndarray

    @property
    def n_nodes(self) -> int:
        return len(self.node_xyz)

    @property
    def n_cells(self) -> int:
        return len(self.cell_nodes)

    @property
    def cell_block(self) -> np.ndarray:
        return self.cell_key[:, 0]


def _bilinear(q: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points of the bilinear patch over quad q = [p(0,0), p(1,0), p(1,1), p(0,1)] at (u, v) grids."""
    u, v = u[..., None], v[..., None]
    return (1 - u) * (1 - v) * q[0] + u * (1 - v) * q[1] + u * v * q[2] + (1 - u) * v * q[3]


def _side_indices(arm: int, nw: int, from_right: bool) -> np.ndarray:
    """Joint (i, j) index pairs [nw, 2] along the joint side facing `arm`, from its right or left corner."""
    right = CORNER_UNIT_IJ[(arm - 1) % 4] * (nw - 1)
    left = CORNER_UNIT_IJ[arm] * (nw - 1)
    a, b = (right, left) if from_right else (left, right)
    s = np.arange(nw)[:, None]
    return a + (b - a) * s // (nw - 1)


def print_direction_angle(axis_deg: float, along: bool) -> float:
    """Print angle (deg, modulo 180) of a layer printed along or across an axis."""
    return float((axis_deg + (0.0 if along else 90.0)) % 180.0)


def _beam_layer_angles(kind: str, axis_deg: float) -> tuple[float, float]:
    """(bottom, top) print angles: the active layer prints along the beam axis, the other across it."""
    along = {"down": (True, False), "up": (False, True), "passive": (False, False)}[kind]
    return print_direction_angle(axis_deg, along[0]), print_direction_angle(axis_deg, along[1])


def build_keyed_mesh(design: Design, preset: MeshPreset) -> KeyedMesh:
    nl, nw, nh = preset.nodes_length, preset.nodes_width, preset.nodes_height
    J, B = design.n_joints, design.n_beams
    g = block_geometry(design)
    z = np.linspace(0.0, design.thickness, nh)
    layer_of_k = np.where(np.arange(nh - 1) < (nh - 1) // 2, LAYER_BOTTOM, LAYER_TOP).astype(np.int8)

    joint_nodes = np.arange(J * nw * nw * nh, dtype=np.int64).reshape(J, nw, nw, nh)
    n_joint_nodes = joint_nodes.size
    beam_nodes = np.empty((B, nl, nw, nh), dtype=np.int64)
    interior = np.arange(B * (nl - 2) * nw * nh, dtype=np.int64).reshape(B, nl - 2, nw, nh) + n_joint_nodes
    beam_nodes[:, 1:-1] = interior
    for b, (a, c) in enumerate(design.beams.tolist()):
        ka, kc = g.beam_arm[b]
        sa = _side_indices(ka, nw, from_right=True)  # beam j = 0 is right of the a -> b axis
        sc = _side_indices(kc, nw, from_right=False)  # ... which is the left of the c -> a direction
        beam_nodes[b, 0] = joint_nodes[a, sa[:, 0], sa[:, 1]]
        beam_nodes[b, -1] = joint_nodes[c, sc[:, 0], sc[:, 1]]

    N = n_joint_nodes + interior.size
    node_xyz = np.zeros((N, 3))
    node_key = np.zeros((N, 4), dtype=np.int32)
    ui, vj, kk = np.meshgrid(np.arange(nw), np.arange(nw), np.arange(nh), indexing="ij")
    for n in range(J):
        ids = joint_nodes[n]
        xy = _bilinear(joint_quad(g.joint_corners[n]), ui / (nw - 1), vj / (nw - 1))
        node_xyz[ids, :2], node_xyz[ids, 2] = xy, z[kk]
        node_key[ids] = np.stack([np.full_like(ui, n), ui, vj, kk], axis=-1)
    ui, vj, kk = np.meshgrid(np.arange(1, nl - 1), np.arange(nw), np.arange(nh), indexing="ij")
    for b in range(B):
        ids = beam_nodes[b, 1:-1]
        c = g.beam_corners[b]  # start-right, start-left, end-right, end-left
        xy = _bilinear(c[[0, 2, 3, 1]], ui / (nl - 1), vj / (nw - 1))
        node_xyz[ids, :2], node_xyz[ids, 2] = xy, z[kk]
        node_key[ids] = np.stack([np.full_like(ui, J + b), ui, vj, kk], axis=-1)

    def hex_cells(block_nodes: np.ndarray) -> np.ndarray:  # [ni, nj, nk] node ids -> [ni-1, nj-1, nk-1, 8]
        p = block_nodes
        return np.stack([p[:-1, :-1, :-1], p[1:, :-1, :-1], p[1:, 1:, :-1], p[:-1, 1:, :-1],
                         p[:-1, :-1, 1:], p[1:, :-1, 1:], p[1:, 1:, 1:], p[:-1, 1:, 1:]], axis=-1)

    cells, keys, layers, angles = [], [], [], []
    ci, cj, ck = np.meshgrid(np.arange(nw - 1), np.arange(nw - 1), np.arange(nh - 1), indexing="ij")
    for n in range(J):
        east = np.degrees(np.arctan2(*g.joint_arms[n, 0][::-1]))
        cells.append(hex_cells(joint_nodes[n]).reshape(-1, 8))
        keys.append(np.stack([np.full_like(ci, n), ci, cj, ck], axis=-1).reshape(-1, 4))
        layers.append(layer_of_k[ck].reshape(-1))
        # joints print alternating layers (odd and even layers perpendicular)
        angles.append(np.array([print_direction_angle(east, k % 2 == 0) for k in ck.reshape(-1)]))
    ci, cj, ck = np.meshgrid(np.arange(nl - 1), np.arange(nw - 1), np.arange(nh - 1), indexing="ij")
    for b, (a, c) in enumerate(design.beams.tolist()):
        axis = design.joint_xy[c] - design.joint_xy[a]
        bottom, top = _beam_layer_angles(design.kinds[b], float(np.degrees(np.arctan2(axis[1], axis[0]))))
        cells.append(hex_cells(beam_nodes[b]).reshape(-1, 8))
        keys.append(np.stack([np.full_like(ci, J + b), ci, cj, ck], axis=-1).reshape(-1, 4))
        lay = layer_of_k[ck].reshape(-1)
        layers.append(lay)
        angles.append(np.where(lay == LAYER_BOTTOM, bottom, top))
    n_jc = J * (nw - 1) ** 2 * (nh - 1)
    cell_ids = np.arange(n_jc + B * (nl - 1) * (nw - 1) * (nh - 1), dtype=np.int64)
    return KeyedMesh(
        preset=preset,
        node_key=node_key,
        node_xyz=node_xyz,
        cell_key=np.concatenate(keys).astype(np.int32),
        cell_nodes=np.concatenate(cells).astype(np.int64),
        cell_layer=np.concatenate(layers).astype(np.int8),
        cell_print_angle=np.concatenate(angles).astype(np.float64),
        joint_nodes=joint_nodes,
        beam_nodes=beam_nodes,
        joint_cells=cell_ids[:n_jc].reshape(J, nw - 1, nw - 1, nh - 1),
        beam_cells=cell_ids[n_jc:].reshape(B, nl - 1, nw - 1, nh - 1),
    )


# ------------------------------------------------------------------------------------------ quality
_HEX_CORNER_EDGES = np.array([  # for each hex8 corner: its three neighbours along local +i, +j, +k order
    [1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]])


def scaled_jacobian(xyz: np.ndarray, cell_nodes: np.ndarray) -> np.ndarray:
    """Minimum over the 8 corners of det[e1, e2, e3] / (|e1||e2||e3|) per cell [C]; 1 = perfect brick."""
    p = xyz[cell_nodes]  # [C, 8, 3]
    e = p[:, _HEX_CORNER_EDGES, :] - p[:, :, None, :]  # [C, 8, 3, 3]
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    return np.linalg.det(e).min(axis=1)


# ------------------------------------------------------------------------------------------ gmsh
def add_to_gmsh(mesh: KeyedMesh, name: str = "design") -> None:
    """Load the mesh into the current gmsh model as discrete volumes, one per block (physical tag block+1).

    Node tags are node ids + 1 and element tags cell ids + 1, so dolfinx's
    `geometry.input_global_indices` (gmsh tag - 1) are our node ids.
    """
    import gmsh

    gmsh.model.add(name)
    vol = gmsh.model.addDiscreteEntity(3)
    gmsh.model.mesh.addNodes(3, vol, np.arange(1, mesh.n_nodes + 1), mesh.node_xyz.reshape(-1))
    blocks = mesh.cell_block
    for blk in np.unique(blocks):
        sel = np.where(blocks == blk)[0]
        tag = vol if blk == blocks[0] else gmsh.model.addDiscreteEntity(3)
        gmsh.model.mesh.addElementsByType(tag, GMSH_HEX8, sel + 1, (mesh.cell_nodes[sel] + 1).reshape(-1))
        gmsh.model.addPhysicalGroup(3, [tag], int(blk) + 1)


def write_mesh(mesh: KeyedMesh, design: Design, out: Path) -> dict[str, Path]:
    """Write mesh.xdmf (+ mesh.h5: cell tags block/layer/print angle, node keys; ParaView opens it),
    mesh.msh (gmsh) and keys.h5 (the key tables); each written to a temporary name, then renamed."""
    import gmsh
    import h5py
    import meshio

    out.mkdir(parents=True, exist_ok=True)
    tmp = out / ".tmp_mesh"
    tmp.mkdir(exist_ok=True)
    vtk_mesh = meshio.Mesh(
        mesh.node_xyz, [("hexahedron", mesh.cell_nodes)],
        point_data={"node_block": mesh.node_key[:, 0], "node_i": mesh.node_key[:, 1],
                    "node_j": mesh.node_key[:, 2], "node_k": mesh.node_key[:, 3]},
        cell_data={"block": [mesh.cell_key[:, 0]], "layer": [mesh.cell_layer.astype(np.int32)],
                   "print_angle": [mesh.cell_print_angle], "cell_i": [mesh.cell_key[:, 1]],
                   "cell_j": [mesh.cell_key[:, 2]], "cell_k": [mesh.cell_key[:, 3]]},
    )
    meshio.write(tmp / "mesh.xdmf", vtk_mesh)
    with h5py.File(tmp / "keys.h5", "w") as f:
        for field in ("node_key", "node_xyz", "cell_key", "cell_nodes", "cell_layer", "cell_print_angle",
                      "joint_nodes", "beam_nodes", "joint_cells", "beam_cells"):
            f.create_dataset(field, data=getattr(mesh, field), compression="gzip")
        f.attrs.update(nodes_length=mesh.preset.nodes_length, nodes_width=mesh.preset.nodes_width,
                       nodes_height=mesh.preset.nodes_height, preset=mesh.preset.name,
                       design_json=design.to_json())
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        add_to_gmsh(mesh)
        gmsh.write(str(tmp / "mesh.msh"))
    finally:
        gmsh.finalize()
    written = {}
    for name in ("mesh.h5", "mesh.xdmf", "keys.h5", "mesh.msh"):  # data before the xdmf that points at it
        (tmp / name).replace(out / name)
        written[name] = out / name
    tmp.rmdir()
    return written


def main() -> None:
    import hydra
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path="../conf", config_name="make_mesh")
    def _main(cfg: DictConfig) -> None:
        from fea_factory.design import DesignLimits, validate

        design = Design.load(cfg.design)
        validate(design, DesignLimits.from_mapping(cfg.blocks.limits))
        preset = MeshPreset.from_mapping(cfg.mesh)
        t0 = time.perf_counter()
        mesh = build_keyed_mesh(design, preset)
        t_build = time.perf_counter() - t0
        written = write_mesh(mesh, design, Path(cfg.out))
        sj = scaled_jacobian(mesh.node_xyz, mesh.cell_nodes)
        print(json.dumps({"design": str(cfg.design), "preset": preset.name, "nodes": mesh.n_nodes,
                          "cells": mesh.n_cells, "build_s": round(t_build, 4),
                          "min_scaled_jacobian": round(float(sj.min()), 4),
                          "files": [str(p) for p in written.values()]}))

    _main()


if __name__ == "__main__":
    main()
