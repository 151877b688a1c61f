"""Block footprints of a design: joint quadrilaterals and beam quadrilaterals in the print plane.

Every joint has four arms, one per lattice direction E (+i), N (+j), W (-i), S (-j), counter-clockwise.
An arm points at the neighbouring joint where a beam exists; a missing arm is the opposite of the arm on
the same lattice axis, or (no beam on that axis at all) the other axis' arm turned by 90 degrees.
Joint corner k lies between arm k and arm k+1 (mod 4), where both arms' beam edges (offset by half the
beam width) meet, so every joint side faces one arm and is shared exactly with the beam on that arm.

Local block frames (right-handed with z up, as the hexahedra are built):
- joint: i from the W side to the E side, j from the S side to the N side;
- beam from joint a to joint b: i along the axis from a to b, j across it to the left, k up.
Units: mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fea_factory.design import Design, DesignError, DesignLimits

ARM_STEPS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # E, N, W, S in lattice steps
ARM_NAMES = ("E", "N", "W", "S")
# joint corner k (between arm k and arm k+1) in joint index coordinates (0 = low side, 1 = high side):
# NE, NW, SW, SE
CORNER_UNIT_IJ = np.array([[1, 1], [0, 1], [0, 0], [1, 0]])


@dataclass
class BlockGeometry:
    """Footprints of every block of a design.

    joint_corners: [J, 4, 2] corner k of joint n between its arms k and k+1 (NE, NW, SW, SE), mm
    joint_arms:    [J, 4, 2] unit arm directions E, N, W, S
    arm_beam:      [J, 4] beam on each arm, -1 where the arm has no beam
    beam_arm:      [B, 2] arm index (0..3) of the beam at its start joint a and at its end joint b
    beam_corners:  [B, 4, 2] start-right, start-left, end-right, end-left (right/left of the a -> b axis)
    """

    joint_corners: np.ndarray
    joint_arms: np.ndarray
    arm_beam: np.ndarray
    beam_arm: np.ndarray
    beam_corners: np.ndarray


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rot90(v: np.ndarray) -> np.ndarray:
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


def _arm_of(step: np.ndarray) -> int:
    return int(np.where((ARM_STEPS == step).all(axis=1))[0][0])


def joint_arms(design: Design) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arm directions [J, 4, 2], the beam on each arm [J, 4] (-1: none) and each beam's arms [B, 2]."""
    J = design.n_joints
    arm_beam = -np.ones((J, 4), dtype=np.int64)
    beam_arm = np.zeros((design.n_beams, 2), dtype=np.int64)
    arms = np.full((J, 4, 2), np.nan)
    for b, (a, c) in enumerate(design.beams.tolist()):
        step = design.joint_ij[c] - design.joint_ij[a]
        ka, kc = _arm_of(step), _arm_of(-step)
        arm_beam[a, ka], arm_beam[c, kc] = b, b
        beam_arm[b] = ka, kc
        axis = _unit(design.joint_xy[c] - design.joint_xy[a])
        arms[a, ka], arms[c, kc] = axis, -axis
    for n in range(J):
        for k in range(4):  # a missing arm mirrors its opposite on the same lattice axis
            if np.isnan(arms[n, k, 0]) and not np.isnan(arms[n, (k + 2) % 4, 0]):
                arms[n, k] = -arms[n, (k + 2) % 4]
        for k in range(4):  # no beam on this lattice axis at all: turn the other axis by 90 degrees
            if np.isnan(arms[n, k, 0]):
                arms[n, k] = _rot90(arms[n, (k - 1) % 4])
    return arms, arm_beam, beam_arm


def _edge_intersection(p: np.ndarray, d1: np.ndarray, o1: float, d2: np.ndarray, o2: float) -> np.ndarray:
    """Point x with (x - p) . n1 = o1 and (x - p) . n2 = o2, n = d turned +90 degrees (left normal)."""
    A = np.stack([_rot90(d1), _rot90(d2)])
    det = np.linalg.det(A)
    if abs(det) < 1e-9:
        return p + _rot90(d1) * o1  # parallel arms: the edge passes straight through
    return p + np.linalg.solve(A, np.array([o1, o2]))


def block_geometry(design: Design) -> BlockGeometry:
    arms, arm_beam, beam_arm = joint_arms(design)
    half = 0.5 * design.beam_width
    corners = np.zeros((design.n_joints, 4, 2))
    for n in range(design.n_joints):
        p = design.joint_xy[n]
        for k in range(4):
            # left edge of arm k meets the right edge of arm k+1
            corners[n, k] = _edge_intersection(p, arms[n, k], half, arms[n, (k + 1) % 4], -half)
    beam_corners = np.zeros((design.n_beams, 4, 2))
    for b, (a, c) in enumerate(design.beams.tolist()):
        ka, kc = beam_arm[b]
        beam_corners[b, 0] = corners[a, (ka - 1) % 4]  # start right
        beam_corners[b, 1] = corners[a, ka]  # start left
        beam_corners[b, 2] = corners[c, kc]  # end right = left of the arm at b, seen from b
        beam_corners[b, 3] = corners[c, (kc - 1) % 4]  # end left
    return BlockGeometry(corners, arms, arm_beam, beam_arm, beam_corners)


def joint_quad(corners: np.ndarray) -> np.ndarray:
    """Joint corners in counter-clockwise order SW, SE, NE, NW (index coords (0,0), (1,0), (1,1), (0,1))."""
    return corners[[2, 3, 0, 1]]


def beam_quad(corners: np.ndarray) -> np.ndarray:
    """Beam corners in counter-clockwise order start-right, end-right, end-left, start-left."""
    return corners[[0, 2, 3, 1]]


def quad_corner_angles(q: np.ndarray) -> np.ndarray:
    """Interior angles (deg) of a counter-clockwise quad [4, 2]; negative cross products give > 180."""
    out = np.zeros(4)
    for k in range(4):
        u = q[(k + 1) % 4] - q[k]
        v = q[(k - 1) % 4] - q[k]
        cross = u[0] * v[1] - u[1] * v[0]
        ang = np.degrees(np.arctan2(abs(cross), u @ v))
        out[k] = ang if cross > 0 else 360.0 - ang
    return out


def _convex_overlap(p: np.ndarray, q: np.ndarray, tol: float) -> bool:
    """Separating-axis test of two convex polygons; touching (overlap depth <= tol) is not an overlap."""
    for poly in (p, q):
        for k in range(len(poly)):
            n = _rot90(poly[(k + 1) % len(poly)] - poly[k])
            n = n / np.linalg.norm(n)
            a, b = p @ n, q @ n
            if a.max() <= b.min() + tol or b.max() <= a.min() + tol:
                return False  # a separating axis exists
    return True


def check_blocks(design: Design, g: BlockGeometry, limits: DesignLimits) -> None:
    """Corner angles, clear beam lengths, overlaps and the printable area; DesignError on the first problem."""
    lo, hi = limits.min_joint_angle, 180.0 - limits.min_joint_angle
    for n in range(design.n_joints):
        ang = quad_corner_angles(joint_quad(g.joint_corners[n]))
        if ang.min() < lo or ang.max() > hi:
            raise DesignError(
                f"joint {n}: corner angles {np.round(ang, 1).tolist()} deg; each must lie in [{lo}, {hi}] deg "
                "for a valid hexahedral block (the beams meeting there are too oblique)")
    for b in range(design.n_beams):
        q = beam_quad(g.beam_corners[b])
        ang = quad_corner_angles(q)
        if ang.min() < lo or ang.max() > hi:
            raise DesignError(f"beam {b}: corner angles {np.round(ang, 1).tolist()} deg; each must lie in "
                              f"[{lo}, {hi}] deg")
        start = 0.5 * (g.beam_corners[b, 0] + g.beam_corners[b, 1])
        end = 0.5 * (g.beam_corners[b, 2] + g.beam_corners[b, 3])
        clear = float(np.linalg.norm(end - start))
        side = min(np.linalg.norm(q[1] - q[0]), np.linalg.norm(q[2] - q[3]))
        if clear < limits.min_beam_length or side < limits.min_beam_length:
            a, c = design.beams[b]
            raise DesignError(
                f"beam {b} (joints {a}-{c}): clear length {min(clear, side):.2f} mm between its joint blocks is "
                f"below the allowed minimum {limits.min_beam_length} mm")
        longest = max(clear, np.linalg.norm(q[1] - q[0]), np.linalg.norm(q[2] - q[3]))
        if longest > limits.max_beam_length:
            a, c = design.beams[b]
            raise DesignError(
                f"beam {b} (joints {a}-{c}): clear length {longest:.2f} mm is above the allowed maximum "
                f"{limits.max_beam_length} mm (the longest beam the stability matrix tested)")
    polys = [("joint", n, joint_quad(g.joint_corners[n])) for n in range(design.n_joints)]
    polys += [("beam", b, beam_quad(g.beam_corners[b])) for b in range(design.n_beams)]
    incident = {("beam", b): set(design.beams[b].tolist()) for b in range(design.n_beams)}
    tol = 1e-6 * max(design.size, 1.0)
    for x in range(len(polys)):
        for y in range(x + 1, len(polys)):
            (kx, ix, px), (ky, iy, py) = polys[x], polys[y]
            if _adjacent(kx, ix, ky, iy, design, incident):
                continue
            if _convex_overlap(px, py, tol):
                raise DesignError(f"{kx} {ix} and {ky} {iy} overlap (crossing or overlapping blocks)")
    all_pts = np.concatenate([p for _, _, p in polys])
    ext = all_pts.max(axis=0) - all_pts.min(axis=0)
    if ext[0] > limits.printable_width or ext[1] > limits.printable_depth:
        raise DesignError(
            f"design footprint {ext[0]:.1f} x {ext[1]:.1f} mm exceeds the printable area "
            f"{limits.printable_width} x {limits.printable_depth} mm")


def _adjacent(kx: str, ix: int, ky: str, iy: int, design: Design, incident: dict) -> bool:
    """Blocks that legitimately share a face or a corner: a joint and its beams, two beams at one joint."""
    if kx == "joint" and ky == "joint":
        return False
    if kx == "joint":
        return ix in incident[(ky, iy)]
    if ky == "joint":
        return iy in incident[(kx, ix)]
    return bool(incident[(kx, ix)] & incident[(ky, iy)])
