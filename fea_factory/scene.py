"""Scenes: which physics terms an episode assembles (residual stress, gravity, buoyancy, fixed face).

Units: mm, s, t (tonne): densities in t/mm^3, g in mm/s^2, body force in N/mm^3.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


G_MAX = 98100.0  # mm/s^2: 10 g, verified by fea_factory.extremes (gravity_10x)


class SceneError(ValueError):
    """A scene whose physics cannot be solved as asked."""


@dataclass(frozen=True)
class Scene:
    name: str = "water_bath"
    residual_stress: bool = True
    gravity: bool = True
    buoyancy: bool = True
    fixed_face: bool = True
    g: float = 9810.0  # mm/s^2
    fluid_density: float = 9.717e-10  # t/mm^3

    def __post_init__(self) -> None:
        if not self.fixed_face:
            raise SceneError(f"scene {self.name!r}: fixed_face is false; a free-floating grid has no support "
                             "(rigid-body modes make the problem singular). Set scene.fixed_face: true")
        if self.buoyancy and not self.gravity:
            raise SceneError(f"scene {self.name!r}: buoyancy without gravity is meaningless; set both or neither")
        if self.g > G_MAX:
            raise SceneError(f"scene.g = {self.g} mm/s^2: must lie in [0, {G_MAX}] (10 x earth gravity, the largest "
                             "body force the stability matrix verified)")
        if self.g < 0 or self.fluid_density < 0:
            raise SceneError(f"scene {self.name!r}: g ({self.g}) and fluid_density ({self.fluid_density}) "
                             "must be >= 0")

    @classmethod
    def from_mapping(cls, m) -> "Scene":
        return cls(**{k: m[k] for k in cls.__dataclass_fields__ if k in m})

    def body_force(self, density: float) -> np.ndarray:
        """Net body force per reference volume (N/mm^3): -(rho - rho_fluid) g e_z, or zero without gravity."""
        if not self.gravity:
            return np.zeros(3)
        rho_net = density - (self.fluid_density if self.buoyancy else 0.0)
        return np.array([0.0, 0.0, -rho_net * self.g])

    def active_terms(self) -> dict[str, bool]:
        return {"residual_stress": self.residual_stress, "body_force": self.gravity,
                "buoyancy": self.buoyancy, "fixed_face": self.fixed_face}

    def as_dict(self) -> dict:
        return asdict(self)
