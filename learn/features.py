"""Block features of an episode, read from the mesh through its key tables only, and points rebuilt from features.

Node-index specs below address a block's node grid: 0 = first, "mid" = middle (node counts are odd), -1 = last.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from learn.conditions import episode_conditions
from learn.graph import (BEAM, BEAM_KINDS, BOX_CORNERS, JOINT, JOINT_CORNER_IJ, JOINT_CORNERS, SECTION_CORNER_JK,
                         SECTION_CORNERS, SECTIONS, Incidence, Term)

# hex8 vertices in gmsh/VTK order as reference-cell coordinates in [0, 1]^3 (data_schema: cell_nodes, quad_points)
HEX8_REF = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
SECTION_I = {"start": 0, "middle": "mid", "end": -1}


def _point(name: str, node: tuple, **coeffs: float) -> tuple[str, tuple, dict]:
    return name, node, coeffs


# Points a joint's geometry rebuilds: (name, node (i, j, k) in joint_nodes, {geometry field: coefficient}).
JOINT_POINTS = (
    _point("center", ("mid", "mid", "mid"), center=1),
    _point("top_center", ("mid", "mid", -1), center=1, extrusion=1),
    *(_point(f"{c}_{h}", (ci and -1, cj and -1, k), center=1, **{f"corner_{c}": 1}, extrusion=e)
      for h, k, e in (("bottom", 0, -1), ("mid", "mid", 0), ("top", -1, 1))
      for c, (ci, cj) in zip(JOINT_CORNERS, JOINT_CORNER_IJ)),
)
# Points a beam's geometry rebuilds: per cross-section its centre, four edge middles and four corners;
# node (i, j, k) in beam_nodes; width points left (+j), height up (+k).
BEAM_POINTS = tuple(
    _point(f"{s}_{name}", (SECTION_I[s], j, k), **{f"{s}_center": 1, f"{s}_width": w, f"{s}_height": h})
    for s in SECTIONS
    for name, j, k, w, h in (
        ("center", "mid", "mid", 0, 0), ("left", -1, "mid", 1, 0), ("right", 0, "mid", -1, 0),
        ("top", "mid", -1, 0, 1), ("bottom", "mid", 0, 0, -1),
        ("right_bottom", 0, 0, -1, -1), ("left_bottom", -1, 0, 1, -1),
        ("left_top", -1, -1, 1, 1), ("right_top", 0, -1, -1, 1)))


def point_matrix(points: tuple, term: Term) -> np.ndarray:
    """[P, n_fields] coefficients of every point field/vector field of `term` (all 3-wide)."""
    names = term.names()
    m = np.zeros((len(points), len(names)))
    for p, (_, _, coeffs) in enumerate(points):
        for field, c in coeffs.items():
            m[p, names.index(field)] = c
    return m


def rebuild_points(geometry, term: Term, points: tuple):
    """Geometry features [..., n, term.size] -> points [..., n, P, 3] (numpy or torch)."""
    m = point_matrix(points, term)
    if isinstance(geometry, torch.Tensor):
        m = torch.as_tensor(m, dtype=geometry.dtype, device=geometry.device)
        return torch.einsum("pf,...fc->...pc", m, geometry.reshape(*geometry.shape[:-1], -1, 3))
    return np.einsum("pf,...fc->...pc", m, geometry.reshape(*geometry.shape[:-1], -1, 3))


def _idx(spec, n: int) -> int:
    return (n - 1) // 2 if spec == "mid" else (n - 1 if spec == -1 else spec)


def _node_table(table: np.ndarray, points: tuple) -> np.ndarray:
    """[n_blocks, P] node id of every point of every block, from a joint_nodes / beam_nodes table."""
    shape = table.shape[1:]
    return np.stack([table[:, _idx(i, shape[0]), _idx(j, shape[1]), _idx(k, shape[2])]
                     for _, (i, j, k), _ in points], axis=1)


@dataclass
class EpisodeFeatures:
    """One episode as graphs, translated so the fixed joint's reference centre is the origin. Arrays: [F, n, D]."""

    name: str
    family: str
    design_size: float  # mm, the error scale
    fea_seconds: float  # wall time of the FEA episode (provenance)
    t: np.ndarray  # [F]
    incidence: Incidence
    joint_state: np.ndarray  # [F, J, JOINT.state_size] geometry | stress
    beam_state: np.ndarray  # [F, B, BEAM.state_size]
    joint_bc: np.ndarray  # [J, JOINT.bc.size]
    beam_bc: np.ndarray  # [B, BEAM.bc.size]
    origin: np.ndarray  # [3] the translation removed (fixed joint reference centre, mm)
    point_nodes: np.ndarray  # [P] FEA node id of every rebuilt point: joints' JOINT_POINTS, then beams' BEAM_POINTS
    fea_points: np.ndarray  # [F, P, 3] FEA positions of those nodes, translated like the features
    conditions: dict = field(default_factory=dict)  # learn.conditions.episode_conditions: physics not in the graph
    fea_load_per_cpu: float = float("nan")  # provenance: how busy the machine was around the FEA (fea_factory.solve)

    @property
    def n_frames(self) -> int:
        return len(self.t)

    @property
    def actuators(self) -> str:
        """The design's actuator group (the sampler's, as in the thesis: all up, all down, random): 'all up',
        'all down' or 'all passive' when every beam is of that kind (from the beams' kind flags), else 'mixed'."""
        flags = np.stack([self.beam_bc[:, BEAM.bc.slice(f"kind_{k}")].ravel() for k in BEAM_KINDS], axis=1)
        kinds = {BEAM_KINDS[c] for c in flags.argmax(axis=1)}
        return f"all {kinds.pop()}" if len(kinds) == 1 else "mixed"

    def first_frame(self) -> "EpisodeFeatures":
        """The episode cut to its frame 0 (the design as printed): what a rollout starts from."""
        return replace(self, t=self.t[:1], joint_state=self.joint_state[:1], beam_state=self.beam_state[:1],
                       fea_points=self.fea_points[:1])

    def rotated(self, R: np.ndarray) -> "EpisodeFeatures":
        from learn.symmetry import rotate_term, rotate_vectors

        def state(x, block):
            g, s = x[..., block.geometry_slice], x[..., block.stress_slice]
            return np.concatenate([rotate_term(g, block.geometry, R), rotate_term(s, block.stress, R)], axis=-1)

        return EpisodeFeatures(
            name=self.name, family=self.family, design_size=self.design_size, fea_seconds=self.fea_seconds,
            fea_load_per_cpu=self.fea_load_per_cpu,
            t=self.t, incidence=self.incidence,
            joint_state=state(self.joint_state, JOINT), beam_state=state(self.beam_state, BEAM),
            joint_bc=rotate_term(self.joint_bc, JOINT.bc, R), beam_bc=rotate_term(self.beam_bc, BEAM.bc, R),
            origin=self.origin, point_nodes=self.point_nodes, fea_points=rotate_vectors(self.fea_points, R),
            conditions=self.conditions)

    def mirrored(self) -> "EpisodeFeatures":
        """The mirror image (learn.symmetry.MIRROR: x <-> y through the fixed joint), labelled as the factory labels
        the mirrored design (joint corners se <-> nw, beam left <-> right). Exact: material, residual stress and
        gravity are mirror-symmetric, so every field equals the one extracted from the FEA of the mirrored design
        (tests/test_learn_symmetry.py solves one)."""
        from learn.symmetry import MIRROR, MIRROR_RENAME
        return self._relabelled(MIRROR, MIRROR_RENAME, MIRROR_RENAME, np.zeros(self.incidence.n_beams, bool))

    def half_turned(self) -> "EpisodeFeatures":
        """The same design, nothing moved, labelled from the opposite corner of its lattice (learn.symmetry
        HALF_TURN_RENAME): every beam reversed, joint corners turned by half. This is how the factory labels the
        design turned by half a turn about z, so it is another labelling a sampled design can have; the FEA of the
        relabelled design gives these features (tests/test_learn_symmetry.py solves one)."""
        from learn.symmetry import HALF_TURN_RENAME, REVERSE_RENAME
        return self._relabelled(np.eye(3), HALF_TURN_RENAME, REVERSE_RENAME, np.ones(self.incidence.n_beams, bool))

    def quarter_turned(self) -> "EpisodeFeatures":
        """The same design, nothing moved, labelled from the next corner of its lattice counter-clockwise, (i, j) ->
        (j, n_i - 1 - i), as the factory labels the design turned by a quarter turn: the beams along i run the other
        way and become the beams along j, those along j keep their direction, joint corners turn by a quarter
        (learn.symmetry.QUARTER_TURN_RENAME). Two quarter turns are the half turn."""
        from learn.symmetry import QUARTER_TURN_RENAME, REVERSE_RENAME
        return self._relabelled(np.eye(3), QUARTER_TURN_RENAME, REVERSE_RENAME, self.beams_along_i())

    def beams_along_i(self) -> np.ndarray:
        """[B] bool: the beams that leave their start joint through its east face (lattice direction +i; else +j)."""
        start = self.incidence.senders[:self.incidence.n_beams]
        return beams_along_i(*(torch.as_tensor(x) for x in (self.joint_state[0], self.beam_state[0], start))).numpy()

    def _relabelled(self, R: np.ndarray, joint_rename: dict, reverse_rename: dict, reverse: np.ndarray
                    ) -> "EpisodeFeatures":
        """Every field transformed by R about the fixed joint and renamed (learn.symmetry.term_relabel): joints by
        joint_rename, beams by it too and, where `reverse` [B] is set, also by reverse_rename (those beams then run
        the other way: start and end joints swap)."""
        from learn.symmetry import composed, relabel_order, state_matrix, term_relabel

        beam_renames = (joint_rename, composed(reverse_rename, joint_rename))  # kept, reversed
        state_M = lambda block, rename: state_matrix(block, lambda term: term_relabel(term, R, rename))  # noqa: E731
        bc_M = lambda block, rename: term_relabel(block.bc, R, rename)  # noqa: E731

        def relabel(x, matrix, block, renames, rev):  # [..., n, D] @ the block's matrix, per row: renames[rev]
            out = np.empty_like(x)
            for r, rename in zip((False, True), renames):
                if (rev == r).any():
                    out[..., rev == r, :] = x[..., rev == r, :].astype(np.float64) @ matrix(block, rename)
            return out

        J, B = self.incidence.n_joints, self.incidence.n_beams
        joints = lambda x, matrix: relabel(x, matrix, JOINT, (joint_rename,) * 2, np.zeros(J, bool))  # noqa: E731
        beams = lambda x, matrix: relabel(x, matrix, BEAM, beam_renames, reverse)  # noqa: E731
        jo = relabel_order([p[0] for p in JOINT_POINTS], joint_rename)
        bo = [relabel_order([p[0] for p in BEAM_POINTS], r) for r in beam_renames]
        order = np.concatenate([(np.arange(J)[:, None] * len(jo) + jo).ravel(),
                                J * len(jo) + np.concatenate([b * len(bo[0]) + bo[int(r)]
                                                              for b, r in enumerate(reverse)])])
        senders, receivers = self.incidence.senders[:B], self.incidence.receivers[:B]
        beam_ends = np.where(reverse[:, None], np.stack([receivers, senders], 1), np.stack([senders, receivers], 1))
        return EpisodeFeatures(
            name=self.name, family=self.family, design_size=self.design_size, fea_seconds=self.fea_seconds,
            fea_load_per_cpu=self.fea_load_per_cpu,
            t=self.t, incidence=Incidence.from_beams(beam_ends, J),
            joint_state=joints(self.joint_state, state_M), beam_state=beams(self.beam_state, state_M),
            joint_bc=joints(self.joint_bc, bc_M), beam_bc=beams(self.beam_bc, bc_M), origin=R @ self.origin,
            point_nodes=self.point_nodes[order], fea_points=(self.fea_points @ R.T)[:, order].astype(np.float32),
            conditions=self.conditions)


def beams_along_i(joint_state, beam_state, start) -> torch.Tensor:
    """[B] bool from states [J, Sj], [B, Sb] of the flat design and each beam's start joint [B]: the beams that leave
    their start joint through its east face (lattice direction +i; else +j), i.e. whose start section centre is
    nearer the middle of the joint's se-ne side than of its ne-nw side. Torch, so a traced rollout computes it."""
    g = JOINT.geometry
    joints = joint_state.index_select(-2, start)
    centre = joints[..., g.slice("center")]
    side = lambda a, b: centre + 0.5 * (joints[..., g.slice(f"corner_{a}")]  # noqa: E731
                                        + joints[..., g.slice(f"corner_{b}")])
    section = beam_state[..., BEAM.geometry.slice("start_center")]
    dist = lambda p: torch.linalg.vector_norm(section - p, dim=-1)  # noqa: E731
    return dist(side("se", "ne")) < dist(side("ne", "nw"))


def rebuild_all_points(joint_state, beam_state):
    """States [..., J, Dj] and [..., B, Db] -> every rebuilt point [..., P, 3] in point_nodes order."""
    jp = rebuild_points(joint_state[..., JOINT.geometry_slice], JOINT.geometry, JOINT_POINTS)
    bp = rebuild_points(beam_state[..., BEAM.geometry_slice], BEAM.geometry, BEAM_POINTS)
    flat = (lambda x: x.flatten(-3, -2)) if isinstance(jp, torch.Tensor) else \
        (lambda x: x.reshape(*x.shape[:-3], -1, 3))
    cat = torch.cat if isinstance(jp, torch.Tensor) else np.concatenate
    return cat([flat(jp), flat(bp)], -2)


def shared_point_pairs(point_nodes: np.ndarray) -> np.ndarray:
    """[M, 2] pairs of rebuilt points that stand for the same FEA node (a beam end face on its joint)."""
    order = np.argsort(point_nodes, kind="stable")
    ids = point_nodes[order]
    pairs = []
    start = 0
    for end in range(1, len(ids) + 1):
        if end == len(ids) or ids[end] != ids[start]:
            group = order[start:end]
            pairs += [(group[0], g) for g in group[1:]]
            start = end
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def welded(points: np.ndarray, point_nodes: np.ndarray) -> np.ndarray:
    """points [..., P, 3] with every group of points that stand for one FEA node (a beam's end face and its joint's
    face) moved to the group's mean: one position per node, a closed solid instead of blocks that each carry their
    own copy of the interface. The mean's error is at most its farthest copy's (it lies in the copies' hull)."""
    _, group, count = np.unique(point_nodes, return_inverse=True, return_counts=True)
    order = np.argsort(group, kind="stable")  # the copies of each node side by side
    starts = np.concatenate([[0], np.cumsum(count)[:-1]])
    mean = np.add.reduceat(points[..., order, :], starts, axis=-2) / count[:, None]  # [..., nodes, 3]
    return mean[..., group, :]


def _corner_quad_point(cells: np.ndarray, nodes: np.ndarray, cell_nodes: np.ndarray,
                       quad_points: np.ndarray) -> np.ndarray:
    """Quadrature point index [n] of each cell nearest to the given vertex node of that cell."""
    hit = cell_nodes[cells] == nodes[:, None]  # [n, 8]
    if not hit.any(axis=1).all():
        raise ValueError("a block corner node is not a vertex of its corner cell: the key tables are inconsistent")
    vertex = hit.argmax(axis=1)
    d = np.linalg.norm(HEX8_REF[vertex][:, None, :] - quad_points[None], axis=-1)  # [n, Q]
    return d.argmin(axis=1)


def _sample_stress(stress: np.ndarray, cells: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """stress [F, C, Q, 6] at (cells, quads) [n, S] -> [F, n, S * 6]."""
    s = stress[:, cells, quads]  # [F, n, S, 6]
    return s.reshape(s.shape[0], s.shape[1], -1)


def joint_stress_sites(ep) -> tuple[np.ndarray, np.ndarray]:
    """Cells and quadrature points [J, 8] sampled for each joint's BOX_CORNERS."""
    nw, nh = ep.joint_nodes.shape[1], ep.joint_nodes.shape[3]
    cells, nodes = [], []
    for name in BOX_CORNERS:
        c, h = name.split("_")
        ci, cj = JOINT_CORNER_IJ[JOINT_CORNERS.index(c)]
        ck = 1 if h == "top" else 0
        cells.append(ep.joint_cells[:, ci * (nw - 2), cj * (nw - 2), ck * (nh - 2)])
        nodes.append(ep.joint_nodes[:, ci * (nw - 1), cj * (nw - 1), ck * (nh - 1)])
    cells, nodes = np.stack(cells, 1), np.stack(nodes, 1)
    q = _corner_quad_point(cells.ravel(), nodes.ravel(), ep.cell_nodes, ep.quad_points).reshape(cells.shape)
    return cells, q


def beam_stress_sites(ep) -> tuple[np.ndarray, np.ndarray]:
    """Cells and quadrature points [B, 12, 2] for each beam's section corners; the two sides of the middle section
    are averaged, the end sections use their one cell twice."""
    nl, nw, nh = ep.beam_nodes.shape[1:]
    mid = (nl - 1) // 2
    cells, nodes = [], []
    for s in SECTIONS:
        i = {"start": 0, "middle": mid, "end": nl - 1}[s]
        sides = {"start": (0, 0), "middle": (mid - 1, mid), "end": (nl - 2, nl - 2)}[s]
        for cj, ck in SECTION_CORNER_JK:
            cells.append(np.stack([ep.beam_cells[:, ci, cj * (nw - 2), ck * (nh - 2)] for ci in sides], -1))
            nodes.append(np.repeat(ep.beam_nodes[:, i, cj * (nw - 1), ck * (nh - 1)][:, None], 2, axis=1))
    cells, nodes = np.stack(cells, 1), np.stack(nodes, 1)  # [B, 12, 2]
    q = _corner_quad_point(cells.ravel(), nodes.ravel(), ep.cell_nodes, ep.quad_points).reshape(cells.shape)
    return cells, q


def fea_seconds(solver_stats: dict) -> float:
    """Total wall time of the FEA episode from its provenance (solver_stats_json: wall_s.total), NaN if absent."""
    wall = solver_stats.get("wall_s", {})
    value = wall.get("total") if isinstance(wall, dict) else None
    return float(value if value is not None else solver_stats.get("wall_total_s", float("nan")))


def extract(ep, name: str = "") -> EpisodeFeatures:
    """Features of every frame of an episode (a data_schema.episode.Episode)."""
    xyz = np.asarray(ep.node_xyz, dtype=np.float64)  # [F, N, 3]
    J, B = len(ep.joint_nodes), len(ep.beam_nodes)
    joint_nodes = _node_table(ep.joint_nodes, JOINT_POINTS)  # [J, Pj]
    beam_nodes = _node_table(ep.beam_nodes, BEAM_POINTS)  # [B, Pb]
    origin = xyz[0, joint_nodes[ep.fixed_joint, 0]].copy()  # JOINT_POINTS[0] is the joint centre
    pos = xyz - origin

    jg = np.zeros((len(xyz), J, JOINT.geometry.size))
    names = [p[0] for p in JOINT_POINTS]
    center = pos[:, joint_nodes[:, names.index("center")]]
    jg[..., JOINT.geometry.slice("center")] = center
    jg[..., JOINT.geometry.slice("extrusion")] = pos[:, joint_nodes[:, names.index("top_center")]] - center
    for c in JOINT_CORNERS:
        jg[..., JOINT.geometry.slice(f"corner_{c}")] = pos[:, joint_nodes[:, names.index(f"{c}_mid")]] - center
    bg = np.zeros((len(xyz), B, BEAM.geometry.size))
    names = [p[0] for p in BEAM_POINTS]
    for s in SECTIONS:
        c = pos[:, beam_nodes[:, names.index(f"{s}_center")]]
        bg[..., BEAM.geometry.slice(f"{s}_center")] = c
        side = lambda a, b: 0.5 * (pos[:, beam_nodes[:, names.index(f"{s}_{a}")]]  # noqa: E731
                                   - pos[:, beam_nodes[:, names.index(f"{s}_{b}")]])
        bg[..., BEAM.geometry.slice(f"{s}_width")] = side("left", "right")  # symmetric about the section: the
        bg[..., BEAM.geometry.slice(f"{s}_height")] = side("top", "bottom")  # mirror maps it exactly (symmetry.py)

    stress = np.asarray(ep.stress)
    jc, jq = joint_stress_sites(ep)
    js = _sample_stress(stress, jc, jq)
    bc_, bq = beam_stress_sites(ep)
    bs = 0.5 * (_sample_stress(stress, bc_[..., 0], bq[..., 0]) + _sample_stress(stress, bc_[..., 1], bq[..., 1]))

    jbc = np.zeros((J, JOINT.bc.size))
    jbc[ep.fixed_joint, JOINT.bc.slice("fixed")] = 1.0
    jbc[:, JOINT.bc.slice("position")] = jg[0, :, JOINT.geometry.slice("center")]
    bbc = np.zeros((B, BEAM.bc.size))
    kind = np.asarray(ep.beam_kind, dtype=np.int64)
    for code, k in enumerate(BEAM_KINDS):
        bbc[kind == code, BEAM.bc.slice(f"kind_{k}")] = 1.0
    bbc[:, BEAM.bc.slice("position")] = bg[0, :, BEAM.geometry.slice("middle_center")]

    point_nodes = np.concatenate([joint_nodes.ravel(), beam_nodes.ravel()])
    return EpisodeFeatures(
        name=name, family=str(ep.family), design_size=float(ep.design_size),
        fea_seconds=fea_seconds(ep.solver_stats),
        fea_load_per_cpu=float(ep.solver_stats.get("load_per_cpu", float("nan"))),
        t=np.asarray(ep.t, dtype=np.float64), incidence=Incidence.from_beams(ep.beams, J),
        joint_state=np.concatenate([jg, js], -1).astype(np.float32),
        beam_state=np.concatenate([bg, bs], -1).astype(np.float32),
        joint_bc=jbc.astype(np.float32), beam_bc=bbc.astype(np.float32), origin=origin,
        point_nodes=point_nodes, fea_points=pos[:, point_nodes].astype(np.float32),
        conditions=episode_conditions(ep.config_yaml, ep.joint_xy, ep.beams))
