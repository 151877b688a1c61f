"""Validity of a learned rollout: flag results that should not be presented as answers.

Symptoms, all measurable without FEA:
- dislocation: a beam's end cross-section and its joint each rebuild the shared interface nodes; when the two
  predictions drift apart the blocks no longer form one solid. It is a certificate as well as a symptom: two
  predictions of one node a distance d apart cannot both lie within d/2 of where the node really is, so the answer's
  max error is at least half the dislocation (`error_lower_bound_rel`), whatever the FEA would say;
- out of range: a block's PCA coefficients leave the range seen in training (widened by a margin), so the
  networks extrapolate;
- unrolled (designs whose actuators are all one kind): such a grid cannot take the doubly curved bowl its
  actuators want without stretching, so it rolls one way into a near-cylinder (37 of 44 held-out FEA answers, session
  29) or, rarely, closes into a bowl by a snap. An answer that has not rolled sits on the symmetric branch between
  the two, where the FEA goes one way or the other: 1 - |s_i - s_j| with s the final frame's extents along the
  lattice's i and j directions over the flat design's (learn.roll; 1: no roll at all; 0 for mixed designs, which
  have no such branch). A threshold of 0 flags every one-kind design whatever its answer (the local models' setting
  since session 36: which way such a grid goes is set by small asymmetries, and the learned answers go the wrong way
  often enough that none is presented as an answer; conf/validity/default.yaml);
- conditions: the episode's material, residual stress, body force, mesh or design size lie outside those of the
  training episodes (learn.conditions). The graphs do not carry them, so the other two checks cannot see them;
- spread (ensembles only, learn.ensemble): the members disagree about a point by more than a fraction of the
  design size (off by default: measured in session 10, the spread of two seeds ranks designs by error no better
  than the disagreement of one network's symmetric copies, Spearman 0.37; docs/learned_simulator.md "Ensembles").

The dislocation and spread are judged relative to the design size, as the error is. The thresholds
(conf/validity/default.yaml) are calibrated against FEA on held-out designs: learn.evaluate measures, on every
report, how many designs worse than `flag_error_rel` the check flags and how many better ones it flags needlessly
(`validity_measured`), and learn.validity_calibration picks the thresholds that best separate the two from such
reports (docs/learned_simulator.md, session 29).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from learn.conditions import REL_TOL, outside
from learn.ensemble import Ensemble, member_spread, members_of
from learn.features import shared_point_pairs
from learn.model import FRAMES, Simulator, static_from
from learn.roll import ONE_KIND, roll
from learn.rollout import Rollout


@dataclass
class Verdict:
    valid: bool
    reasons: list[str] = field(default_factory=list)
    max_dislocation_mm: float = 0.0  # largest distance between two predictions of one interface node
    max_dislocation_rel: float = 0.0  # the same / design size
    error_lower_bound_rel: float = 0.0  # half of it: the answer's max error / design size is at least this
    dislocation_per_frame: list[float] = field(default_factory=list)
    out_of_range_fraction: float = 0.0  # of (frame, block) pairs with a coefficient outside the training range
    unrolled_one_kind: float = 0.0  # all one kind: 1 - |s_i - s_j| of the final shape (unrolled above); mixed: 0
    first_bad_frame: int | None = None
    max_spread_rel: float | None = None  # ensembles: largest member-to-mean point distance / design size
    spread_per_frame: list[float] = field(default_factory=list)  # the same per frame

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def dislocation(r: Rollout) -> np.ndarray:
    """[F] max distance (mm) between the joint's and the beam's prediction of the same interface node."""
    pairs = shared_point_pairs(r.point_nodes)
    if len(pairs) == 0:
        return np.zeros(r.n_frames)
    return np.linalg.norm(r.points[:, pairs[:, 0]] - r.points[:, pairs[:, 1]], axis=-1).max(axis=1)


def unrolled_one_kind(r: Rollout) -> float:
    """1 - |s_i - s_j|, s the final frame's extents along the design's lattice directions i and j over frame 0's
    (learn.roll), for a design whose actuators are all one kind (an answer that has not chosen a direction to roll
    in); 0 for a mixed design."""
    if r.features.actuators not in ONE_KIND:
        return 0.0
    return float(1.0 - abs(roll(r.features, r.points)))


def out_of_range(model: Simulator | Ensemble, r: Rollout, margin: float) -> np.ndarray:
    """[F] fraction of blocks with any PCA coefficient outside the training range widened by `margin` (an
    ensemble: outside that of any member)."""
    f = r.features
    static = static_from(f.joint_bc, f.beam_bc, f.incidence)
    joint_bad = torch.zeros(r.joint_states.shape[:2], dtype=torch.bool)
    beam_bad = torch.zeros(r.beam_states.shape[:2], dtype=torch.bool)
    with torch.inference_mode():
        for member in members_of(model):
            z = member.coefficients(torch.as_tensor(r.joint_states, dtype=torch.float32),
                                    torch.as_tensor(r.beam_states, dtype=torch.float32), static)
            for term, coeffs in z.items():
                bad = member.pca[term].outside(coeffs, margin).any(-1) | ~torch.isfinite(coeffs).all(-1)
                if term.startswith("joint"):
                    joint_bad |= bad
                else:
                    beam_bad |= bad
    return torch.cat([joint_bad, beam_bad], 1).float().mean(1).numpy()


def judging_frame(frames) -> str:
    """The section of conf/validity whose thresholds judge a model whose members read their blocks in `frames`: a
    rotated frame's (local, fixed) when any member reads in it, as an ensemble's out-of-range share counts a block
    outside any member's range; else "global", the top level. Members in two rotated frames are refused."""
    rotated = sorted(set(frames) - {"global"})
    if len(rotated) > 1:
        raise ValueError(f"the model's members read their blocks in frames {rotated}: no one section of thresholds "
                         "judges them; check or calibrate each apart")
    return rotated[0] if rotated else "global"


def thresholds(validity: dict, model: Simulator | Ensemble) -> dict:
    """The keyword arguments of `check` for `model` from conf/validity: its top-level thresholds, overridden by those
    under the model's frame (judging_frame: `local:` for a model, or an ensemble with any member, in that frame).
    The out-of-range share is read against the model's own training ranges, which a model reading each block in its
    own frame has narrower, so its calibration differs."""
    base = {k: v for k, v in validity.items() if not isinstance(v, dict)}
    for frame, overrides in validity.items():
        if isinstance(overrides, dict) and frame not in FRAMES:
            raise ValueError(f"validity.{frame}: not a model frame; allowed: {list(FRAMES)}")
    frame = judging_frame(m.args.get("frame", "global") for m in members_of(model))
    overrides = validity.get(frame)
    if isinstance(overrides, dict):
        unknown = set(overrides) - set(base)
        if unknown:
            raise ValueError(f"validity.{frame}: unknown thresholds {sorted(unknown)}; allowed: {sorted(base)}")
        base.update(overrides)
    return base


def check(model: Simulator | Ensemble, r: Rollout, max_dislocation_rel: float = 0.04, range_margin: float = 0.0,
          max_out_of_range: float = 0.3, max_unrolled_one_kind: float = 0.85, envelope: dict | None = None,
          condition_tolerance: float = REL_TOL, max_spread_rel: float | None = None) -> Verdict:
    """Verdict on one rollout; invalid when any frame breaks a threshold (the dislocation and spread as fractions
    of the design size, the out-of-range share as a fraction of the blocks; the defaults are
    conf/validity/default.yaml's), any value is not finite, or the episode's
    conditions (material, residual stress, body force, mesh, design size) lie outside the training `envelope`
    (stored in the checkpoint by learn.train) by more than `condition_tolerance`, relative. An ensemble's rollout
    (r.member_points) also reports its members' spread, and is invalid where it exceeds `max_spread_rel` of the
    design size (None: reported, not judged)."""
    reasons = [f"conditions outside training: {why}"
               for why in outside(r.features.conditions, envelope or {}, condition_tolerance)]
    off_conditions = bool(reasons)
    finite = np.isfinite(r.points).all(axis=(1, 2))
    size = r.features.design_size
    disl = np.where(finite, dislocation(r), np.inf)
    oor = np.where(finite, out_of_range(model, r, range_margin), 1.0)
    torn, outside_range = disl > max_dislocation_rel * size, oor > max_out_of_range
    bad = torn | outside_range | ~finite
    unrolled = unrolled_one_kind(r) if finite.all() else 0.0
    if unrolled > max_unrolled_one_kind:  # a property of the answer's last frame
        bad[-1] = True
        reasons.append(f"all actuators {r.features.actuators.removeprefix('all ')}: a bifurcation, where the grid "
                       "rolls one way or the other or snaps into a bowl as small asymmetries decide; the answer's "
                       f"1 - |s_i - s_j| = {unrolled:.3g} (1: not rolled, 0: fully rolled one way) is above "
                       f"{max_unrolled_one_kind:.3g}")
    spread = None
    if r.member_points is not None:
        spread = np.where(finite, member_spread(r.member_points) / size, np.inf)
        if max_spread_rel is not None:
            bad |= spread > max_spread_rel
            if (spread > max_spread_rel).any():
                k = int(np.argmax(spread > max_spread_rel))
                reasons.append(f"ensemble members disagree by {100 * spread[k]:.3g} % of the design size at frame "
                               f"{k} (limit {100 * max_spread_rel:.3g} %)")
    if not finite.all():
        reasons.append(f"non-finite points from frame {int(np.argmin(finite))}")
    if torn.any():
        k = int(np.argmax(torn))
        reasons.append(f"beam/joint faces dislocated by {disl[k]:.3g} mm = {100 * disl[k] / size:.3g} % of the design "
                       f"size at frame {k} (limit {100 * max_dislocation_rel:.3g} %): the max error is at least "
                       f"{100 * disl[k] / size / 2:.3g} %")
    if outside_range.any():
        k = int(np.argmax(outside_range))
        reasons.append(f"{100 * oor[k]:.0f} % of blocks outside the training feature range at frame {k} "
                       f"(limit {100 * max_out_of_range:.3g} %; margin {range_margin} of the range)")
    return Verdict(valid=not bad.any() and not off_conditions, reasons=reasons, max_dislocation_mm=float(disl.max()),
                   max_dislocation_rel=float(disl.max() / size), error_lower_bound_rel=float(disl.max() / size / 2),
                   dislocation_per_frame=[float(d) for d in disl], out_of_range_fraction=float(oor.max()),
                   unrolled_one_kind=unrolled,
                   first_bad_frame=0 if off_conditions else int(np.argmax(bad)) if bad.any() else None,
                   max_spread_rel=None if spread is None else float(spread.max()),
                   spread_per_frame=[] if spread is None else [float(x) for x in spread])
