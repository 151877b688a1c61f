"""Hyperelastic laws behind one small interface: W(F) = W_dev(I1bar) + W_vol(J).

Units: MPa (N/mm^2) for moduli and stresses.

Marlow-like construction (Marlow 2003; Abaqus "Marlow" form): the deviatoric energy depends on
I1bar = J^(-2/3) tr C only and is built from ONE uniaxial nominal stress-strain table so that a uniaxial
test reproduces it. For incompressible uniaxial tension at stretch lam = 1 + eps,

    I1bar(lam) = lam^2 + 2 / lam,        T(lam) = 2 (lam - lam^-2) W_dev'(I1bar(lam)).

Abaqus integrates the table into W_dev numerically (piecewise); piecewise laws put kinks into the
Hessian and hurt Newton, so we fit the smooth polynomial W_dev = sum_k c_k (I1bar - 3)^k, k = 1..order,
by linear least squares of T over the table points (T is linear in c), and check W_dev' > 0 over the
fitted range (Drucker stability). Outside the fitted I1bar range the law extrapolates: the range is
recorded. The small-strain shear modulus is mu0 = 2 c_1 (E0 = 6 c_1 = 3 mu0).
Volumetric part (Abaqus: (J - 1)^2 / D1 with K = 2 / D1): W_vol = K/2 (J - 1)^2, K from a Poisson ratio.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fea_factory.checks import integer_in

POISSON_MAX = 0.4999  # tests/test_solver.py (locking) and fea_factory.extremes (nu_0.4999)


class MaterialError(ValueError):
    """A material definition outside its valid range."""


def bulk_modulus(mu0: float, poisson: float) -> float:
    """K = 2 mu0 (1 + nu) / (3 (1 - 2 nu)) for the small-strain shear modulus mu0."""
    if not 0.0 <= poisson <= POISSON_MAX:
        raise MaterialError(f"material.poisson = {poisson}: must lie in [0, {POISSON_MAX}] (K/mu <= 5000: Q2 "
                            "elements verified free of volumetric locking and convergent up to there)")
    return 2.0 * mu0 * (1.0 + poisson) / (3.0 * (1.0 - 2.0 * poisson))


@dataclass(frozen=True)
class ReducedPolynomial:
    """W = sum_k c_k (I1bar - 3)^k + K/2 (J - 1)^2: neo-Hookean (c = [mu/2]), Yeoh (3 terms), Marlow fit."""

    c: tuple[float, ...]  # MPa
    kappa: float  # MPa, bulk modulus
    name: str = "reduced_polynomial"
    fitted_I1bar_range: tuple[float, float] | None = None
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def mu0(self) -> float:
        return 2.0 * self.c[0]

    def W_dev(self, I1bar):
        x = I1bar - 3
        return sum(ck * x ** (k + 1) for k, ck in enumerate(self.c))

    def dW_dev(self, I1bar):
        x = I1bar - 3
        return sum((k + 1) * ck * x**k for k, ck in enumerate(self.c))

    def W_vol(self, J):
        return 0.5 * self.kappa * (J - 1) ** 2

    def strain_energy(self, F):
        """UFL (or numpy for a single 3x3 F) strain energy density per reference volume, MPa."""
        import ufl

        J = ufl.det(F)
        I1bar = J ** (-2.0 / 3.0) * ufl.tr(F.T * F)
        return self.W_dev(I1bar) + self.W_vol(J)

    def uniaxial_nominal_stress(self, stretch: np.ndarray) -> np.ndarray:
        """Incompressible uniaxial nominal stress T(lam) = 2 (lam - lam^-2) W_dev'(lam^2 + 2/lam)."""
        lam = np.asarray(stretch, dtype=float)
        return 2.0 * (lam - lam**-2) * self.dW_dev(lam**2 + 2.0 / lam)


def fit_marlow(strain, nominal_stress, poisson: float, order: int = 3) -> ReducedPolynomial:
    """Fit the smooth Marlow-like deviatoric energy to a uniaxial nominal stress-strain table."""
    eps = np.asarray(strain, dtype=float)
    T = np.asarray(nominal_stress, dtype=float)
    order = integer_in(order, "material.order", MaterialError, 1, 6, "terms of the polynomial")
    if eps.shape != T.shape or eps.ndim != 1 or len(eps) < order + 1:
        raise MaterialError(f"material.table: strain and stress need equal lengths >= {order + 1}; "
                            f"got {eps.shape} and {T.shape}")
    if np.any(eps <= -1.0) or not np.all(np.isfinite(T)):
        raise MaterialError("material.table: strains must be > -1 and stresses finite")
    keep = np.abs(eps) > 1e-12  # lam = 1 carries no information (0/0)
    lam, T = 1.0 + eps[keep], T[keep]
    x = lam**2 + 2.0 / lam - 3.0
    # T = 2 (lam - lam^-2) * sum_k k c_k x^(k-1): linear in c
    A = np.stack([2.0 * (lam - lam**-2) * (k + 1) * x**k for k in range(order)], axis=1)
    c, *_ = np.linalg.lstsq(A, T, rcond=None)
    lo, hi = 3.0, float(x.max() + 3.0)
    mat = ReducedPolynomial(tuple(float(v) for v in c), kappa=bulk_modulus(2.0 * c[0], poisson),
                            name="marlow", fitted_I1bar_range=(lo, hi))
    grid = np.linspace(lo, hi, 200)
    if c[0] <= 0 or np.any(mat.dW_dev(grid) <= 0):
        raise MaterialError("material.table: the fitted Marlow energy has W' <= 0 inside the data range "
                            "(Drucker-unstable); check the table or lower material.order")
    return mat


def make_material(cfg) -> ReducedPolynomial:
    """Material from conf/material/*.yaml (law: marlow | neo_hookean | yeoh)."""
    law = cfg["law"]
    poisson = float(cfg["poisson"])
    if law == "marlow":
        table = cfg["table"]
        return fit_marlow(table["strain"], table["nominal_stress"], poisson, cfg.get("order", 3))
    if law == "neo_hookean":
        mu = float(cfg["mu"])
        if mu <= 0:
            raise MaterialError(f"material.mu = {mu}: must be > 0 MPa")
        return ReducedPolynomial((mu / 2.0,), bulk_modulus(mu, poisson), "neo_hookean")
    if law == "yeoh":
        c = tuple(float(cfg[k]) for k in ("C10", "C20", "C30"))
        if c[0] <= 0:
            raise MaterialError(f"material.C10 = {c[0]}: must be > 0 MPa")
        return ReducedPolynomial(c, bulk_modulus(2.0 * c[0], poisson), "yeoh")
    raise MaterialError(f"material.law = {law!r}: must be one of marlow, neo_hookean, yeoh")
