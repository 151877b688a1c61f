"""XDMF views for ParaView: an episode's frames (or any other hex-mesh time series) as one temporal collection.

    python -m data_schema.view data/episodes/episode_00000.h5     # -> episode_00000.view.xdmf + episode_00000.view.h5
    python -m data_schema.view data/episodes/ --out views/         # every episode below a directory

The reference mesh is written once; each frame carries the displacement from it (ParaView: Warp By Vector, scale 1)
and, per cell, the Cauchy stress averaged over the cell's quadrature points (6 components, Voigt order
xx, yy, zz, xy, xz, yz, MPa) and its von Mises value, beside the static tags (block, layer, print angle).
Units as in the episode: mm, MPa. The pair (.xdmf, .h5) is written under temporary names and renamed, data first.
"""
from __future__ import annotations

import argparse
import contextlib
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from data_schema.episode import EPISODE_SUFFIX, read_episode

VIEW_SUFFIX = ".view.xdmf"  # its data goes to .view.h5 (meshio names it after the .xdmf): never an episode's name


def data_path(out: Path) -> Path:
    """The HDF5 file meshio writes beside an .xdmf (same stem)."""
    return out.with_suffix(".h5")


def _refuse_episode(path: Path, out: Path) -> None:
    import h5py

    from data_schema.fields import SCHEMA_VERSION_ATTR

    if path.exists():
        with h5py.File(path, "r") as h5:
            if SCHEMA_VERSION_ATTR in h5.attrs:
                raise ValueError(f"out={str(out)!r}: its data file {path} is an episode; choose another name "
                                 f"(default: <episode>{VIEW_SUFFIX})")


def von_mises(voigt: np.ndarray) -> np.ndarray:
    """sigma_vM = sqrt(((s11 - s22)^2 + (s22 - s33)^2 + (s33 - s11)^2) / 2 + 3 (s12^2 + s13^2 + s23^2)),
    from stresses [..., 6] in Voigt order xx, yy, zz, xy, xz, yz."""
    s11, s22, s33, s12, s13, s23 = np.moveaxis(np.asarray(voigt, dtype=np.float64), -1, 0)
    return np.sqrt(0.5 * ((s11 - s22) ** 2 + (s22 - s33) ** 2 + (s33 - s11) ** 2) + 3 * (s12**2 + s13**2 + s23**2))


def write_series(out: str | Path, points: np.ndarray, hexahedra: np.ndarray, t: np.ndarray,
                 point_data: dict[str, np.ndarray] | None = None, cell_data: dict[str, np.ndarray] | None = None,
                 static_cell_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write `out` (.xdmf) and its HDF5 data: points [N, 3], hex8 cells [C, 8] (VTK order), times t [F];
    point_data / cell_data {name: [F, N or C, ...]} per frame; static_cell_data {name: [C, ...]} repeated in
    every frame (XDMF time series carry data per step only). Atomic: a reader sees the old pair or the new one."""
    import meshio

    out = Path(out).absolute()
    if out.suffix != ".xdmf":
        raise ValueError(f"out={str(out)!r}: must end in .xdmf")
    _refuse_episode(data_path(out), out)
    point_data, cell_data, static_cell_data = point_data or {}, cell_data or {}, static_cell_data or {}
    F, N, C = len(t), len(points), len(hexahedra)
    for name, v in point_data.items():
        if v.shape[:2] != (F, N):
            raise ValueError(f"point_data[{name!r}]: shape {v.shape}; expected ({F}, {N}, ...)")
    for name, v in cell_data.items():
        if v.shape[:2] != (F, C):
            raise ValueError(f"cell_data[{name!r}]: shape {v.shape}; expected ({F}, {C}, ...)")
    for name, v in static_cell_data.items():
        if len(v) != C:
            raise ValueError(f"static_cell_data[{name!r}]: {len(v)} values; expected {C}")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".view_", dir=out.parent))
    try:
        # meshio 5.0 opens its HDF5 file (<stem>.h5) relative to the working directory, not beside the .xdmf
        with contextlib.chdir(tmp), meshio.xdmf.TimeSeriesWriter(tmp / out.name) as writer:
            writer.write_points_cells(np.asarray(points, dtype=np.float64), [("hexahedron", np.asarray(hexahedra))])
            for k in range(F):
                writer.write_data(float(t[k]), point_data={n: v[k] for n, v in point_data.items()},
                                  cell_data={**{n: [v[k]] for n, v in cell_data.items()},
                                             **{n: [v] for n, v in static_cell_data.items()}})
        (tmp / data_path(out).name).replace(data_path(out))  # the data before the xdmf that points at it
        (tmp / out.name).replace(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def view_path(episode: Path, directory: Path | None = None) -> Path:
    """<episode stem>.view.xdmf beside the episode or in `directory`."""
    return (directory or episode.parent) / (episode.name.removesuffix(EPISODE_SUFFIX) + VIEW_SUFFIX)


def write_episode_view(episode: str | Path, out: str | Path | None = None) -> Path:
    """The XDMF view of one episode file (see the module doc); out defaults to <episode>.view.xdmf beside it."""
    episode = Path(episode)
    ep = read_episode(episode)
    out = Path(out) if out is not None else view_path(episode)
    xyz0 = np.asarray(ep.node_xyz0, dtype=np.float64)
    stress = np.asarray(ep.stress, dtype=np.float64)  # [F, C, Q, 6]
    w = np.asarray(ep.quad_weights, dtype=np.float64)
    cell_stress = np.einsum("fcqs,q->fcs", stress, w / w.sum())  # quadrature mean over the reference cell
    return write_series(
        out, xyz0, ep.cell_nodes, np.asarray(ep.t),
        point_data={"displacement": np.asarray(ep.node_xyz, dtype=np.float64) - xyz0},
        cell_data={"stress": cell_stress, "von_mises": von_mises(cell_stress)},
        static_cell_data={"block": ep.cell_key[:, 0].astype(np.int32), "layer": ep.cell_layer.astype(np.int32),
                          "print_angle": ep.cell_print_angle.astype(np.float32)})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m data_schema.view", description=__doc__.splitlines()[0])
    parser.add_argument("path", help=f"an episode ({EPISODE_SUFFIX}) or a directory searched for episodes")
    parser.add_argument("--out", help="an .xdmf file (one episode) or a directory (default: beside each episode)")
    args = parser.parse_args(argv)
    src = Path(args.path)
    episodes = sorted(src.rglob(f"*{EPISODE_SUFFIX}")) if src.is_dir() else [src]
    episodes = [e for e in episodes if not e.name.endswith(".view.h5")]  # views' own data files
    if not episodes:
        print(f"no {EPISODE_SUFFIX} episodes under {src}", file=sys.stderr)
        return 2
    if args.out and len(episodes) > 1 and Path(args.out).suffix == ".xdmf":
        print(f"--out {args.out}: give a directory for {len(episodes)} episodes", file=sys.stderr)
        return 2
    for e in episodes:
        out = None
        if args.out:
            o = Path(args.out)
            out = o if o.suffix == ".xdmf" else view_path(e, o)
        try:
            print(write_episode_view(e, out))
        except ValueError as err:
            print(f"data_schema.view: {e}: {err}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
