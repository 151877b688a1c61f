"""Stability at the extremes: one case per parameter pushed to the edge of (or past) its nominal range.

Each case is a design plus conf overrides, solved in-process (serial) at the default mesh unless the case is
about the mesh. A case passes the stability test when it converges with finite output, or fails as a
structured SolveFailure with a reason; it never yields NaN. Cases inside the documented safe ranges must
converge. `scripts/stability_matrix.py` writes the table; `tests/test_extremes.py` (slow) asserts it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from fea_factory.compare import bench_design
from fea_factory.design import Design, lattice_design

CONF = str(Path(__file__).resolve().parent.parent / "conf")


def nominal_sigma(material: str = "pla_80c") -> float:
    """The shipped residual stress of `material` (MPa), read from conf/material: the one source of truth."""
    return float(OmegaConf.load(Path(CONF) / "material" / f"{material}.yaml").residual_stress.sigma)


NOMINAL_SIGMA = nominal_sigma()


def strip(length: float, kind: str = "up", width: float = 7.2) -> Design:
    """One actuator of clear length `length` (mm) between two joints along +x; joint 0 fixed."""
    return Design([[0, 0], [1, 0]], [[0.0, 0.0], [length + width, 0.0]], [[0, 1]], [kind], 0)


def max_jitter_design() -> Design:
    """A 3x3 lattice of 50 mm steps whose joints sit at the sampler's largest jitter (r = 0.2 x 50 mm = 10 mm),
    pushed alternately so that neighbouring corners open and close (most skewed blocks)."""
    xs, ys = np.meshgrid([0.0, 50.0, 100.0], [0.0, 50.0, 100.0], indexing="ij")
    xy = np.stack([xs, ys], -1)
    ang = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 0]]) * np.pi / 4 + np.pi / 8
    xy = xy + 10.0 * np.stack([np.cos(ang), np.sin(ang)], -1) * (np.arange(9).reshape(3, 3) != 4)[..., None]
    return lattice_design(xy, "down", (1, 1), meta={"family": "extreme_jitter"})


@dataclass
class Case:
    name: str
    quantity: str                    # what is pushed
    value: str                       # its value, as printed in the table
    overrides: list[str] = field(default_factory=list)
    design: str = "bench"            # bench | strip_short | strip_long | jitter
    must_converge: bool = True       # inside the documented safe range


DESIGNS = {"bench": bench_design, "strip_short": lambda: strip(10.0), "strip_long": lambda: strip(150.0),
           "jitter": max_jitter_design}

CASES = [
    Case("sigma_0", "residual stress", "0 (gravity only)", ["material.residual_stress.sigma=0.0"]),
    Case("sigma_1x", "residual stress", f"1x ({NOMINAL_SIGMA} MPa)", []),
    Case("sigma_2x", "residual stress", "2x", [f"material.residual_stress.sigma={2 * NOMINAL_SIGMA}"]),
    Case("sigma_3x", "residual stress", "3x", [f"material.residual_stress.sigma={3 * NOMINAL_SIGMA}"]),
    Case("nu_0.45", "bulk/shear", "nu 0.45 (K/mu 9.7)", ["material.poisson=0.45"]),
    Case("nu_0.499", "bulk/shear", "nu 0.499 (K/mu 500)", ["material.poisson=0.499"]),
    Case("nu_0.4999", "bulk/shear", "nu 0.4999 (K/mu 5000)", ["material.poisson=0.4999"]),
    Case("beam_short", "beam length/thickness", "10 mm / 4 mm = 2.5", [], design="strip_short"),
    Case("beam_long", "beam length/thickness", "150 mm / 4 mm = 37.5", [], design="strip_long"),
    Case("jitter_max", "vertex jitter", "r = 0.2 x spacing, all down", [], design="jitter"),
    Case("gravity_10x", "body force", "10x (g = 98.1 m/s^2)", ["scene.g=98100.0"]),
    Case("mesh_coarse", "mesh", "coarse 5/3/3", ["mesh=coarse"]),
    Case("mesh_fine", "mesh", "fine 17/5/5", ["mesh=fine"]),
]


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return hydra_compose(config_name="solve", overrides=["design=unused", "out=unused", *overrides])


def run_case(case: Case, comm=None) -> dict:
    """Solve one case; the row of the stability table (status ok | failed, reason, counts, finiteness)."""
    from mpi4py import MPI

    from fea_factory.solve import solve_design
    from fea_factory.solver import SolveFailure

    design = DESIGNS[case.design]()
    cfg = compose(case.overrides)
    row = {"case": case.name, "quantity": case.quantity, "value": case.value, "must_converge": case.must_converge}
    t0 = time.perf_counter()
    try:
        keyed, frames, stats, _ = solve_design(design, cfg, comm or MPI.COMM_WORLD)
    except SolveFailure as e:
        row.update(status="failed", reason=str(e), cutbacks=None, finite=True)
    else:
        xyz, sig = np.asarray(frames.node_xyz), np.asarray(frames.stress)
        disp = np.linalg.norm(xyz[-1] - xyz[0], axis=1).max()
        row.update(status="ok", reason="", increments=stats["increments"], newton=stats["newton_total"],
                   cutbacks=stats["cutbacks"], finite=bool(np.isfinite(xyz).all() and np.isfinite(sig).all()),
                   max_disp_mm=float(disp), max_disp_rel=float(disp / design.size))
    row["wall_s"] = time.perf_counter() - t0
    return row
