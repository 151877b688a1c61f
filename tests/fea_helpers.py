"""Shared builders for the solver verification tests: single-beam designs and a small solve driver."""
from __future__ import annotations

import numpy as np

from fea_factory.design import Design
from fea_factory.material import ReducedPolynomial, bulk_modulus
from fea_factory.mesh import MeshPreset, build_keyed_mesh
from fea_factory.scene import Scene
from fea_factory.solver import GridSolver, SolverSettings

JOINT = 7.2  # mm, joint block length = beam width


def strip_design(length: float, kind: str = "passive") -> Design:
    """One beam of clear length `length` (mm) between two joints along +x; joint 0 is the fixed one."""
    return Design([[0, 0], [1, 0]], [[0.0, 0.0], [length + JOINT, 0.0]], [[0, 1]], [kind], 0)


def neo_hookean(E: float = 1.2, nu: float = 0.3) -> ReducedPolynomial:
    mu = E / (2 * (1 + nu))
    return ReducedPolynomial((mu / 2,), bulk_modulus(mu, nu), "neo_hookean")


def youngs(material: ReducedPolynomial) -> float:
    mu, K = material.mu0, material.kappa
    return 9 * K * mu / (3 * K + mu)


def solve(design: Design, preset: MeshPreset, material, S0_cells, scene: Scene, body_force, clamp="block",
          settings: SolverSettings | None = None, comm=None):
    from mpi4py import MPI

    mesh = build_keyed_mesh(design, preset)
    if callable(S0_cells):
        S0_cells = S0_cells(mesh)
    settings = settings or SolverSettings(increments=10, save_every=10)
    solver = GridSolver(design, mesh, material, scene, S0_cells, body_force, settings, comm or MPI.COMM_WORLD,
                        clamp=clamp)
    frames = solver.run()
    return mesh, frames, solver


def beam_midline(mesh, xyz: np.ndarray, beam: int = 0) -> np.ndarray:
    """Deformed mid-width, mid-height line of a beam [nl, 3] through its key table."""
    nl, nw, nh = mesh.beam_nodes.shape[1:]
    return xyz[mesh.beam_nodes[beam, :, nw // 2, nh // 2]]


def circle_fit(x: np.ndarray, z: np.ndarray) -> tuple[float, float]:
    """Least-squares circle through points (Kasa fit): curvature and max radial residual (mm)."""
    A = np.stack([x, z, np.ones_like(x)], axis=1)
    rhs = x**2 + z**2
    (a, b, c), *_ = np.linalg.lstsq(A, rhs, rcond=None)
    xc, zc = a / 2, b / 2
    R = np.sqrt(c + xc**2 + zc**2)
    resid = np.abs(np.hypot(x - xc, z - zc) - R).max()
    return 1.0 / R, float(resid)


def bottom_layer_prestress(sigma: float):
    """S0 = sigma e_x (x) e_x in the beam's bottom layer only (the Timoshenko bilayer with one active layer)."""
    def build(mesh):
        S0 = np.zeros((mesh.n_cells, 3, 3))
        beam_cells = mesh.cell_key[:, 0] >= 2
        S0[beam_cells & (mesh.cell_layer == 0), 0, 0] = sigma
        return S0
    return build
