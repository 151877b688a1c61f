"""A design before triggering, as a one-frame episode: what a learned simulator starts from, written without a solve.

    python -m fea_factory.initial design=FILE.json out=FILE.h5 [mesh=...] [material=...] [scene=...]

Frame 0 of every solved episode is the flat reference mesh with zero stress (t = 0: no residual stress released,
no load); this writes exactly that frame through the same mesh and episode record as fea_factory.solve, with the
same resolved configuration (so learn's validity check can compare material, scene and mesh with the training
envelope) and no load increments. `learn.predict` rolls a trained model out from it (`make predict`).
"""
from __future__ import annotations

import sys

import numpy as np

from fea_factory.design import Design, DesignLimits, validate
from fea_factory.mesh import MeshPreset, build_keyed_mesh
from fea_factory.scene import Scene
from fea_factory.solve import episode_from_solution
from fea_factory.solver import Frames, stress_quadrature


def initial_episode(design: Design, cfg, config_yaml: str):
    """The episode (data_schema) holding only frame 0 of `design` under the conf groups in cfg."""
    validate(design, DesignLimits.from_mapping(cfg.blocks.limits))
    keyed = build_keyed_mesh(design, MeshPreset.from_mapping(cfg.mesh))
    qp, qw = stress_quadrature(cfg.solver.stress_quadrature_degree)
    frames = Frames(t=[0.0], node_xyz=[keyed.node_xyz], stress=[np.zeros((keyed.n_cells, len(qp), 6))],
                    quad_points=qp, quad_weights=qw)
    stats = {"solved": False, "increment_t": [], "newton_iterations": []}
    return episode_from_solution(design, keyed, frames, stats, Scene.from_mapping(cfg.scene), config_yaml,
                                 int(cfg.get("seed", 0)), mpi_size=1)


def main() -> None:
    import hydra
    from omegaconf import DictConfig, OmegaConf

    @hydra.main(version_base="1.3", config_path="../conf", config_name="solve")
    def _main(cfg: DictConfig) -> None:
        from data_schema.episode import write_episode

        try:
            ep = initial_episode(Design.load(cfg.design), cfg, OmegaConf.to_yaml(cfg, resolve=True))
        except ValueError as err:  # a design outside the limits, a bad mesh preset: named by the validators
            print(f"initial: {err}", file=sys.stderr)
            sys.exit(2)
        print(write_episode(cfg.out, ep))

    _main()


if __name__ == "__main__":
    main()
