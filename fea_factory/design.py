"""Grid designs: joints on a quad lattice, beams between lattice neighbours, JSON round-trip and validation.

Units: millimetres for lengths, degrees for angles. A design is flat (z = 0 is the print bed).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from data_schema import atomic

BEAM_KINDS = ("up", "down", "passive")
DESIGN_FORMAT = "morphsim.design/1"


class DesignError(ValueError):
    """A design that cannot be printed or meshed; the message names the joint/beam and the allowed range."""


@dataclass(frozen=True)
class DesignLimits:
    """Printable and meshable ranges (conf/design/*.yaml)."""

    printable_width: float = 300.0  # mm, x extent of the print bed
    printable_depth: float = 300.0  # mm, y extent of the print bed
    min_beam_length: float = 10.0  # mm, clear length of a beam between its two joint blocks
    max_beam_length: float = 150.0  # mm, longest clear length verified stable (length/thickness 37.5)
    min_joint_angle: float = 45.0  # deg, smallest corner angle of a joint block (and 180 - it the largest)
    min_beam_width: float = 2.0  # mm
    max_beam_width: float = 20.0  # mm
    min_thickness: float = 1.0  # mm
    max_thickness: float = 20.0  # mm

    @classmethod
    def from_mapping(cls, m: Any) -> "DesignLimits":
        known = {f: m[f] for f in cls.__dataclass_fields__ if f in m}
        return cls(**{k: float(v) for k, v in known.items()})


@dataclass
class Design:
    """A quad-mesh grid of joints (nodes) and beams (edges).

    joint_ij: [J, 2] int lattice index of each joint (i along the grid's first direction, j the second)
    joint_xy: [J, 2] float joint centre in the print plane, mm
    beams:    [B, 2] int joint pair (a, b); the beam's axis runs from a to b
    kinds:    [B] one of BEAM_KINDS ("up": bends up, its top layer prints along the axis;
              "down": its bottom layer prints along the axis; "passive": both layers across)
    """

    joint_ij: np.ndarray
    joint_xy: np.ndarray
    beams: np.ndarray
    kinds: list[str]
    fixed_joint: int
    beam_width: float = 7.2  # mm
    thickness: float = 4.0  # mm
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_ij = np.asarray(self.joint_ij, dtype=np.int64).reshape(-1, 2)
        self.joint_xy = np.asarray(self.joint_xy, dtype=np.float64).reshape(-1, 2)
        self.beams = np.asarray(self.beams, dtype=np.int64).reshape(-1, 2)
        self.kinds = [str(k) for k in self.kinds]
        self.fixed_joint = int(self.fixed_joint)
        self.beam_width = float(self.beam_width)
        self.thickness = float(self.thickness)

    @property
    def n_joints(self) -> int:
        return len(self.joint_xy)

    @property
    def n_beams(self) -> int:
        return len(self.beams)

    @property
    def size(self) -> float:
        """Design size (mm): the larger side of the bounding box of the joint centres, the error scale
        (one definition, data_schema.episode.design_size; a valid design has a beam, so it is > 0)."""
        from data_schema.episode import design_size

        return design_size(self.joint_xy)

    # ---------------------------------------------------------------- JSON
    def to_dict(self) -> dict:
        return {
            "format": DESIGN_FORMAT,
            "joints": [{"ij": [int(i), int(j)], "xy": [float(x), float(y)]}
                       for (i, j), (x, y) in zip(self.joint_ij, self.joint_xy)],
            "beams": [[int(a), int(b), k] for (a, b), k in zip(self.beams, self.kinds)],
            "fixed_joint": self.fixed_joint,
            "beam_width": self.beam_width,
            "thickness": self.thickness,
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Design":
        fmt = d.get("format")
        if fmt != DESIGN_FORMAT:
            raise DesignError(f"design field 'format' is {fmt!r}; expected {DESIGN_FORMAT!r}")
        for key in ("joints", "beams", "fixed_joint"):
            if key not in d:
                raise DesignError(f"design is missing field {key!r}")
        joints, beams = d["joints"], d["beams"]
        return cls(
            joint_ij=[j["ij"] for j in joints],
            joint_xy=[j["xy"] for j in joints],
            beams=[b[:2] for b in beams],
            kinds=[b[2] for b in beams],
            fixed_joint=d["fixed_joint"],
            beam_width=d.get("beam_width", 7.2),
            thickness=d.get("thickness", 4.0),
            meta=d.get("meta", {}),
        )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_json(cls, text: str) -> "Design":
        return cls.from_dict(json.loads(text))

    def save(self, path: str | Path) -> None:
        atomic.write_text(path, self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> "Design":
        return cls.from_json(Path(path).read_text())


def validate(design: Design, limits: DesignLimits = DesignLimits()) -> None:
    """Raise DesignError on the first problem found; return None for a printable, meshable design."""
    from fea_factory import geometry  # geometry needs a topologically valid design first

    _validate_fields(design, limits)
    _validate_topology(design)
    blocks = geometry.block_geometry(design)
    geometry.check_blocks(design, blocks, limits)


def _validate_fields(d: Design, limits: DesignLimits) -> None:
    if d.n_joints < 2:
        raise DesignError(f"design has {d.n_joints} joints; at least 2 are needed")
    if d.n_beams < 1:
        raise DesignError("design has no beams; at least 1 is needed")
    if not np.all(np.isfinite(d.joint_xy)):
        bad = int(np.where(~np.isfinite(d.joint_xy).all(axis=1))[0][0])
        raise DesignError(f"joint {bad}: position {d.joint_xy[bad].tolist()} is not finite")
    if not limits.min_beam_width <= d.beam_width <= limits.max_beam_width:
        raise DesignError(f"beam_width {d.beam_width} mm is outside the allowed range "
                          f"[{limits.min_beam_width}, {limits.max_beam_width}] mm")
    if not limits.min_thickness <= d.thickness <= limits.max_thickness:
        raise DesignError(f"thickness {d.thickness} mm is outside the allowed range "
                          f"[{limits.min_thickness}, {limits.max_thickness}] mm")
    if not 0 <= d.fixed_joint < d.n_joints:
        raise DesignError(f"fixed_joint {d.fixed_joint} is outside the allowed range [0, {d.n_joints - 1}]")
    if len(d.kinds) != d.n_beams:
        raise DesignError(f"design has {d.n_beams} beams but {len(d.kinds)} beam kinds")
    for b, k in enumerate(d.kinds):
        if k not in BEAM_KINDS:
            raise DesignError(f"beam {b}: kind {k!r} is not one of {list(BEAM_KINDS)}")


def _validate_topology(d: Design) -> None:
    seen_ij: dict[tuple[int, int], int] = {}
    for n, ij in enumerate(map(tuple, d.joint_ij.tolist())):
        if ij in seen_ij:
            raise DesignError(f"joint {n}: lattice index {list(ij)} is already used by joint {seen_ij[ij]}")
        seen_ij[ij] = n
    pairs: dict[frozenset, int] = {}
    degree = np.zeros(d.n_joints, dtype=int)
    for b, (a, c) in enumerate(d.beams.tolist()):
        for end in (a, c):
            if not 0 <= end < d.n_joints:
                raise DesignError(f"beam {b}: joint index {end} is outside the allowed range [0, {d.n_joints - 1}]")
        if a == c:
            raise DesignError(f"beam {b}: joins joint {a} to itself")
        key = frozenset((a, c))
        if key in pairs:
            raise DesignError(f"beam {b}: joints {a} and {c} are already joined by beam {pairs[key]} "
                              "(overlapping beams)")
        pairs[key] = b
        di, dj = np.abs(d.joint_ij[c] - d.joint_ij[a])
        if di + dj != 1:
            raise DesignError(
                f"beam {b}: joins joint {a} at lattice {d.joint_ij[a].tolist()} and joint {c} at lattice "
                f"{d.joint_ij[c].tolist()}, which are not grid neighbours: beams must run along the two grid "
                "directions (lattice step of exactly 1 in i or j)")
        if np.linalg.norm(d.joint_xy[c] - d.joint_xy[a]) < 1e-9:  # the beam axis (geometry) would be 0/0
            raise DesignError(f"beam {b}: joints {a} and {c} are both at {d.joint_xy[a].tolist()}; "
                              "a beam needs two distinct joint positions")
        degree[a] += 1
        degree[c] += 1
    for n in range(d.n_joints):
        if degree[n] == 0:
            raise DesignError(f"joint {n}: has no beam; every joint needs 1 to 4 beams")
        if degree[n] > 4:
            raise DesignError(f"joint {n}: has {degree[n]} beams; a quad grid joint allows at most 4")
    # Every joint must hang from the fixed joint: a floating part makes the FEA problem singular.
    reach = {d.fixed_joint}
    frontier = [d.fixed_joint]
    nbrs: dict[int, list[int]] = {n: [] for n in range(d.n_joints)}
    for a, c in d.beams.tolist():
        nbrs[a].append(c)
        nbrs[c].append(a)
    while frontier:
        n = frontier.pop()
        for m in nbrs[n]:
            if m not in reach:
                reach.add(m)
                frontier.append(m)
    if len(reach) != d.n_joints:
        lost = sorted(set(range(d.n_joints)) - reach)
        raise DesignError(f"joints {lost} are not connected to the fixed joint {d.fixed_joint} by beams; "
                          "a floating part has no support")


def lattice_design(xy: np.ndarray, kinds: list[str] | str, fixed_ij: tuple[int, int],
                   beam_width: float = 7.2, thickness: float = 4.0, meta: dict | None = None) -> Design:
    """A full nx x ny grid from joint positions xy [nx, ny, 2] (mm).

    Joints are numbered j-major (n = j * nx + i); beams list first the i-direction beams
    (i, j)-(i+1, j) row by row, then the j-direction beams (i, j)-(i, j+1). `kinds` is one kind for all
    beams or a list of B kinds in that order.
    """
    xy = np.asarray(xy, dtype=np.float64)
    nx, ny = xy.shape[:2]
    if nx < 2 or ny < 2:
        raise DesignError(f"grid size {nx} x {ny}: at least 2 joints are needed along each direction")
    ij = np.array([(i, j) for j in range(ny) for i in range(nx)])
    pos = np.array([xy[i, j] for i, j in ij])
    beams = [(j * nx + i, j * nx + i + 1) for j in range(ny) for i in range(nx - 1)]
    beams += [(j * nx + i, (j + 1) * nx + i) for j in range(ny - 1) for i in range(nx)]
    if isinstance(kinds, str):
        kinds = [kinds] * len(beams)
    if len(kinds) != len(beams):
        raise DesignError(f"{len(kinds)} beam kinds given for a {nx} x {ny} grid with {len(beams)} beams")
    fi, fj = fixed_ij
    if not (0 <= fi < nx and 0 <= fj < ny):
        raise DesignError(f"fixed joint lattice index {list(fixed_ij)} is outside the grid [0, {nx - 1}] x [0, {ny - 1}]")
    return Design(ij, pos, beams, list(kinds), fj * nx + fi, beam_width, thickness, dict(meta or {}))
