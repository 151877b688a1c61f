"""Consistency checks of an in-memory episode, shared by the writer (before writing) and the validator (after reading).

A problem is a (field, message) pair; the field names the dataset or attribute at fault ("file" and
"schema_version" are used for problems of the file itself).
"""
from __future__ import annotations

import json
from typing import Any

import numpy as np

from data_schema.fields import FIELDS, MESH_DIM_ATTRS, Field, parse_symbol

Problem = tuple[str, str]


class EpisodeError(ValueError):
    """An episode that breaks the schema; `field` names the dataset or attribute at fault."""

    def __init__(self, path: Any, field: str, message: str):
        self.path, self.field, self.message = path, field, message
        super().__init__(f"{path}: {field}: {message}")


# ----------------------------------------------------------------------------------------------- types
def coerce(f: Field, value: Any) -> tuple[Any, str | None]:
    """`value` cast to the declared type of `f`, or (None, why not). Never casts lossily (float -> int, overflow)."""
    if f.is_attr:
        return _coerce_attr(f, value)
    arr = np.asarray(value)
    want = np.dtype(f.dtype)
    if arr.dtype.kind not in ("iu" if want.kind in "iu" else "iuf"):
        return None, f"dtype {arr.dtype} cannot be stored as {want}"
    if arr.ndim != len(f.shape):
        return None, f"has {arr.ndim} axes {list(arr.shape)}; expected {len(f.shape)} axes {f.shape_text}"
    if want.kind in "iu" and arr.size and arr.dtype != want:
        lo, hi = np.iinfo(want).min, np.iinfo(want).max
        if arr.min() < lo or arr.max() > hi:
            return None, f"values [{arr.min()}, {arr.max()}] do not fit in {want}"
    return arr.astype(want, copy=False), None


def _coerce_attr(f: Field, value: Any) -> tuple[Any, str | None]:
    if f.dtype == "str":
        if isinstance(value, bytes):
            value = value.decode("utf-8")
        return (value, None) if isinstance(value, str) else (None, f"is {type(value).__name__}; expected str")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None, f"is {type(value).__name__}; expected {f.pytype.__name__}"
    if f.dtype == "int64":
        if isinstance(value, (float, np.floating)) and not float(value).is_integer():
            return None, f"is {value}; expected an integer"
        value = int(value)
        if not -2**63 <= value < 2**63:
            return None, f"{value} does not fit in int64"
        return value, None
    return float(value), None


# ----------------------------------------------------------------------------------------------- shapes
def resolve_dims(shapes: dict[str, tuple[int, ...]]) -> tuple[dict[str, int], list[Problem]]:
    """Dimension values from the arrays' shapes (first field declaring a symbol wins) and every mismatch."""
    dims: dict[str, int] = {}
    source: dict[str, str] = {}
    problems: list[Problem] = []
    for f in FIELDS:
        if f.is_attr or f.name not in shapes:
            continue
        for axis, (sym, n) in enumerate(zip(f.shape, shapes[f.name])):
            name, offset = parse_symbol(sym)
            if name is None:
                if n != offset:
                    problems.append((f.name, f"axis {axis} has length {n}; expected {offset}"))
                continue
            value = n - offset
            if name not in dims:
                dims[name], source[name] = value, f.name
            elif dims[name] != value:
                problems.append((f.name, f"axis {axis} has length {n}, i.e. {name} = {value}; {source[name]} "
                                         f"gives {name} = {dims[name]} (shape {list(shapes[f.name])})"))
                break
    return dims, problems


# ----------------------------------------------------------------------------------------------- semantics
def episode_problems(ep: Any) -> list[Problem]:
    """Every problem of an episode whose fields already have their declared types (see `coerce`)."""
    shapes = {f.name: getattr(ep, f.name).shape for f in FIELDS if not f.is_attr}
    dims, problems = resolve_dims(shapes)
    for sym, attr in MESH_DIM_ATTRS.items():
        value = getattr(ep, attr)
        if sym in dims and value != dims[sym]:
            problems.append((attr, f"is {value} but the node tables give {sym} = {dims[sym]}"))
        elif value < 3 or value % 2 == 0:
            problems.append((attr, f"is {value}; node counts must be odd and >= 3 (mid planes must exist)"))
    if problems:
        return problems  # the checks below index arrays by these dimensions
    for check in (_finite, _json_attrs, _design, _keys, _block_tables, _cells, _frames, _increments):
        problems += check(ep, dims)
    return problems


def _finite(ep: Any, dims: dict) -> list[Problem]:
    out = []
    for f in FIELDS:
        if not f.is_attr and f.dtype.startswith("float"):
            a = getattr(ep, f.name)
            bad = ~np.isfinite(a)
            if bad.any():
                first = np.argwhere(bad)[0].tolist()
                out.append((f.name, f"{int(bad.sum())} non-finite values, first at index {first}: {a[tuple(first)]}"))
        elif f.is_attr and f.dtype == "float64" and not np.isfinite(getattr(ep, f.name)):
            out.append((f.name, f"is {getattr(ep, f.name)}; expected a finite number"))
    return out


def _json_attrs(ep: Any, dims: dict) -> list[Problem]:
    out = []
    for f in FIELDS:
        if f.is_attr and f.name.endswith("_json"):
            try:
                json.loads(getattr(ep, f.name))
            except ValueError as e:
                out.append((f.name, f"is not valid JSON: {e}"))
    return out


def _in_range(name: str, a: np.ndarray, lo: int, hi: int, what: str) -> list[Problem]:
    """Values of `a` must lie in [lo, hi)."""
    bad = (a < lo) | (a >= hi)
    if not bad.any():
        return []
    first = np.argwhere(bad)[0].tolist()
    return [(name, f"{int(bad.sum())} {what} outside [0, {hi - lo}), first {a[tuple(first)]} at index {first}")]


def _design(ep: Any, dims: dict) -> list[Problem]:
    J = dims["J"]
    out = _in_range("beams", ep.beams, 0, J, "joint ids")
    out += _in_range("beam_kind", ep.beam_kind, 0, 3, "kind codes")
    if not 0 <= ep.fixed_joint < J:
        out.append(("fixed_joint", f"is {ep.fixed_joint}; expected a joint id in [0, {J})"))
    for name in ("beam_width", "thickness"):
        if not getattr(ep, name) > 0:
            out.append((name, f"is {getattr(ep, name)}; expected > 0 mm"))
    if not ep.family:
        out.append(("family", "is empty"))
    return out


def _sorted_unique(name: str, key: np.ndarray) -> list[Problem]:
    """Rows of `key` must be unique and in strictly increasing lexicographic order."""
    if len(key) < 2:
        return []
    uniq, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = uniq[np.argmax(counts > 1)]
        rows = np.where((key == dup).all(axis=1))[0].tolist()
        return [(name, f"duplicate key {dup.tolist()} at rows {rows}")]
    diff = key[1:].astype(np.int64) - key[:-1]
    col = np.argmax(diff != 0, axis=1)  # first column where consecutive rows differ
    step = diff[np.arange(len(diff)), col]
    if (step < 0).any():
        r = int(np.argmax(step < 0))
        return [(name, f"keys are not in lexicographic order: row {r} {key[r].tolist()} comes before row {r + 1} "
                       f"{key[r + 1].tolist()}")]
    return []


def _keys(ep: Any, dims: dict) -> list[Problem]:
    out = _sorted_unique("node_key", ep.node_key) + _sorted_unique("cell_key", ep.cell_key)
    J, B, N, C, nl, nw, nh = (dims[s] for s in ("J", "B", "N", "C", "nl", "nw", "nh"))
    n_expected = J * nw * nw * nh + B * (nl - 2) * nw * nh
    if N != n_expected:
        out.append(("node_key", f"{N} nodes; J = {J} joints of {nw}x{nw}x{nh} and B = {B} beams of "
                                f"{nl - 2}x{nw}x{nh} owned nodes make {n_expected}"))
    c_expected = J * (nw - 1) ** 2 * (nh - 1) + B * (nl - 1) * (nw - 1) * (nh - 1)
    if C != c_expected:
        out.append(("cell_key", f"{C} cells; J = {J} joints and B = {B} beams of this mesh make {c_expected}"))
    return out


def _block_keys(n_blocks: int, dims_ijk: tuple[int, int, int], first_block: int) -> np.ndarray:
    """Expected (block, i, j, k) of every entry of a [n_blocks, L, W, H] block table."""
    grid = np.indices((n_blocks, *dims_ijk))
    grid[0] += first_block
    return np.moveaxis(grid, 0, -1)


def _table_problems(name: str, table: np.ndarray, key: np.ndarray, expected: np.ndarray, count: int,
                    what: str) -> list[Problem]:
    """Ids in `table` within [0, count) and key[table] == expected (compared on the entries where expected >= 0)."""
    out = _in_range(name, table, 0, count, f"{what} ids")
    if out:
        return out
    got = key[table]
    mask = (expected >= 0).all(axis=-1)
    bad = mask & (got != expected).any(axis=-1)
    if bad.any():
        at = tuple(np.argwhere(bad)[0])
        out.append((name, f"entry {list(map(int, at))} is {what} {int(table[at])} with key {got[at].tolist()}; "
                          f"expected key {expected[at].tolist()}"))
    return out


def _block_tables(ep: Any, dims: dict) -> list[Problem]:
    J, B, N, C, nl, nw, nh = (dims[s] for s in ("J", "B", "N", "C", "nl", "nw", "nh"))
    out = _table_problems("joint_nodes", ep.joint_nodes, ep.node_key, _block_keys(J, (nw, nw, nh), 0), N, "node")
    beam_expect = _block_keys(B, (nl, nw, nh), J)
    beam_expect[:, [0, -1]] = -1  # end faces belong to joints: checked below
    out += _table_problems("beam_nodes", ep.beam_nodes, ep.node_key, beam_expect, N, "node")
    if not out:
        for end, face in ((0, 0), (1, -1)):
            owner = ep.node_key[ep.beam_nodes[:, face], 0]  # [B, nw, nh]
            bad = owner != ep.beams[:, end, None, None]
            if bad.any():
                b = int(np.argwhere(bad)[0][0])
                out.append(("beam_nodes", f"beam {b}: face i = {face % nl} has nodes of block "
                                          f"{int(owner[bad][0])}; it must alias joint {int(ep.beams[b, end])}"))
                break
            faces = ep.beam_nodes[:, face].reshape(B, -1)
            if (np.diff(np.sort(faces, axis=1), axis=1) == 0).any():
                out.append(("beam_nodes", f"face i = {face % nl} of a beam repeats a node id"))
        used = np.zeros(N, dtype=bool)
        used[ep.joint_nodes.ravel()] = True
        used[ep.beam_nodes.ravel()] = True
        if not used.all():
            out.append(("node_key", f"{int((~used).sum())} nodes belong to no block table, "
                                    f"first node {int(np.argmin(used))}"))
    out += _table_problems("joint_cells", ep.joint_cells, ep.cell_key,
                           _block_keys(J, (nw - 1, nw - 1, nh - 1), 0), C, "cell")
    out += _table_problems("beam_cells", ep.beam_cells, ep.cell_key,
                           _block_keys(B, (nl - 1, nw - 1, nh - 1), J), C, "cell")
    if not out:
        counts = np.bincount(np.concatenate([ep.joint_cells.ravel(), ep.beam_cells.ravel()]), minlength=C)
        if (counts != 1).any():
            c = int(np.argmax(counts != 1))
            out.append(("cell_key", f"cell {c} appears {counts[c]} times in joint_cells/beam_cells; expected once"))
    return out


def corner_nodes(nodes: np.ndarray) -> np.ndarray:
    """Hex8 corners (bottom quad counter-clockwise, then top) of every cell of a [n, L, W, H] node table."""
    i0, i1 = slice(None, -1), slice(1, None)
    quad = [(i0, i0), (i1, i0), (i1, i1), (i0, i1)]
    corners = [nodes[:, a, b, k] for k in (i0, i1) for a, b in quad]
    return np.stack(corners, axis=-1)  # [n, L-1, W-1, H-1, 8]


def _hex_corner_dets(x: np.ndarray) -> np.ndarray:
    """Jacobian determinants [C, 8] at the corners of hex8 cells with vertex coordinates x [C, 8, 3]."""
    bottom, top = x[:, :4], x[:, 4:]
    up = top - bottom  # [C, 4, 3]
    dets = []
    for quad in (bottom, top):
        e1 = np.roll(quad, -1, axis=1) - quad  # to the next vertex counter-clockwise
        e2 = np.roll(quad, 1, axis=1) - quad  # to the previous one
        dets.append(np.einsum("cvi,cvi->cv", np.cross(e1, e2), up))
    return np.concatenate(dets, axis=1)


def _cells(ep: Any, dims: dict) -> list[Problem]:
    N, C = dims["N"], dims["C"]
    out = _in_range("cell_nodes", ep.cell_nodes, 0, N, "node ids")
    out += _in_range("cell_layer", ep.cell_layer, 0, 2, "layer codes")
    if out:
        return out
    expected = np.empty((C, 8), dtype=np.int64)
    expected[ep.joint_cells.ravel()] = corner_nodes(ep.joint_nodes).reshape(-1, 8)
    expected[ep.beam_cells.ravel()] = corner_nodes(ep.beam_nodes).reshape(-1, 8)
    bad = (np.sort(ep.cell_nodes, axis=1) != np.sort(expected, axis=1)).any(axis=1)
    if bad.any():
        c = int(np.argmax(bad))
        return [("cell_nodes", f"cell {c} (key {ep.cell_key[c].tolist()}) has nodes {ep.cell_nodes[c].tolist()}; "
                               f"its block table gives {sorted(expected[c].tolist())}")]
    dets = _hex_corner_dets(ep.node_xyz0[ep.cell_nodes])
    if (dets <= 0).any():
        c = int(np.argmax((dets <= 0).any(axis=1)))
        return [("cell_nodes", f"cell {c} (key {ep.cell_key[c].tolist()}) is inverted or degenerate in node_xyz0: "
                               f"corner Jacobians {np.round(dets[c], 6).tolist()}; expected all > 0 "
                               "(bottom quad counter-clockwise seen from above, then top quad)")]
    return []


def _strictly_increasing(name: str, a: np.ndarray) -> list[Problem]:
    if len(a) > 1 and not (np.diff(a) > 0).all():
        i = int(np.argmax(np.diff(a) <= 0))
        return [(name, f"not strictly increasing: [{i}] = {a[i]} then [{i + 1}] = {a[i + 1]}")]
    return []


def _frames(ep: Any, dims: dict) -> list[Problem]:
    out = []
    t = ep.t
    if dims["F"] == 0:
        return [("t", "no frames")]
    if t[0] != 0:
        out.append(("t", f"starts at {t[0]}; expected 0"))
    if t[-1] > 1:
        out.append(("t", f"ends at {t[-1]}; expected <= 1"))
    out += _strictly_increasing("t", t)
    ref = ep.node_xyz0.astype(np.float32).astype(np.float64)
    tol = 4 * np.finfo(np.float32).eps * max(1.0, float(np.abs(ep.node_xyz0).max(initial=0.0)))
    dev = np.abs(ep.node_xyz[0].astype(np.float64) - ref)
    if t[0] == 0 and dev.size and dev.max() > tol:
        n = int(np.argmax(dev.max(axis=1)))
        out.append(("node_xyz", f"frame 0 differs from node_xyz0 by {dev.max():.3g} mm at node {n}; "
                                f"frame 0 must be the reference (tolerance {tol:.2g} mm)"))
    qp, qw = ep.quad_points, ep.quad_weights
    if ((qp < 0) | (qp > 1)).any():
        out.append(("quad_points", "coordinates outside the reference cell [0, 1]^3"))
    if abs(qw.sum() - 1.0) > 1e-6:
        out.append(("quad_weights", f"sum to {qw.sum()}; expected 1 (volume of [0, 1]^3)"))
    return out


def _increments(ep: Any, dims: dict) -> list[Problem]:
    a = ep.increment_t
    out = _strictly_increasing("increment_t", a)
    if a.size and (a[0] <= 0 or a[-1] > 1):
        out.append(("increment_t", f"spans [{a[0]}, {a[-1]}]; expected increments within (0, 1]"))
    if (ep.newton_iterations < 0).any():
        out.append(("newton_iterations", "negative iteration counts"))
    return out
