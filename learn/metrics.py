"""Losses and rollout errors: multi-step training loss and position error relative to the design size."""
from __future__ import annotations

import numpy as np
import torch

from learn.dataset import GraphSet
from learn.features import BEAM_POINTS, JOINT_POINTS, rebuild_all_points
from learn.graph import BEAM, JOINT
from learn.model import Simulator
from learn.rollout import unroll


def column_weights(block, stress_weight: float) -> torch.Tensor:
    w = torch.ones(block.state_size)
    w[block.stress_slice] = stress_weight
    return w


def beam_chords(beam_state: torch.Tensor) -> torch.Tensor:
    """[..., B, 6] each beam's two half chords, start -> middle and middle -> end section centre (mm): how far and
    which way the beam has turned and bent, independent of where it sits."""
    centre = lambda s: beam_state[..., BEAM.geometry.slice(f"{s}_center")]  # noqa: E731
    return torch.cat([centre("middle") - centre("start"), centre("end") - centre("middle")], -1)


GEOMETRY_LOSSES = ("columns", "points", "both")  # loss_geometry (conf/train.yaml): multistep_loss
NOISE_SHAPES = ("columns", "rigid")  # noise_shape (conf/train.yaml): multistep_loss


def noise_shape_checked(value) -> str:
    if value not in NOISE_SHAPES:
        raise ValueError(f"noise_shape={value!r}: must be {' | '.join(NOISE_SHAPES)} (columns: every column read on "
                         "its own; rigid: every joint moved rigidly, its beams with it)")
    return value


def noise_placement_checked(noise_std: float, start: bool, every_step: bool) -> None:
    """noise_std > 0 must displace some state: the start (noise_start) or the later steps' (noise_every_step)."""
    if noise_std > 0 and not start and not every_step:
        raise ValueError(f"noise_start=false with noise_every_step=false and noise_std={noise_std:g}: no state would "
                         "be displaced; set noise_every_step=true (noise on the later steps only) or noise_std=0")


def rigidly_displaced(model: Simulator, joint_state: torch.Tensor, beam_state: torch.Tensor, batch: GraphSet,
                      noise_std: float, generator: torch.Generator | None = None,
                      joint_std: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The states with every free joint moved rigidly by a random (v, omega) and its beams' sections with it
    (learn.stiffness.rigidly_moved: the shape of the stiffness model's own step, so of its errors): no block
    distorted, the fixed joint not moved (the model pins it). v ~ N(0, (noise_std s_v)^2) per axis, s_v the mean
    step std of the joint centres (mm); omega ~ N(0, (noise_std s_w)^2) per axis (rad), s_w the mean step std of the
    joints' vectors over their mean length, so a vector moves by about what noise_std of its step std moves it as a
    column on its own."""
    from learn.kinematics import POINTS
    from learn.stiffness import rigidly_moved
    joint_std = model.step_std()[0] if joint_std is None else joint_std
    vector = POINTS[JOINT.name][:, 0] == 0  # [fields] the joint's vectors (corners, extrusion), not its centre
    s_v = joint_std[JOINT.origin_slice].mean()
    s_w = (joint_std[JOINT.geometry_slice].unflatten(-1, (-1, 3))[vector].mean()
           / joint_state[..., JOINT.geometry_slice].unflatten(-1, (-1, 3))[..., vector, :].norm(dim=-1).mean())
    free = 1.0 - batch.static.joint_bc[..., JOINT.bc.slice("fixed")]  # [J, 1]
    shape = (*joint_state.shape[:-1], 3)
    v = noise_std * s_v * free * torch.randn(shape, generator=generator)
    omega = noise_std * s_w.detach() * free * torch.randn(shape, generator=generator)
    return rigidly_moved(joint_state, beam_state, v, omega, batch.index.beam_ends(), model.beam_middle)


def multistep_loss(model: Simulator, batch: GraphSet, horizon: int = 1, noise_std: float = 0.0,
                   stress_weight: float = 1.0, generator: torch.Generator | None = None,
                   geometry: str = "columns", carry: float = 1.0, chord_weight: float = 0.0,
                   final_weight: float = 0.0, noise_every_step: bool = False,
                   point_weight: float = 1.0, noise_shape: str = "columns",
                   noise_start: bool = True, item_power: float = 1.0) -> torch.Tensor:
    """Mean squared error of the states after 1..horizon steps from every start frame; `noise_std` (in units of
    the per-column step std) perturbs the start states so the model learns to correct its own drift;
    noise_every_step: also the state every later step starts from (the one the model reached), on the columns the
    network reads (geometry; stress too unless model.stress_input=false), so that each step is trained to bring a
    displaced state back to the FEA's next frame, not only to continue it. noise_shape "columns": each column
    displaced on its own (which also distorts the blocks); "rigid": every free joint moved rigidly and its beams with
    it (rigidly_displaced, the shape of the stiffness model's step), stress untouched. noise_start=false: the start
    states exact (the flat design the answer starts from is), only the later steps' displaced (with
    noise_every_step; without it there would be no noise at all, refused). A direct model
    (model.update=direct) answers every frame 1..F-1 from frame 0 in one pass: the horizon and the carry do not apply.
    geometry="columns": every state column in units of its step std (stress columns weighted by stress_weight);
    geometry="points": the geometry as the points it rebuilds (what the evaluation measures), their distance to
    the FEA's in units of the mean geometry step std, plus the stress columns as above; geometry="both": every
    column as "columns" does and the points' term on top at `point_weight` (the columns hold the blocks' orientation,
    which "points" weighs ~1/100 as much and lets drift over a rollout; the points place the blocks: session 42).
    carry: the fraction of the gradient carried back from each step into the state it started from. 1: through the
    whole unroll; 0: stopped between steps (the pushforward trick: every step is trained as a single step, from the
    state the model itself reached, to the FEA's next state); in between, a frame's error presses on the earlier
    steps at carry^(distance), so the early steps weigh less against the last ones. The loss value is the same.
    chord_weight > 0 adds the beams' half chords (beam_chords) in units of their FEA step std over the batch, weighted
    so: the turn of each beam relative to itself, which the absolute columns (whose step std is the motion of the
    whole grid) weigh little, and which carried by the lever arm is most of the position error (docs/learned_simulator.md).
    final_weight > 0 adds, at that weight, the state columns' error at the episode's final frame (where the unroll
    reaches it): the shape a designer asks for, and the frame whose error the evaluation's max over frames mostly is.
    item_power p > 1: the batch's loss is the power mean (mean_i L_i^p)^(1/p) of its items' losses L_i (each item's
    share of every term above, times the item count, so that at p = 1 their mean is the loss as above), which weighs
    an item's gradient by (L_i / the power mean)^(p-1): the designs the model answers worst weigh more (the tail of
    the evaluation's distribution, its p95, not its median)."""
    if geometry not in GEOMETRY_LOSSES:
        raise ValueError(f"loss geometry={geometry!r}: must be {' | '.join(GEOMETRY_LOSSES)}")
    F = len(batch.t)
    h = max(1, min(int(horizon), F - 1))
    S = F - h  # start frames 0 .. F-1-h
    if model.direct:  # every frame from frame 0 in one pass: no horizon, nothing carried between steps
        h, S = 1, 1
    j, b = batch.joint_state[:S], batch.beam_state[:S]
    joint_std, beam_std = model.step_std()  # global columns in global step stds, whatever frame the network reads
    rigid = noise_shape_checked(noise_shape) == "rigid"

    def displaced(j, b, nj, nb):
        """The states displaced by noise of noise_shape: rigid, or per column with the stds nj, nb (raw units)."""
        if rigid:
            return rigidly_displaced(model, j, b, batch, noise_std, generator, joint_std)
        return (j + nj * torch.randn(j.shape, generator=generator), b + nb * torch.randn(b.shape, generator=generator))

    noise_placement_checked(noise_std, noise_start, noise_every_step)
    if noise_std > 0 and noise_start:
        j, b = displaced(j, b, noise_std * joint_std, noise_std * beam_std)
    point_w = {"columns": 0.0, "points": 1.0, "both": float(point_weight)}[geometry]  # the point term's weight
    wj, wb = column_weights(JOINT, stress_weight), column_weights(BEAM, stress_weight)
    if geometry == "points":
        wj[JOINT.geometry_slice], wb[BEAM.geometry_slice] = 0.0, 0.0
    if point_w:
        scale = torch.cat([joint_std[JOINT.geometry_slice], beam_std[BEAM.geometry_slice]])
        scale = scale.mean()
    if chord_weight > 0:
        chord_std = beam_chords(batch.beam_state).diff(dim=0).flatten(0, -2).std(0).clamp_min(1e-3)
    reduce = item_reducer(batch, item_power)
    columns = lambda ej, eb: reduce(wj * ej ** 2, "joint", -2) + reduce(wb * eb ** 2, "beam", -2)  # noqa: E731
    every = noise_every_step and noise_std > 0 and not model.direct
    if every:  # in raw units: the step std of each column the network reads, 0 on the others
        read = float(model.args.get("stress_input", True))  # the stress columns' weight: 1 where they are read
        nj, nb = (noise_std * std * column_weights(spec, read) for std, spec in ((joint_std, JOINT), (beam_std, BEAM)))
    loss = torch.zeros(() if item_power == 1 else len(batch))
    for k in range(h):
        if every and k > 0:  # the state the model reached, displaced
            j, b = displaced(j, b, nj, nb)
        if carry == 0:
            j, b = j.detach(), b.detach()
        elif carry < 1:  # the same states forward, carry x the gradient backward
            j, b = carry * j + (1 - carry) * j.detach(), carry * b + (1 - carry) * b.detach()
        if model.direct:
            js, bs = unroll(model, j[0], b[0], batch.static, batch.t)
            j, b = js[1:], bs[1:]
            tj, tb = batch.joint_state[1:], batch.beam_state[1:]
        else:
            j, b = model.step(j, b, batch.static, batch.t[k:S + k])
            tj, tb = batch.joint_state[k + 1:S + k + 1], batch.beam_state[k + 1:S + k + 1]
        ej, eb = (j - tj) / joint_std, (b - tb) / beam_std
        loss = loss + columns(ej, eb)
        if chord_weight > 0:
            loss = loss + chord_weight * reduce(((beam_chords(b) - beam_chords(tb)) / chord_std).square(), "beam", -2)
        if point_w:
            d = (rebuild_all_points(j, b) - rebuild_all_points(tj, tb)) / scale
            loss = loss + point_w * reduce(d.square().sum(-1), "point", -1)
    loss = loss / h
    if final_weight > 0:  # the last step from the last start frame S-1 lands on the episode's final frame F-1
        loss = loss + final_weight * columns(ej[-1], eb[-1])
    return loss if item_power == 1 else loss.pow(item_power).mean().pow(1 / item_power)


ITEM_POWER_RANGE = (1.0, 16.0)  # item_power (conf/train.yaml): 1 = every item alike; 16 ~ the worst item's loss


def item_reducer(batch: GraphSet, item_power: float):
    """reduce(x, block, row_dim): x.mean() at item_power 1 (the loss as it always was); otherwise [n_items] each
    item's share of x.mean() times n_items (rows of `block`, joint | beam | point, along row_dim), whose mean is
    x.mean()."""
    if item_power == 1:
        return lambda x, block, row_dim: x.mean()
    n = len(batch)
    owner = {"joint": np.repeat(np.arange(n), np.diff(batch.joint_offsets)),
             "beam": np.repeat(np.arange(n), np.diff(batch.beam_offsets))}
    owner["point"] = point_owner(batch)
    owner = {k: torch.as_tensor(v, dtype=torch.long) for k, v in owner.items()}

    def reduce(x: torch.Tensor, block: str, row_dim: int) -> torch.Tensor:
        rows = x.movedim(row_dim, 0).reshape(x.shape[row_dim], -1).sum(1)  # [R] each row's sum
        return torch.zeros(n, dtype=rows.dtype).index_add(0, owner[block], rows) * (n / x.numel())
    return reduce


def point_owner(batch: GraphSet) -> np.ndarray:
    """[P] item of every point rebuilt from the batch's union graph (joints' points first, then beams')."""
    jo, bo = batch.joint_offsets, batch.beam_offsets
    joint_item = np.repeat(np.arange(len(batch)), np.diff(jo))
    beam_item = np.repeat(np.arange(len(batch)), np.diff(bo))
    return np.concatenate([np.repeat(joint_item, len(JOINT_POINTS)), np.repeat(beam_item, len(BEAM_POINTS))])


def fea_points(batch: GraphSet) -> np.ndarray:
    """[F, P, 3] FEA positions in the order rebuild_all_points gives for the batch's union graph."""
    joint_parts, beam_parts = [], []
    for f in batch.items:
        n_joint_points = f.incidence.n_joints * len(JOINT_POINTS)
        joint_parts.append(f.fea_points[:, :n_joint_points])
        beam_parts.append(f.fea_points[:, n_joint_points:])
    return np.concatenate(joint_parts + beam_parts, axis=1)


def max_per_item(err: np.ndarray, owner: np.ndarray, n: int) -> np.ndarray:
    """[..., P] point errors -> [..., n] the largest of each item's points (owner: point_owner)."""
    out = np.zeros((*err.shape[:-1], n))
    for idx in np.ndindex(err.shape[:-1]):
        np.maximum.at(out[idx], owner, err[idx])
    return out


def rollout_errors(model: Simulator, batch: GraphSet) -> tuple[np.ndarray, np.ndarray]:
    """Full rollouts from frame 0 of every item -> max and mean point error / design size, each [n_items, F]."""
    with torch.inference_mode():
        js, bs = unroll(model, batch.joint_state[0], batch.beam_state[0], batch.static, batch.t)
        pred = rebuild_all_points(js, bs).numpy()
    err = np.linalg.norm(pred - fea_points(batch), axis=-1)  # [F, P]
    owner = point_owner(batch)
    size = np.array([f.design_size for f in batch.items])
    n = len(batch)
    max_err = max_per_item(err, owner, n).T  # [n, F]
    counts = np.bincount(owner, minlength=n)
    mean_err = np.stack([np.bincount(owner, weights=e, minlength=n) / counts for e in err], axis=1)
    return max_err / size[:, None], mean_err / size[:, None]
