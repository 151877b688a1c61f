"""How far a grid has rolled, measured along its own lattice.

A flat grid whose actuators all bend one way ("all up" or "all down") asks for the same curvature along its rows
and its columns: a bowl, which a sheet cannot take without stretching. So it rolls one way into a near-cylinder, or
rarely snaps shut into a bowl: a bifurcation. The FEA rolls every such grid that rolls along its longer flat span
(scripts/roll_direction.py: 33 of 33 in 182 episodes, session 30), so which way it goes is set by the design.

Measured along the lattice, not along x and y: i and j are the mean in-plane directions of the design's beams
along i and along j (a grid's lattice may lie at any angle to x), and the shrink along u is the final frame's extent
of the points along u over the flat frame's. A roll along i shrinks i and keeps j: s_i - s_j < 0.
"""
from __future__ import annotations

import numpy as np

from learn.graph import JOINT

ONE_KIND = ("all up", "all down")  # EpisodeFeatures.actuators of the designs that face the bifurcation
ROLLED = 0.15  # |s_i - s_j| above this: one way has curled clearly more than the other


def flat_centres(f) -> np.ndarray:
    """[J, 2] the design's flat joint centres (their bc positions, relative to the fixed joint)."""
    return f.joint_bc[:, JOINT.bc.slice("position")][:, :2]


def lattice_directions(f) -> tuple[np.ndarray, np.ndarray]:
    """The mean in-plane unit direction of a design's beams along i and of those along j (each beam pointed along
    +i or +j by its lattice sense, so that they add up)."""
    p = flat_centres(f)
    beams = np.stack([f.incidence.senders[:f.incidence.n_beams], f.incidence.receivers[:f.incidence.n_beams]], 1)
    along_i = f.beams_along_i()
    out = []
    for mask in (along_i, ~along_i):
        d = p[beams[mask, 1]] - p[beams[mask, 0]]
        d = d * np.sign(d @ d[0])[:, None]  # one sense for all
        u = d.sum(0)
        out.append(u / np.linalg.norm(u))
    return out[0], out[1]


def extent(points: np.ndarray, u: np.ndarray) -> float:
    """The extent of points [P, >= 2] along the in-plane unit direction u."""
    return float(np.ptp(points[:, :2] @ u))


def span_ratio(f) -> float:
    """The flat grid's span along i over its span along j (its joint centres' extents)."""
    ui, uj = lattice_directions(f)
    return extent(flat_centres(f), ui) / extent(flat_centres(f), uj)


def shrinks(f, points: np.ndarray) -> tuple[float, float]:
    """(s_i, s_j): the last frame's extents of points [F, P, 3] along the lattice over the first frame's."""
    ui, uj = lattice_directions(f)
    return (extent(points[-1], ui) / max(extent(points[0], ui), 1e-9),
            extent(points[-1], uj) / max(extent(points[0], uj), 1e-9))


def roll(f, points: np.ndarray) -> float:
    """s_i - s_j of points [F, P, 3]: < 0 rolled along i, > 0 along j, near 0 not rolled (or closed alike both
    ways)."""
    s_i, s_j = shrinks(f, points)
    return s_i - s_j
