"""Design JSON round-trip and every validation error of fea_factory.design / fea_factory.geometry."""
import json
import warnings

import numpy as np
import pytest

from fea_factory.design import Design, DesignError, DesignLimits, lattice_design, validate
from fea_factory.geometry import beam_quad, block_geometry, joint_quad, quad_corner_angles

LIMITS = DesignLimits()


def grid(nx=3, ny=3, s=60.0):
    """Regular lattice positions [nx, ny, 2] with spacing s (mm)."""
    i, j = np.meshgrid(np.arange(nx) * s, np.arange(ny) * s, indexing="ij")
    return np.stack([i, j], axis=-1)


def square(**kw):
    """A valid 3 x 3 design: 9 joints, 12 beams, fixed centre joint 4."""
    return lattice_design(grid(), kw.pop("kinds", "up"), (1, 1), **kw)


def plus(angles_deg, length=50.0):
    """A centre joint with four beams E, N, W, S pointing at the given angles (counter-clockwise)."""
    a = np.radians(angles_deg)
    xy = [(0.0, 0.0)] + [(length * np.cos(t), length * np.sin(t)) for t in a]
    return Design([(1, 1), (2, 1), (1, 2), (0, 1), (1, 0)], xy, [(0, 1), (0, 2), (0, 3), (0, 4)], ["up"] * 4, 0)


def raises(design, match, limits=LIMITS):
    with pytest.raises(DesignError, match=match):
        validate(design, limits)


# ------------------------------------------------------------------------------------------ JSON
def test_valid_designs_pass():
    validate(square())
    validate(lattice_design(grid(2, 2), "passive", (0, 0)))
    validate(lattice_design(grid(7, 3, 40.0), "down", (3, 1)))


def test_json_round_trip(tmp_path):
    kinds = ["up", "down", "passive"] * 4
    d = square(kinds=kinds, beam_width=6.0, thickness=3.0, meta={"family": "regular", "spacing": [60.0, 60.0]})
    path = tmp_path / "d.json"
    d.save(path)
    assert not (tmp_path / "d.json.tmp").exists()
    e = Design.load(path)
    assert np.array_equal(e.joint_ij, d.joint_ij) and np.array_equal(e.beams, d.beams)
    assert np.array_equal(e.joint_xy, d.joint_xy)  # floats survive JSON exactly (repr round-trip)
    assert (e.kinds, e.fixed_joint, e.beam_width, e.thickness, e.meta) == (kinds, 4, 6.0, 3.0, d.meta)
    assert e.to_json() == d.to_json()


def test_json_format_and_missing_fields():
    d = square().to_dict()
    with pytest.raises(DesignError, match="'format'"):
        Design.from_dict({**d, "format": "other/1"})
    for key in ("joints", "beams", "fixed_joint"):
        with pytest.raises(DesignError, match=f"missing field '{key}'"):
            Design.from_json(json.dumps({k: v for k, v in d.items() if k != key}))


# ------------------------------------------------------------------------------------------ fields
def test_too_few_joints_or_beams():
    raises(Design([(0, 0)], [(0, 0)], [], [], 0), "at least 2 are needed")
    raises(Design([(0, 0), (1, 0)], [(0, 0), (50, 0)], [], [], 0), "no beams")


def test_non_finite_position():
    d = square()
    d.joint_xy[3] = np.nan
    raises(d, r"joint 3: position .* is not finite")


def test_beam_width_and_thickness_ranges():
    raises(square(beam_width=1.0), r"beam_width 1.0 mm is outside the allowed range \[2.0, 20.0\]")
    raises(square(beam_width=25.0), r"beam_width 25.0 mm is outside")
    raises(square(thickness=0.5), r"thickness 0.5 mm is outside the allowed range \[1.0, 20.0\]")
    raises(square(thickness=30.0), r"thickness 30.0 mm is outside")


def test_fixed_joint_out_of_range():
    d = square()
    d.fixed_joint = 9
    raises(d, r"fixed_joint 9 is outside the allowed range \[0, 8\]")
    d.fixed_joint = -1
    raises(d, r"fixed_joint -1 is outside")
    with pytest.raises(DesignError, match=r"fixed joint lattice index \[3, 0\] is outside the grid"):
        lattice_design(grid(), "up", (3, 0))


def test_bad_kind_and_kind_count():
    kinds = ["up"] * 12
    kinds[5] = "sideways"
    raises(square(kinds=kinds), r"beam 5: kind 'sideways' is not one of \['up', 'down', 'passive'\]")
    d = square()
    d.kinds = d.kinds[:-1]
    raises(d, "12 beams but 11 beam kinds")
    with pytest.raises(DesignError, match="11 beam kinds given for a 3 x 3 grid with 12 beams"):
        lattice_design(grid(), ["up"] * 11, (1, 1))
    with pytest.raises(DesignError, match="grid size 1 x 3"):
        lattice_design(grid(1, 3), "up", (0, 0))


# ------------------------------------------------------------------------------------------ topology
def test_duplicate_lattice_index():
    d = square()
    d.joint_ij[8] = d.joint_ij[0]
    raises(d, r"joint 8: lattice index \[0, 0\] is already used by joint 0")


def test_beam_end_out_of_range_and_self_beam():
    d = square()
    d.beams[2] = (4, 12)
    raises(d, r"beam 2: joint index 12 is outside the allowed range \[0, 8\]")
    d = square()
    d.beams[2] = (4, 4)
    raises(d, "beam 2: joins joint 4 to itself")


def test_non_grid_neighbour_beam():
    d = square()
    d.beams[0] = (0, 4)  # diagonal: lattice step (1, 1)
    raises(d, r"beam 0: joins joint 0 at lattice \[0, 0\] and joint 4 at lattice \[1, 1\], which are not grid "
              "neighbours")
    d.beams[0] = (0, 2)  # two steps along i
    raises(d, "not grid neighbours")


def test_duplicate_beam():
    """A joint can never get > 4 beams: unique lattice indices + the neighbour rule leave 4 neighbours, and a
    fifth beam must repeat one of them, which the duplicate check reports first."""
    d = square()
    d.beams = np.vstack([d.beams, [[4, 1]]])  # joint 4 already has beams to 1, 3, 5, 7
    d.kinds = d.kinds + ["up"]
    raises(d, r"beam 12: joints 4 and 1 are already joined by beam \d+ \(overlapping beams\)")


def test_joint_without_beam():
    d = square()
    keep = [b for b, (a, c) in enumerate(d.beams.tolist()) if 8 not in (a, c)]
    d.beams, d.kinds = d.beams[keep], [d.kinds[b] for b in keep]
    raises(d, "joint 8: has no beam; every joint needs 1 to 4 beams")


def test_disconnected_part():
    # 2 x 2 grid with only the two i-direction beams: rows {0, 1} and {2, 3} float apart
    d = lattice_design(grid(2, 2), "up", (0, 0))
    d.beams, d.kinds = d.beams[:2], d.kinds[:2]
    raises(d, r"joints \[2, 3\] are not connected to the fixed joint 0")


# ------------------------------------------------------------------------------------------ geometry
def test_short_beam():
    # spacing 15 mm leaves 15 - 7.2 = 7.8 mm of clear beam between the joint blocks
    raises(lattice_design(grid(2, 2, 15.0), "up", (0, 0)),
           r"beam 0 \(joints 0-1\): clear length 7.80 mm between its joint blocks is below the allowed minimum 10.0 mm")


def test_sharp_joint_corner_from_heavy_jitter():
    xy = grid()
    xy[1, 0] += (0.0, 40.0)  # the corner joint's two neighbours jittered 40 mm towards each other:
    xy[0, 1] += (40.0, 0.0)  # its E and N arms meet at 22.6 deg
    d = lattice_design(xy, "up", (1, 1))
    raises(d, r"joint 0: corner angles \[22.6, 157.4, 22.6, 157.4\] deg; each must lie in \[45.0, 135.0\] deg")
    validate(d, DesignLimits(min_joint_angle=20.0))  # the same design passes a looser limit


def test_sharp_beam_corner():
    """Joint corners can be fine while a beam's end face is too oblique to its axis."""
    d = plus([0, 125, 195, 230])
    g = block_geometry(d)
    assert quad_corner_angles(joint_quad(g.joint_corners[0])).min() > 50.0
    assert min(quad_corner_angles(beam_quad(q)).min() for q in g.beam_corners) < 40.0
    raises(d, r"beam \d: corner angles .* each must lie in \[45.0, 135.0\] deg")
    validate(plus([0, 90, 180, 270]))


def test_overlapping_blocks():
    # a C-shaped path (0,0)-(1,0)-(2,0)-(2,1)-(2,2)-(1,2)-(0,2)-(0,1) whose free end (0,1) is pulled down to
    # 6 mm from joint (0,0): the two 7.2 mm joint blocks overlap though no beam joins them
    ij = [(0, 0), (1, 0), (2, 0), (2, 1), (2, 2), (1, 2), (0, 2), (0, 1)]
    xy = [(0, 0), (50, 0), (100, 0), (100, 50), (100, 100), (50, 100), (0, 100), (0, 6)]
    beams = [(k, k + 1) for k in range(7)]
    d = Design(ij, xy, beams, ["up"] * 7, 0)
    raises(d, "joint 0 and joint 7 overlap")
    d.joint_xy[7] = (0, 12)  # 12 - 7.2 = 4.8 mm gap: fine
    validate(d)


def test_crossing_beams():
    # the same C-shape, its last beam (0,2)-(0,1) run down across the first beam (0,0)-(1,0)
    ij = [(0, 0), (1, 0), (2, 0), (2, 1), (2, 2), (1, 2), (0, 2), (0, 1)]
    xy = [(0, 0), (60, 0), (100, 0), (100, 50), (100, 100), (65, 100), (30, 100), (30, -30)]
    d = Design(ij, xy, [(k, k + 1) for k in range(7)], ["up"] * 7, 0)
    raises(d, "beam 0 and beam 6 overlap")
    d.joint_xy[7] = (30, 30)  # stops 30 mm above the first beam
    validate(d)


def test_footprint_larger_than_printable_area():
    d = lattice_design(grid(3, 2, 160.0), "up", (1, 0))  # 320 + 7.2 mm wide, beams 152.8 mm (long limit lifted)
    raises(d, r"design footprint 327.2 x 167.2 mm exceeds the printable area 300.0 x 300.0 mm",
           DesignLimits(max_beam_length=200.0))
    raises(d, r"clear length 152.80 mm is above the allowed maximum 150.0 mm", DesignLimits(printable_width=400.0))
    validate(d, DesignLimits(printable_width=400.0, max_beam_length=200.0))


def test_coincident_joints():
    """Two joined joints at one point: a clear error, not a 0/0 beam axis turned into a misleading angle error."""
    xy = grid()
    xy[1, 1] = xy[1, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from the geometry
        raises(lattice_design(xy, "up", (1, 1)), r"beam 7: joints 1 and 4 are both at \[60.0, 0.0\]")
