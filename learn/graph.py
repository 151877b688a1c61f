"""Graph of a design: joints are nodes, beams are directed edges; named feature layouts declared once.

Every feature vector is a concatenation of named fields. A field has a kind that says how it transforms:
- "point":  a position (mm); translated to a local origin and rotated,
- "vector": a displacement between points (mm); rotated only,
- "stress": a Cauchy stress in Voigt order xx, yy, zz, xy, xz, yz (MPa); rotated as R s R^T,
- "scalar": unchanged (flags, one-hot codes, time).
Columns are only ever addressed through `Term.slice(name)` and `Term.kind_mask(kind)`, never by number.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

KINDS = ("point", "vector", "stress", "scalar")
WIDTH = {"point": 3, "vector": 3, "stress": 6, "scalar": 1}


@dataclass(frozen=True)
class Field:
    name: str
    kind: str
    size: int = 0  # 0: the kind's natural width

    @property
    def width(self) -> int:
        return self.size or WIDTH[self.kind]


@dataclass(frozen=True)
class Term:
    """One term (geometry, stress or boundary condition) of a block's feature vector."""

    name: str
    fields: tuple[Field, ...]

    @property
    def size(self) -> int:
        return sum(f.width for f in self.fields)

    def slice(self, name: str) -> slice:
        start = 0
        for f in self.fields:
            if f.name == name:
                return slice(start, start + f.width)
            start += f.width
        raise KeyError(f"term {self.name!r} has no field {name!r}; fields: {[f.name for f in self.fields]}")

    def slices(self, kind: str) -> list[slice]:
        return [self.slice(f.name) for f in self.fields if f.kind == kind]

    def names(self, kind: str | None = None) -> list[str]:
        return [f.name for f in self.fields if kind is None or f.kind == kind]


JOINT_CORNERS = ("sw", "se", "ne", "nw")  # mid-height quad corners, counter-clockwise from (i, j) = (0, 0)
JOINT_CORNER_IJ = ((0, 0), (1, 0), (1, 1), (0, 1))  # 0 = low index side, 1 = high index side
BOX_CORNERS = tuple(f"{c}_{h}" for h in ("bottom", "top") for c in JOINT_CORNERS)
SECTIONS = ("start", "middle", "end")  # beam cross-sections at node planes i = 0, (nl-1)/2, nl-1
SECTION_CORNERS = ("right_bottom", "left_bottom", "left_top", "right_top")  # (j, k) = (0,0) (1,0) (1,1) (0,1)
SECTION_CORNER_JK = ((0, 0), (1, 0), (1, 1), (0, 1))
BEAM_KINDS = ("up", "down", "passive")  # data_schema beam_kind codes 0, 1, 2

JOINT_GEOMETRY = Term("geometry", (
    Field("center", "point"),  # centre of the mid-height quad
    *(Field(f"corner_{c}", "vector") for c in JOINT_CORNERS),  # centre -> mid-height quad corner
    Field("extrusion", "vector"),  # centre -> top-face centre
))
JOINT_STRESS = Term("stress", tuple(Field(f"corner_{c}", "stress") for c in BOX_CORNERS))
JOINT_BC = Term("bc", (
    Field("fixed", "scalar"),
    Field("position", "vector"),  # reference centre relative to the fixed joint's reference centre
))
BEAM_GEOMETRY = Term("geometry", tuple(
    f for s in SECTIONS for f in (
        Field(f"{s}_center", "point"),
        Field(f"{s}_width", "vector"),  # half of (right edge middle -> left edge middle): half width, to the left
        Field(f"{s}_height", "vector"),  # half of (bottom edge middle -> top edge middle): half thickness, up
    )))
BEAM_STRESS = Term("stress", tuple(Field(f"{s}_{c}", "stress") for s in SECTIONS for c in SECTION_CORNERS))
BEAM_BC = Term("bc", (
    *(Field(f"kind_{k}", "scalar") for k in BEAM_KINDS),  # one-hot actuator kind
    Field("position", "vector"),  # reference middle centre relative to the fixed joint's reference centre
))


@dataclass(frozen=True)
class Block:
    """A block type: its three feature terms and the point its features are translated to for its own update.

    The state the simulator advances is cat(geometry, stress); the boundary-condition term stays constant.
    """

    name: str
    geometry: Term
    stress: Term
    bc: Term
    origin: str  # a point field of `geometry`

    @property
    def state_size(self) -> int:
        return self.geometry.size + self.stress.size

    @property
    def geometry_slice(self) -> slice:
        return slice(0, self.geometry.size)

    @property
    def stress_slice(self) -> slice:
        return slice(self.geometry.size, self.state_size)

    @property
    def origin_slice(self) -> slice:
        return self.geometry.slice(self.origin)


JOINT = Block("joint", JOINT_GEOMETRY, JOINT_STRESS, JOINT_BC, origin="center")
BEAM = Block("beam", BEAM_GEOMETRY, BEAM_STRESS, BEAM_BC, origin="middle_center")


@dataclass(frozen=True)
class Incidence:
    """Directed edges of a graph: each beam b = (a, c) gives a -> c (edge b) and c -> a (edge B + b)."""

    senders: np.ndarray  # [E] joint
    receivers: np.ndarray  # [E] joint
    edge_beam: np.ndarray  # [E] beam
    n_joints: int
    n_beams: int
    joint_graph: np.ndarray | None = None  # [J] design each joint belongs to in a disjoint union (None: one design)
    beam_graph: np.ndarray | None = None  # [B]
    n_graphs: int = 1

    @classmethod
    def from_beams(cls, beams: np.ndarray, n_joints: int) -> "Incidence":
        beams = np.asarray(beams, dtype=np.int64).reshape(-1, 2)
        b = np.arange(len(beams))
        return cls(senders=np.concatenate([beams[:, 0], beams[:, 1]]),
                   receivers=np.concatenate([beams[:, 1], beams[:, 0]]),
                   edge_beam=np.concatenate([b, b]), n_joints=int(n_joints), n_beams=len(beams))

    @property
    def n_edges(self) -> int:
        return len(self.senders)

    def adjacency(self) -> np.ndarray:
        """The thesis' M_adj: [B, J] ones where a beam touches a joint."""
        m = np.zeros((self.n_beams, self.n_joints), dtype=np.int8)
        m[self.edge_beam, self.senders] = 1
        return m

    def tensors(self, device: str | torch.device = "cpu") -> "GraphIndex":
        member = (None, None) if self.joint_graph is None else \
            (torch.as_tensor(self.joint_graph, device=device), torch.as_tensor(self.beam_graph, device=device))
        return GraphIndex(*(torch.as_tensor(a, device=device) for a in (self.senders, self.receivers, self.edge_beam)),
                          n_joints=self.n_joints, n_beams=self.n_beams, joint_graph=member[0], beam_graph=member[1],
                          n_graphs=self.n_graphs)


@dataclass
class GraphIndex:
    """Incidence as torch index tensors, as the networks consume it."""

    senders: torch.Tensor  # [E]
    receivers: torch.Tensor  # [E]
    edge_beam: torch.Tensor  # [E]
    n_joints: int
    n_beams: int
    joint_graph: torch.Tensor | None = None  # [J] design of every joint in a disjoint union; None: a single design
    beam_graph: torch.Tensor | None = None  # [B]
    n_graphs: int = 1

    def beam_starts(self) -> torch.Tensor:
        """[B] the start joint of every beam: the sender of its first directed edge (a beam's edge a -> c comes
        before c -> a, in one graph as in a disjoint union)."""
        return self.beam_ends()[0]

    def with_reversed(self, reverse: torch.Tensor) -> "GraphIndex":
        """The graph with the beams where `reverse` [B] is set running the other way: both directed edges of such a
        beam swap sender and receiver, so its start joint (beam_ends) is its former end joint. The set of directed
        edges stays the same and a core sums a beam's two edges alike, so only what reads a beam's direction (the
        stiffness update's solve and rigid motion) sees the difference."""
        flip = reverse.index_select(0, self.edge_beam)
        return replace(self, senders=torch.where(flip, self.receivers, self.senders),
                       receivers=torch.where(flip, self.senders, self.receivers))

    def labelled_union(self, reverse: torch.Tensor) -> "GraphIndex":
        """L copies of this graph as one disjoint union, copy i with the beams where `reverse` [L, B] is set reversed
        (with_reversed): joints and beams of copy i follow those of copy i - 1, each copy's designs are designs of
        their own."""
        L, J, B = reverse.shape[0], self.n_joints, self.n_beams
        copies = [self.with_reversed(reverse[i]) for i in range(L)]
        own = lambda graph, n: torch.zeros(n, dtype=torch.long) if graph is None else graph  # noqa: E731
        return GraphIndex(senders=torch.cat([c.senders + i * J for i, c in enumerate(copies)]),
                          receivers=torch.cat([c.receivers + i * J for i, c in enumerate(copies)]),
                          edge_beam=torch.cat([self.edge_beam + i * B for i in range(L)]),
                          n_joints=L * J, n_beams=L * B,
                          joint_graph=torch.cat([own(self.joint_graph, J) + i * self.n_graphs for i in range(L)]),
                          beam_graph=torch.cat([own(self.beam_graph, B) + i * self.n_graphs for i in range(L)]),
                          n_graphs=L * self.n_graphs)

    def beam_ends(self) -> tuple[torch.Tensor, torch.Tensor]:
        """[B] twice: the start and the end joint of every beam (sender and receiver of its first directed edge)."""
        edges = torch.arange(len(self.edge_beam), device=self.edge_beam.device)
        first = edges.new_full((self.n_beams,), len(self.edge_beam)).scatter_reduce(0, self.edge_beam, edges, "amin")
        return self.senders.index_select(0, first), self.receivers.index_select(0, first)


def disjoint_union(parts: list[Incidence]) -> tuple[Incidence, np.ndarray, np.ndarray]:
    """One graph holding all parts; also the joint and beam offsets [P + 1] of every part."""
    jo = np.cumsum([0] + [p.n_joints for p in parts])
    bo = np.cumsum([0] + [p.n_beams for p in parts])
    inc = Incidence(
        senders=np.concatenate([p.senders + jo[i] for i, p in enumerate(parts)]),
        receivers=np.concatenate([p.receivers + jo[i] for i, p in enumerate(parts)]),
        edge_beam=np.concatenate([p.edge_beam + bo[i] for i, p in enumerate(parts)]),
        n_joints=int(jo[-1]), n_beams=int(bo[-1]),
        joint_graph=np.repeat(np.arange(len(parts)), np.diff(jo)),
        beam_graph=np.repeat(np.arange(len(parts)), np.diff(bo)), n_graphs=len(parts))
    return inc, jo, bo
