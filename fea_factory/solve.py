"""Solve one design into one episode file.

CLI (serial or under MPI):
    python -m fea_factory.solve design=FILE out=FILE.h5 [mesh=coarse] [scene=dry] [material=yeoh] ...
    mpirun -n 2 python -m fea_factory.solve design=FILE out=FILE.h5
    python -m fea_factory.solve design=FILE out=FILE.h5 solver.tolerance=1%   (cheapest measured setting, see
                                                                            fea_factory.tradeoff)
A diverged solve prints a JSON failure record, exits with status 3 and writes nothing.
"""
from __future__ import annotations

import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from fea_factory.clearance import clearance
from fea_factory.design import Design, DesignLimits, validate
from fea_factory.material import make_material
from fea_factory.mesh import MeshPreset, build_keyed_mesh
from fea_factory.residual_stress import check_residual_stress
from fea_factory.scene import Scene
from fea_factory.solver import GridSolver, SolveFailure, SolverSettings, prestress_for
from fea_factory.tradeoff import TradeoffError, apply_tolerance

EXIT_DIVERGED = 3
EXIT_CONTACT = 4  # blocks sharing no joint came closer than solver.min_clearance_mm: refused, not data
KIND_CODES = {"up": 0, "down": 1, "passive": 2}


def git_revision() -> str:
    try:
        root = Path(__file__).resolve().parent.parent
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True, timeout=5)
        return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "") if rev.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_versions() -> dict:
    import dolfinx
    import gmsh
    import h5py
    from petsc4py import PETSc

    return {"dolfinx": dolfinx.__version__, "gmsh": gmsh.__version__,
            "petsc": ".".join(map(str, PETSc.Sys.getVersion())), "numpy": np.__version__,
            "h5py": h5py.__version__, "python": platform.python_version()}


def machine_load(load_before: float) -> float:
    """The 1-minute load average per CPU, the larger of before and after a solve: ~1 when every core ran one job
    (make dataset JOBS=2 on 2 cores), more when other work shared them, and then the wall times above are inflated
    (a speed-up against them overstated: session 59's held-out episodes, generated beside tests and probes)."""
    return round(max(load_before, os.getloadavg()[0]) / (os.cpu_count() or 1), 2)


def solve_design(design: Design, cfg, comm, progress=None):
    """Mesh and solve a validated design with the conf groups in cfg; returns (mesh, frames, stats, scene)."""
    validate(design, DesignLimits.from_mapping(cfg.blocks.limits))
    t0 = time.perf_counter()
    preset = MeshPreset.from_mapping(cfg.mesh)
    keyed = build_keyed_mesh(design, preset)
    t_keyed = time.perf_counter() - t0
    material = make_material(cfg.material)
    scene = Scene.from_mapping(cfg.scene)
    settings = SolverSettings.from_mapping(cfg.solver)
    rs = cfg.material.residual_stress
    S0 = prestress_for(keyed, design, check_residual_stress(rs), str(rs.joint_model))
    solver = GridSolver(design, keyed, material, scene, S0, scene.body_force(float(cfg.material.density)),
                        settings, comm)
    solver.stats["wall_mesh_s"] += t_keyed
    load_before = os.getloadavg()[0]
    frames = solver.run(progress=progress)
    solver.stats["wall_total_s"] = time.perf_counter() - t0
    solver.stats["mpi_size"] = comm.size
    solver.stats["load_per_cpu"] = machine_load(load_before)
    solver.stats["marlow_c"] = list(material.c)
    return keyed, frames, solver.stats, scene


def failure_clearance(fail: SolveFailure, design: Design, cfg) -> dict:
    """The clearance (fea_factory.clearance) of the last state a failed solve reached, as last_* fields: a value
    near zero says the grid was folding onto itself, which a model without contact cannot follow."""
    if fail.last_xyz is None:
        return {}
    keyed = build_keyed_mesh(design, MeshPreset.from_mapping(cfg.mesh))  # the key tables only (cheap)
    c = clearance(fail.last_xyz, keyed.joint_nodes, keyed.beam_nodes, design.beams).as_dict()
    return {"last_t": fail.last_t, "last_clearance_mm": c["clearance_mm"],
            "last_clearance_blocks": c["clearance_blocks"]}


def episode_from_solution(design: Design, keyed, frames, stats: dict, scene: Scene, config_yaml: str,
                          seed: int, mpi_size: int):
    """The episode record (data_schema) of a solved design."""
    from data_schema.episode import Episode

    return Episode(
        joint_ij=design.joint_ij, joint_xy=design.joint_xy, beams=design.beams,
        beam_kind=np.array([KIND_CODES[k] for k in design.kinds], dtype=np.int8),
        fixed_joint=design.fixed_joint, beam_width=design.beam_width, thickness=design.thickness,
        family=str(design.meta.get("family", "unknown")), design_json=design.to_json(),
        node_key=keyed.node_key, node_xyz0=keyed.node_xyz, cell_key=keyed.cell_key,
        cell_nodes=keyed.cell_nodes, cell_layer=keyed.cell_layer, cell_print_angle=keyed.cell_print_angle,
        joint_nodes=keyed.joint_nodes, beam_nodes=keyed.beam_nodes, joint_cells=keyed.joint_cells,
        beam_cells=keyed.beam_cells, nodes_length=keyed.preset.nodes_length,
        nodes_width=keyed.preset.nodes_width, nodes_height=keyed.preset.nodes_height, preset=keyed.preset.name,
        t=np.asarray(frames.t), node_xyz=np.stack(frames.node_xyz), stress=np.stack(frames.stress),
        quad_points=frames.quad_points, quad_weights=frames.quad_weights,
        config_yaml=config_yaml, seed=int(seed), git_rev=git_revision(), versions_json=json.dumps(package_versions()),
        mpi_size=int(mpi_size), solver_stats_json=json.dumps({k: v for k, v in stats.items()
                                                              if k not in ("increment_t", "newton_iterations")}),
        scene_terms_json=json.dumps(scene.active_terms()),
        increment_t=np.asarray(stats["increment_t"], dtype=np.float64),
        newton_iterations=np.asarray(stats["newton_iterations"], dtype=np.int32),
    )


def main() -> None:
    import hydra
    from omegaconf import DictConfig, OmegaConf

    @hydra.main(version_base="1.3", config_path="../conf", config_name="solve")
    def _main(cfg: DictConfig) -> None:
        from mpi4py import MPI

        from data_schema.episode import write_episode

        logging.getLogger("UFL").setLevel(logging.WARNING)
        logging.getLogger("FFCx").setLevel(logging.WARNING)
        comm = MPI.COMM_WORLD
        try:  # solver.tolerance: the cheapest measured setting meeting it (recorded in cfg.solver.tolerance_pick)
            apply_tolerance(cfg, ranks=comm.size)
        except TradeoffError as err:
            if comm.rank == 0:
                print(f"solve: invalid configuration: {err}", file=sys.stderr)
            sys.exit(2)
        design = Design.load(cfg.design)
        try:
            keyed, frames, stats, scene = solve_design(design, cfg, comm)
        except SolveFailure as fail:
            if comm.rank == 0:
                print(json.dumps({"status": "diverged", "design": str(cfg.design), **fail.info,
                                  **failure_clearance(fail, design, cfg)}))
            sys.exit(EXIT_DIVERGED)
        if comm.rank == 0:
            c = clearance(np.stack(frames.node_xyz), keyed.joint_nodes, keyed.beam_nodes, design.beams)
            stats.update(c.as_dict())
            limit = float(cfg.solver.get("min_clearance_mm", 0.0))
            if c.mm < limit:
                print(json.dumps({"status": "contact", "design": str(cfg.design), **c.as_dict(),
                                  "reason": f"{c.blocks[0]} and {c.blocks[1]} come within {c.mm:.3g} mm at frame "
                                            f"{c.frame} (solver.min_clearance_mm = {limit}): the grid folds onto "
                                            "itself and the model has no contact"}))
        if comm.rank == 0 and c.mm < limit:
            sys.exit(EXIT_CONTACT)
        if comm.rank == 0:
            ep = episode_from_solution(design, keyed, frames, stats, scene,
                                       OmegaConf.to_yaml(cfg, resolve=True), int(cfg.get("seed", 0)), comm.size)
            path = write_episode(cfg.out, ep)
            print(json.dumps({"status": "ok", "out": str(path), "frames": len(frames.t),
                              "increments": stats["increments"], "newton": stats["newton_total"],
                              "newton_failed": stats["newton_failed"],
                              "cutbacks": stats["cutbacks"], "wall_total_s": round(stats["wall_total_s"], 3),
                              "clearance_mm": stats["clearance_mm"]}))

    _main()


if __name__ == "__main__":
    main()
