"""Simulation conditions the graphs do not carry, and the training envelope a learned rollout is trusted in.

A block's features hold its shape, stress and actuator kind, never the material, the residual-stress magnitude or
the body force: two scenes that differ only there give the network the same initial graph and the same answer.
So a rollout is flagged when the conditions of its episode (its provenance config) or the size of its design lie
outside those of the training episodes. Numbers compare within a relative tolerance, strings exactly.
"""
from __future__ import annotations

import numpy as np
from omegaconf import OmegaConf

# provenance config entries that change the physics but not the initial graph
PHYSICS_KEYS = ("material.law", "material.poisson", "material.density", "material.residual_stress.sigma",
                "material.residual_stress.joint_model", "scene.residual_stress", "scene.gravity", "scene.buoyancy",
                "scene.g", "scene.fluid_density", "mesh.nodes_length", "mesh.nodes_width", "mesh.nodes_height")
REL_TOL = 0.05  # a number within 5 % of the training range counts as inside it


def episode_conditions(config_yaml: str, joint_xy: np.ndarray, beams: np.ndarray) -> dict:
    """{name: number | str | [lo, hi]} of one episode: the PHYSICS_KEYS of its resolved config (missing ones left
    out), the design's joint count and the range of its beams' centre-to-centre lengths (mm)."""
    cfg = OmegaConf.create(config_yaml or {})
    out = {k: v for k in PHYSICS_KEYS if (v := OmegaConf.select(cfg, k)) is not None}
    out = {k: (float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)) for k, v in out.items()}
    xy, pairs = np.asarray(joint_xy, float), np.asarray(beams, int)[:, :2]
    lengths = np.linalg.norm(xy[pairs[:, 0]] - xy[pairs[:, 1]], axis=1)
    out.update({"design.n_joints": float(len(xy)), "design.beam_length": [float(lengths.min()), float(lengths.max())]})
    return out


def envelope(conditions: list[dict]) -> dict:
    """The training envelope: {name: [min, max]} for numbers and intervals, {name: [values...]} for strings."""
    out: dict = {}
    for name in sorted({k for c in conditions for k in c}):
        values = [c[name] for c in conditions if name in c]
        if all(isinstance(v, (float, list)) for v in values):  # numbers and [lo, hi] intervals
            flat = [x for v in values for x in (v if isinstance(v, list) else [v])]
            out[name] = [min(flat), max(flat)]
        else:
            out[name] = sorted({str(v) for v in values})
    return out


def outside(conditions: dict, env: dict, rel_tol: float = REL_TOL) -> list[str]:
    """Reasons (empty when inside): every condition of the episode outside the envelope, named with its range."""
    reasons = []
    for name, value in sorted(conditions.items()):
        if name not in env:
            continue
        allowed = env[name]
        if isinstance(value, (float, list)) and all(isinstance(a, float) for a in allowed):
            lo, hi = allowed
            slack = rel_tol * max(abs(lo), abs(hi), 1e-12)
            vlo, vhi = (value, value) if isinstance(value, float) else value
            if vlo < lo - slack or vhi > hi + slack:
                shown = f"{vlo:.4g}" if vlo == vhi else f"[{vlo:.4g}, {vhi:.4g}]"
                reasons.append(f"{name} = {shown} outside the training range [{lo:.4g}, {hi:.4g}]")
        elif str(value) not in allowed:
            reasons.append(f"{name} = {value} not among the training values {allowed}")
    return reasons
