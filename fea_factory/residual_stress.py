"""Printed residual stress per cell: a uniaxial stress of magnitude sigma along the layer's print direction.

Thesis ("Boundary Conditions"): s11 = sigma cos^2(a), s22 = sigma - s11, s33 = 0, s13 = s23 = 0 and
|s12| = sigma sin(a) cos(a), i.e. S0 = sigma d (x) d with d the in-plane print direction. We store print
angles counter-clockwise from +x, d = (cos a, sin a, 0), so s12 = +sigma sin(a) cos(a); the thesis's
minus sign belongs to its CAD tool's clockwise angle. Either way the principal axis of S0 is the toolpath.

The stress is an initial (second Piola-Kirchhoff) stress in the reference configuration, as Abaqus'
*Initial Conditions, type=STRESS: the body is not in equilibrium with it, and releasing it (scaled by the
pseudo-time t) makes each layer shrink along its toolpath: a layer free to deform contracts by
sigma / E along d and widens by nu sigma / E across it.
Units: MPa.
"""
from __future__ import annotations

import numpy as np

JOINT_MODELS = ("average", "alternating", "none")


def print_direction(angle_deg: np.ndarray) -> np.ndarray:
    """Unit print directions [C, 3] from angles in degrees (counter-clockwise from +x)."""
    a = np.radians(np.asarray(angle_deg, dtype=float))
    return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=-1)


def check_residual_stress(rs) -> float:
    """sigma (MPa) of a conf/material residual_stress mapping, refused outside [0, sigma_max] (the largest value
    the stability matrix verified; sigma itself when the material gives no sigma_max)."""
    sigma = float(rs["sigma"])
    sigma_max = float(rs.get("sigma_max", sigma))
    if not 0.0 <= sigma <= sigma_max:
        raise ValueError(f"material.residual_stress.sigma = {rs['sigma']} MPa: must lie in [0, {sigma_max}] "
                         "(material.residual_stress.sigma_max, the largest value verified stable)")
    return sigma


def initial_stress(print_angle: np.ndarray, is_joint: np.ndarray, sigma: float, joint_model: str) -> np.ndarray:
    """S0 per cell [C, 3, 3]: sigma d (x) d in beams; joints per `joint_model` (see conf/material)."""
    if joint_model not in JOINT_MODELS:
        raise ValueError(f"material.residual_stress.joint_model = {joint_model!r}: must be one of {list(JOINT_MODELS)}")
    if not np.isfinite(sigma) or sigma < 0:
        raise ValueError(f"material.residual_stress.sigma = {sigma}: must be a finite value >= 0 MPa")
    d = print_direction(print_angle)
    S0 = sigma * d[:, :, None] * d[:, None, :]
    joints = np.asarray(is_joint, dtype=bool)
    if joint_model == "average":  # mean of two perpendicular layers: sigma/2 in-plane, isotropic
        S0[joints] = 0.5 * sigma * np.diag([1.0, 1.0, 0.0])
    elif joint_model == "none":
        S0[joints] = 0.0
    return S0
