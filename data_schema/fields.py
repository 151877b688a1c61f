"""The episode layout, declared once: every dataset and attribute of an episode file with its shape, dtype and units.

Shapes are tuples of dimension symbols resolved from the data when a file is written, read or validated:
J joints, B beams, N nodes, C cells, F frames, Q quadrature points per cell, K load increments taken,
nl / nw / nh nodes along a block's length / width / height ("nw-1": cells along the width).
A field with shape None is a scalar HDF5 attribute of its group.

    python -m data_schema.fields --markdown   # the layout as a Markdown table (pasted into README.md)
"""
from __future__ import annotations

import argparse
import re
from dataclasses import dataclass

import numpy as np

SCHEMA_VERSION = "morphsim.episode/1"
SCHEMA_VERSION_ATTR = "schema_version"  # root attribute holding SCHEMA_VERSION

BEAM_KINDS = ("up", "down", "passive")  # beam_kind code -> name
LAYERS = ("bottom", "top")  # cell_layer code -> name
VOIGT = ("xx", "yy", "zz", "xy", "xz", "yz")  # order of the last axis of stress
DIMS = ("J", "B", "N", "C", "F", "Q", "K", "nl", "nw", "nh")
MESH_DIM_ATTRS = {"nl": "nodes_length", "nw": "nodes_width", "nh": "nodes_height"}  # dims echoed as /mesh attrs

_SYMBOL = re.compile(r"^(?P<name>[A-Za-z]+)(?P<offset>[+-]\d+)?$")


@dataclass(frozen=True)
class Field:
    """One dataset (shape given) or scalar attribute (shape None) of an episode file."""

    name: str  # also the Episode attribute name; unique across groups
    group: str  # HDF5 group under the root
    shape: tuple[str | int, ...] | None  # dimension symbols ("F", "N", 3), "nw-1"; None = attribute
    dtype: str  # numpy dtype name; "str" for text attributes
    units: str  # "mm", "MPa", "deg", "1" (dimensionless) or "" (ids, codes, text)
    per_frame: bool  # first axis is the frame axis F (stored chunked one frame per chunk)
    description: str

    @property
    def is_attr(self) -> bool:
        return self.shape is None

    @property
    def path(self) -> str:
        """HDF5 path of the dataset, or of the group holding the attribute."""
        return f"/{self.group}/{self.name}" if not self.is_attr else f"/{self.group}"

    @property
    def pytype(self) -> type:
        """Python type of the Episode attribute."""
        if not self.is_attr:
            return np.ndarray
        return {"str": str, "int64": int, "float64": float}[self.dtype]

    @property
    def shape_text(self) -> str:
        return "attr" if self.is_attr else "[" + ", ".join(map(str, self.shape)) + "]"


def parse_symbol(sym: str | int) -> tuple[str | None, int]:
    """("nw-1") -> ("nw", -1); ("F") -> ("F", 0); (3) -> (None, 3)."""
    if isinstance(sym, int):
        return None, sym
    m = _SYMBOL.match(sym)
    if m is None or m["name"] not in DIMS:
        raise ValueError(f"bad dimension symbol {sym!r}; expected one of {DIMS}, optionally with +/-offset")
    return m["name"], int(m["offset"] or 0)


def _f(name, group, shape, dtype, units, description, per_frame=False) -> Field:
    return Field(name, group, shape, dtype, units, per_frame, description)


FIELDS: tuple[Field, ...] = (
    # ---------------------------------------------------------------- /design
    _f("joint_ij", "design", ("J", 2), "int64", "", "lattice index (i, j) of each joint"),
    _f("joint_xy", "design", ("J", 2), "float64", "mm", "joint centre in the print plane"),
    _f("beams", "design", ("B", 2), "int64", "", "joint pair (a, b) of each beam; the beam axis runs from a to b"),
    _f("beam_kind", "design", ("B",), "int8", "", "0 = up, 1 = down, 2 = passive (BEAM_KINDS)"),
    _f("fixed_joint", "design", None, "int64", "", "joint glued to the support by its top face"),
    _f("beam_width", "design", None, "float64", "mm", "beam width (and joint block side)"),
    _f("thickness", "design", None, "float64", "mm", "print thickness of every block"),
    _f("family", "design", None, "str", "", 'design family, e.g. "random", "regular"'),
    _f("design_json", "design", None, "str", "", "the full fea_factory design JSON, sampler meta included"),
    # ---------------------------------------------------------------- /mesh
    _f("node_key", "mesh", ("N", 4), "int32", "",
       "(block, i, j, k) of the block owning the node; a joint/beam interface node is owned by the joint"),
    _f("node_xyz0", "mesh", ("N", 3), "float64", "mm", "reference node coordinates"),
    _f("cell_key", "mesh", ("C", 4), "int32", "", "(block, i, j, k) of the cell"),
    _f("cell_nodes", "mesh", ("C", 8), "int64", "",
       "node ids, hex8 in gmsh/VTK order (bottom quad counter-clockwise, then top quad)"),
    _f("cell_layer", "mesh", ("C",), "int8", "", "0 = bottom half, 1 = top half (LAYERS)"),
    _f("cell_print_angle", "mesh", ("C",), "float32", "deg",
       "print direction of the cell's layer, counter-clockwise from +x"),
    _f("joint_nodes", "mesh", ("J", "nw", "nw", "nh"), "int64", "",
       "node id of joint block node (i, j, k): i W->E, j S->N, k up"),
    _f("beam_nodes", "mesh", ("B", "nl", "nw", "nh"), "int64", "",
       "node id of beam block node (i, j, k): i along a->b, j across to the left, k up; "
       "faces i = 0 and i = nl-1 alias joint nodes"),
    _f("joint_cells", "mesh", ("J", "nw-1", "nw-1", "nh-1"), "int64", "", "cell id of joint block cell (i, j, k)"),
    _f("beam_cells", "mesh", ("B", "nl-1", "nw-1", "nh-1"), "int64", "", "cell id of beam block cell (i, j, k)"),
    _f("nodes_length", "mesh", None, "int64", "", "nl, nodes along a beam (odd)"),
    _f("nodes_width", "mesh", None, "int64", "", "nw, nodes across a block (odd)"),
    _f("nodes_height", "mesh", None, "int64", "", "nh, nodes through the thickness (odd)"),
    _f("preset", "mesh", None, "str", "", 'mesh preset name, e.g. "coarse"'),
    # ---------------------------------------------------------------- /frames
    _f("t", "frames", ("F",), "float64", "1", "pseudo-time in [0, 1], strictly increasing, t[0] = 0",
       per_frame=True),
    _f("node_xyz", "frames", ("F", "N", 3), "float32", "mm", "node positions per frame (frame 0 = reference)",
       per_frame=True),
    _f("stress", "frames", ("F", "C", "Q", 6), "float32", "MPa",
       "Cauchy stress at quadrature points, Voigt order xx, yy, zz, xy, xz, yz", per_frame=True),
    _f("quad_points", "frames", ("Q", 3), "float64", "1",
       "reference-cell coordinates in [0, 1]^3 (same hex8 vertex order as cell_nodes)"),
    _f("quad_weights", "frames", ("Q",), "float64", "1", "quadrature weights (sum 1, the reference-cell volume)"),
    # ---------------------------------------------------------------- /provenance
    _f("config_yaml", "provenance", None, "str", "", "full resolved Hydra config"),
    _f("seed", "provenance", None, "int64", "", "random seed of the episode"),
    _f("git_rev", "provenance", None, "str", "", "git revision of the code that wrote the episode"),
    _f("versions_json", "provenance", None, "str", "", "versions of dolfinx, gmsh, petsc, numpy, h5py, python"),
    _f("mpi_size", "provenance", None, "int64", "", "MPI ranks of the solve"),
    _f("solver_stats_json", "provenance", None, "str", "",
       "newton iterations, cutbacks, increments taken, wall times mesh/jit/solve/total in s, "
       "load_per_cpu (1-min load average per CPU around the solve: above ~1, the wall times are inflated)"),
    _f("scene_terms_json", "provenance", None, "str", "", "which physics terms were active"),
    _f("increment_t", "provenance", ("K",), "float64", "1", "pseudo-times of the load increments actually taken"),
    _f("newton_iterations", "provenance", ("K",), "int32", "", "Newton iterations of each increment"),
)

FIELD_BY_NAME: dict[str, Field] = {f.name: f for f in FIELDS}
GROUPS: tuple[str, ...] = tuple(dict.fromkeys(f.group for f in FIELDS))


def _check_declaration() -> None:
    assert len(FIELD_BY_NAME) == len(FIELDS), "field names must be unique across groups"
    for f in FIELDS:
        if f.shape is not None:
            for sym in f.shape:
                parse_symbol(sym)
            np.dtype(f.dtype)
        assert f.per_frame == (f.shape is not None and f.shape[0] == "F"), f.name


_check_declaration()


def markdown_table() -> str:
    """The layout as a Markdown table, one row per field, in declaration order."""
    rows = [
        "| group | field | shape | dtype | units | per frame | description |",
        "|---|---|---|---|---|---|---|",
        f"| / | `{SCHEMA_VERSION_ATTR}` | attr | str |  |  | `{SCHEMA_VERSION}` (format name and version) |",
    ]
    for f in FIELDS:
        rows.append(f"| /{f.group} | `{f.name}` | {f.shape_text} | {f.dtype} | {f.units} | "
                    f"{'yes' if f.per_frame else ''} | {f.description} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m data_schema.fields", description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true", help="print the layout as a Markdown table")
    args = parser.parse_args(argv)
    if args.markdown:
        print(markdown_table())
    else:
        for f in FIELDS:
            print(f"{f.path:<14} {f.name:<18} {f.shape_text:<26} {f.dtype:<8} {f.units}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
