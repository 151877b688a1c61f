"""Several trained simulators answering as one (a deep ensemble): each member rolls the design out on its own
(with its own symmetry copies, learn.rollout.answer_unroll), the answer is the mean state of every frame, and
the members' disagreement (member_spread) is reported with every rollout. Measured (session 10, two seeds, 25
held-out designs): the ensemble beats the mean of its members on every design (x0.89) but only matches one network
averaged over the mirror at the same cost, and its spread ranks the designs by error no better than symmetric
copies do (Spearman 0.37), so it is not yet a validity signal (docs/learned_simulator.md, "Ensembles").

Members must be independent trainings on the same held-out designs (another seed, another core): a design that
one member trained on is not held out for the ensemble, so `load` refuses members whose splits differ.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from learn import checkpoint, publish
from learn.model import Simulator


class Ensemble(nn.Module):
    """Members' rollouts averaged frame by frame (learn.rollout.answer_unroll dispatches on this class)."""

    def __init__(self, members: list[Simulator]):
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs >= 2 members, got {len(members)}")
        self.members = nn.ModuleList(members)

    @property
    def kinematic(self) -> bool:  # learn.rollout.CompiledRollout: one trace per graph when any member needs it
        return any(m.kinematic for m in self.members)

    @property
    def stiffness(self) -> bool:  # learn.rollout.CompiledRollout: one trace per graph size when any member needs it
        return any(m.stiffness for m in self.members)

    @property
    def span_input(self) -> bool:  # learn.rollout.CompiledRollout: the beams' spans have the graph's size traced in
        return any(m.span_input for m in self.members)

    @property
    def args(self) -> dict:
        """What a report records of the model: the first member's model args with the member count, and every
        member's args (PCA sizes aside) when they differ."""
        plain = [{k: v for k, v in m.args.items() if k != "pca"} for m in self.members]
        out = {**self.members[0].args, "ensemble_members": len(self.members)}
        if any(a != plain[0] for a in plain[1:]):
            out["member_args"] = plain
        return out

    @property
    def n_parameters(self) -> int:
        return sum(m.n_parameters for m in self.members)

    def answer_with(self, rollout_rotations=None, rollout_mirror=None, rollout_lattice_turns=None) -> "Ensemble":
        for m in self.members:
            m.answer_with(rollout_rotations, rollout_mirror, rollout_lattice_turns)
        return self


def checkpoint_paths(value) -> list[str]:
    """conf `checkpoint`: one path, or a list of paths (an ensemble: 'checkpoint=[runs/a/best.pt,runs/b/best.pt]');
    a published model's directory (models/<name>) is its members, each checked against its card's sha256."""
    paths = [str(v) for v in ([value] if isinstance(value, (str, Path)) else value)]
    if not paths or not all(paths):
        raise ValueError(f"checkpoint={value!r}: give one checkpoint path or a list of them (an ensemble)")
    return [m for p in paths for m in (publish.members(p) if Path(p).is_dir() else [p])]


def load(paths: list[str | Path]) -> tuple[Simulator | Ensemble, dict]:
    """One checkpoint -> its Simulator; several -> their Ensemble. Returns the model and the first checkpoint
    (split, config, envelope). Members whose held-out designs (val, test) differ from the first's are refused."""
    if not paths:
        raise ValueError("checkpoint: give one checkpoint path or a list of them (an ensemble)")
    ckpts = [checkpoint.load(p) for p in paths]
    first = ckpts[0]
    for p, c in zip(paths[1:], ckpts[1:]):
        for part in ("val", "test"):
            if sorted(c["split"].get(part, [])) != sorted(first["split"].get(part, [])):
                raise ValueError(f"ensemble member {p}: its {part} designs differ from those of {paths[0]}; "
                                 "members must share their held-out designs (train them with the same split_from)")
    models = [checkpoint.model_from(c) for c in ckpts]
    return (models[0] if len(models) == 1 else Ensemble(models)), first


def member_spread(member_points: np.ndarray) -> np.ndarray:
    """[M, F, P, 3] the members' rebuilt points -> [F] the largest distance of a member's point from the
    members' mean (mm), per frame: how much the members disagree about the answer."""
    mean = member_points.mean(axis=0)
    return np.linalg.norm(member_points - mean, axis=-1).max(axis=(0, 2))


def members_of(model: Simulator | Ensemble) -> list[Simulator]:
    return list(model.members) if isinstance(model, Ensemble) else [model]


def stack_mean(parts: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.stack([p[0] for p in parts]).mean(0), torch.stack([p[1] for p in parts]).mean(0)
