"""Spatial symmetry: the fixed joint at the origin; rotations about z and the mirror (points, vectors, stress)."""
from __future__ import annotations

import numpy as np

from learn.graph import Term

VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # xx, yy, zz, xy, xz, yz


def rotation_z(angle: float) -> np.ndarray:
    """[3, 3] rotation by `angle` radians counter-clockwise about +z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def voigt_to_tensor(s: np.ndarray) -> np.ndarray:
    """[..., 6] Voigt -> [..., 3, 3] symmetric tensor."""
    t = np.zeros(s.shape[:-1] + (3, 3), dtype=s.dtype)
    for n, (i, j) in enumerate(VOIGT):
        t[..., i, j] = t[..., j, i] = s[..., n]
    return t


def tensor_to_voigt(t: np.ndarray) -> np.ndarray:
    return np.stack([t[..., i, j] for i, j in VOIGT], axis=-1)


def rotate_stress(s: np.ndarray, R: np.ndarray) -> np.ndarray:
    """[..., 6] Voigt stresses rotated as R s R^T."""
    t = voigt_to_tensor(s)
    return tensor_to_voigt(np.einsum("ia,...ab,jb->...ij", R, t, R).astype(s.dtype))


def rotate_vectors(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """[..., 3] points or vectors about the origin."""
    return (v @ R.T).astype(v.dtype)


def rotate_term(x: np.ndarray, term: Term, R: np.ndarray) -> np.ndarray:
    """Rotate every point, vector and stress field of a feature array [..., term.size]."""
    out = x.copy()
    for kind in ("point", "vector"):
        for sl in term.slices(kind):
            out[..., sl] = rotate_vectors(x[..., sl], R)
    for sl in term.slices("stress"):
        out[..., sl] = rotate_stress(x[..., sl], R)
    return out


def translate_term(x: np.ndarray, term: Term, origin: np.ndarray) -> np.ndarray:
    """Points of a feature array [..., term.size] relative to `origin` [..., 3]; vectors and stresses unchanged."""
    out = x.copy()
    for sl in term.slices("point"):
        out[..., sl] = x[..., sl] - origin
    return out


def rotation_angles(n: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """n angles evenly spread over a full turn, the first one 0 unless `rng` shifts them all at random."""
    offset = 0.0 if rng is None else rng.uniform(0.0, 2.0 * np.pi / max(n, 1))
    return offset + 2.0 * np.pi * np.arange(n) / max(n, 1)


def term_rotation(term: Term, R: np.ndarray) -> np.ndarray:
    """[size, size] matrix M with rotate_term(x, term, R) = x @ M (the rotation is linear in the features)."""
    return rotate_term(np.eye(term.size), term, R)


def state_matrix(block, term_matrix) -> np.ndarray:
    """[S, S] block-diagonal matrix acting on a block's state (geometry | stress) as x @ M, from a per-term
    matrix function term_matrix(term)."""
    M = np.zeros((block.state_size, block.state_size))
    for sl, term in ((block.geometry_slice, block.geometry), (block.stress_slice, block.stress)):
        M[sl, sl] = term_matrix(term)
    return M


def state_rotation(block, R: np.ndarray) -> np.ndarray:
    """[S, S] matrix rotating a block's state (geometry | stress) as x @ M."""
    return state_matrix(block, lambda term: term_rotation(term, R))


MIRROR = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # reflection x <-> y through the origin
# A relabelling moves every field (and rebuilt point) to the name it has in the relabelled design: name parts
# ("_"-separated) are renamed one by one. Width vectors (half of right edge -> left edge) change sign whenever left
# and right swap.
# The mirrored design is labelled like a sampled one: its lattice indices (i, j) swap, so every beam still runs
# towards +i or +j and the joint axes stay right-handed (i: W -> E side, j: S -> N side). What that relabels:
# joint corners (i, j) -> (j, i), i.e. se <-> nw (sw, ne stay); a beam's left and right (its j axis points to the
# left of a -> b), the width vector minus the reflected one.
MIRROR_RENAME = {"se": "nw", "nw": "se", "left": "right", "right": "left"}
# The lattice half-turn: the same design, nothing moved, labelled from the opposite corner of its lattice,
# (i, j) -> (n_i - 1 - i, n_j - 1 - j), as the factory labels the design turned by half a turn: every beam runs the
# other way (REVERSE_RENAME: start <-> end sections, left <-> right, width negated; EpisodeFeatures.half_turned
# reverses the beams) and every joint's corners turn by half (sw <-> ne, se <-> nw).
REVERSE_RENAME = {"start": "end", "end": "start", "left": "right", "right": "left"}  # a beam running the other way
HALF_TURN_RENAME = {"sw": "ne", "ne": "sw", "se": "nw", "nw": "se"}  # joint corners; every beam reversed
# The lattice quarter turn, (i, j) -> (j, n_i - 1 - i): joint corner (ci, cj) -> (cj, 1 - ci); the beams along i
# become beams along j and run the other way (reversed), the beams along j become beams along i, direction kept.
QUARTER_TURN_RENAME = {"sw": "nw", "se": "sw", "ne": "se", "nw": "ne"}
# The labellings a design is averaged over at answer time (model.rollout_lattice_turns): quarter turns of the lattice
# from its labelling as sampled. k quarter turns reverse no beam (0), the beams along i (1), every beam (2), the beams
# along j (3).
LATTICE_QUARTER_TURNS = {1: (0,), 2: (0, 2), 4: (0, 1, 2, 3)}


def renamed(name: str, rename: dict[str, str]) -> str:
    """`name` with every "_"-separated part renamed."""
    return "_".join(rename.get(part, part) for part in name.split("_"))


def composed(first: dict[str, str], then: dict[str, str]) -> dict[str, str]:
    """The part renaming `first`, then `then`."""
    return {p: then.get(first.get(p, p), first.get(p, p)) for p in {*first, *then}}


def term_relabel(term: Term, R: np.ndarray, rename: dict[str, str]) -> np.ndarray:
    """[size, size] matrix M with relabel(x) = x @ M: every field transformed by R (rotate_term) and moved to the
    field it becomes in the relabelled design; width vectors (half of right edge -> left edge) negated where left and
    right swap."""
    moved = rotate_term(np.eye(term.size), term, R)
    M = np.zeros_like(moved)
    flip = rename.get("left") == "right"
    for name in term.names():
        src, dst = term.slice(name), term.slice(renamed(name, rename))
        M[:, dst] = (-1.0 if flip and name.endswith("_width") else 1.0) * moved[:, src]
    return M


def lattice_rename(quarter_turns: int) -> dict[str, str]:
    """The joint-corner renaming of `quarter_turns` lattice quarter turns (QUARTER_TURN_RENAME applied that often)."""
    rename: dict[str, str] = {}
    for _ in range(quarter_turns % 4):
        rename = composed(rename, QUARTER_TURN_RENAME)
    return rename


def lattice_matrices(block, quarter_turns: int) -> tuple[np.ndarray, np.ndarray]:
    """[2, S, S] and [2, D, D]: the state and bc matrices (x @ M) of `quarter_turns` lattice quarter turns for a block
    that keeps its direction (0) and for one that runs the other way after them (1: REVERSE_RENAME too)."""
    rename = lattice_rename(quarter_turns)
    renames = (rename, composed(REVERSE_RENAME, rename))
    state = [state_matrix(block, lambda term: term_relabel(term, np.eye(3), r)) for r in renames]
    return np.stack(state), np.stack([term_relabel(block.bc, np.eye(3), r) for r in renames])


def relabel_order(names: list[str], rename: dict[str, str]) -> np.ndarray:
    """[n] index: entry p of the relabelled list is entry order[p] of `names` (point or field names): the one that
    `rename` turns into names[p]."""
    source = {renamed(n, rename): k for k, n in enumerate(names)}
    return np.array([source[n] for n in names])


def term_mirror(term: Term) -> np.ndarray:
    """[size, size] matrix M with mirror(x) = x @ M: every field reflected (MIRROR) and relabelled (MIRROR_RENAME);
    an involution (M @ M = I)."""
    return term_relabel(term, MIRROR, MIRROR_RENAME)


def state_mirror(block) -> np.ndarray:
    """[S, S] matrix mirroring a block's state (geometry | stress) as x @ M."""
    return state_matrix(block, term_mirror)
