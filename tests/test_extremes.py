"""Stability at the extremes (slow): every case converges with finite output or fails as a structured
SolveFailure naming its reason; cases inside the documented safe ranges converge."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("dolfinx")
from fea_factory.extremes import CASES, NOMINAL_SIGMA, compose, run_case  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def test_nominal_sigma_is_the_composed_material_sigma():
    assert float(compose([]).material.residual_stress.sigma) == pytest.approx(NOMINAL_SIGMA)
    sigma_2x = next(c for c in CASES if c.name == "sigma_2x")
    assert sigma_2x.overrides == [f"material.residual_stress.sigma={2 * NOMINAL_SIGMA}"]


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_extreme_case_converges_or_fails_cleanly(case):
    row = run_case(case)
    assert row["finite"], f"{case.name}: non-finite output reached the frames"
    if row["status"] == "failed":
        assert row["reason"], f"{case.name}: a failure without a reason"
        assert not case.must_converge, f"{case.name} is inside the safe range but failed: {row['reason']}"


def test_designs_and_settings_outside_the_safe_ranges_are_refused_with_the_field_named():
    from mpi4py import MPI

    from fea_factory.compare import bench_design
    from fea_factory.design import DesignError, DesignLimits, validate
    from fea_factory.extremes import strip
    from fea_factory.material import MaterialError, bulk_modulus
    from fea_factory.scene import Scene, SceneError
    from fea_factory.solve import solve_design

    validate(strip(150.0), DesignLimits())
    with pytest.raises(DesignError, match="above the allowed maximum 150"):
        validate(strip(160.0), DesignLimits())
    with pytest.raises(SceneError, match="scene.g"):
        Scene(g=2e5)
    with pytest.raises(MaterialError, match="material.poisson"):
        bulk_modulus(1.0, 0.49995)
    with pytest.raises(ValueError, match=r"material.residual_stress.sigma = 0.25 MPa: must lie in \[0, 0.1974\]"):
        solve_design(bench_design(), compose(["material.residual_stress.sigma=0.25"]), MPI.COMM_WORLD)


@pytest.mark.parametrize("order", [2.5, 0, 7, True, "3"])
def test_a_marlow_order_that_is_not_an_integer_in_range_is_refused_by_name(order):
    import yaml

    from fea_factory.material import MaterialError, make_material

    cfg = yaml.safe_load((ROOT / "conf/material/pla_80c.yaml").read_text())
    make_material(cfg)  # the conf's own order (3) fits
    with pytest.raises(MaterialError, match=rf"material.order = {order!r}: must be an integer in \[1, 6\]"):
        make_material({**cfg, "order": order})  # 2.5 was fitted as 2 before, '3' raised a TypeError
