"""Calibrate the printed residual stress: the sigma at which a free actuator bends through a target angle.

    python -m fea_factory.calibrate [target_deg=75] [length=50] [material=pla_80c] [mesh=default]

There is no physical bend measurement in this project yet (the thesis matched printed samples); the default
sigma in conf/material/*.yaml is chosen so that a 50 mm up/down actuator (7.2 x 4 mm) bends through ~75 deg,
the size of transformation the thesis shows. The bend angle is the rotation of the beam's end cross-section
relative to its start (clamped joint side), read from the sections' thickness vectors through the key table. A secant iteration on sigma (bend ~ linear in sigma at small strain) hits the target.
"""
from __future__ import annotations

import json
import logging

import numpy as np

from fea_factory.design import Design

log = logging.getLogger(__name__)


def actuator_design(length: float, kind: str, width: float) -> Design:
    """Two joints along +x joined by one actuator of clear length `length`; joint 0 is fixed."""
    return Design([[0, 0], [1, 0]], [[0.0, 0.0], [length + width, 0.0]], [[0, 1]], [kind], 0)


def bend_angle_deg(mesh, xyz: np.ndarray, beam: int = 0) -> float:
    """Signed rotation (deg, about +y) of the beam's end cross-section relative to its start cross-section.

    A section's orientation is its thickness vector (bottom to top node at mid-width); plane sections stay
    plane in bending, so the angle between the two is the bend, independent of how many nodes the beam has.
    """
    nl, nw, nh = mesh.beam_nodes.shape[1:]
    n0 = xyz[mesh.beam_nodes[beam, 0, nw // 2, nh - 1]] - xyz[mesh.beam_nodes[beam, 0, nw // 2, 0]]
    n1 = xyz[mesh.beam_nodes[beam, -1, nw // 2, nh - 1]] - xyz[mesh.beam_nodes[beam, -1, nw // 2, 0]]
    a0, a1 = np.arctan2(n0[0], n0[2]), np.arctan2(n1[0], n1[2])
    return float(np.degrees(np.angle(np.exp(1j * (a1 - a0)))))


def actuator_bend(cfg, sigma: float, comm=None) -> tuple[float, dict]:
    """Bend angle (deg) of the calibration actuator at residual stress `sigma` (MPa), and the solver stats."""
    from mpi4py import MPI

    from fea_factory.material import make_material
    from fea_factory.mesh import MeshPreset, build_keyed_mesh
    from fea_factory.scene import Scene
    from fea_factory.solver import GridSolver, SolverSettings, prestress_for

    design = actuator_design(float(cfg.length), str(cfg.kind), float(cfg.blocks.beam_width))
    keyed = build_keyed_mesh(design, MeshPreset.from_mapping(cfg.mesh))
    scene = Scene.from_mapping(cfg.scene)
    material = make_material(cfg.material)
    S0 = prestress_for(keyed, design, sigma, str(cfg.material.residual_stress.joint_model))
    solver = GridSolver(design, keyed, material, scene, S0, scene.body_force(float(cfg.material.density)),
                        SolverSettings.from_mapping(cfg.solver), comm or MPI.COMM_WORLD, clamp="top_face")
    frames = solver.run()
    return bend_angle_deg(keyed, frames.node_xyz[-1]), solver.stats


def calibrate(cfg) -> dict:
    """Secant iteration on sigma for |angle| = target_deg; returns the evaluations and the result."""
    target = float(cfg.target_deg)
    s0 = float(cfg.material.residual_stress.sigma)
    evals = []

    def f(s):
        a, st = actuator_bend(cfg, s)
        evals.append({"sigma_MPa": s, "angle_deg": a, "newton": st["newton_total"]})
        log.info("sigma = %.5f MPa -> bend %.2f deg (%d Newton its)", s, a, st["newton_total"])
        return abs(a) - target

    x0, f0 = s0, f(s0)
    x1 = s0 * (target / (f0 + target)) if f0 + target > 0 else 2 * s0
    while len(evals) < int(cfg.max_evaluations):
        f1 = f(x1)
        if abs(f1) <= float(cfg.tolerance_deg):
            break
        x0, f0, x1 = x1, f1, x1 - f1 * (x1 - x0) / (f1 - f0)
        if x1 <= 0:
            raise RuntimeError(f"calibration diverged (sigma {x1}); evaluations: {evals}")
    best = min(evals, key=lambda e: abs(abs(e["angle_deg"]) - target))
    return {"target_deg": target, "length_mm": float(cfg.length), "kind": str(cfg.kind),
            "sigma_MPa": best["sigma_MPa"], "angle_deg": best["angle_deg"], "evaluations": evals}


def main() -> None:
    import hydra

    @hydra.main(config_path="../conf", config_name="calibrate", version_base=None)
    def run(cfg) -> None:
        result = calibrate(cfg)
        print(json.dumps(result, indent=1))
        print(f"set material.residual_stress.sigma: {result['sigma_MPa']:.4g}  "
              f"# {result['angle_deg']:.1f} deg for a {result['length_mm']:g} mm {result['kind']} actuator")

    run()


if __name__ == "__main__":
    main()
