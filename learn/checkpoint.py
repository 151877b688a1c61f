"""Checkpoints: plain tensors and containers only (torch.load(weights_only=True)), written atomically."""
from __future__ import annotations

from pathlib import Path

import torch

from data_schema import atomic
from learn.checks import integer_in
from learn.model import Simulator

FORMAT = "morphsim.learn/1"


def save(path: str | Path, model: Simulator, **extra) -> Path:
    """state_dict (PCA and normalisers included) + model args + anything plain in `extra` (config, split, ...)."""
    with atomic.replacing(path) as tmp:
        torch.save({"format": FORMAT, "model_args": model.args, "state_dict": model.state_dict(), **extra}, tmp)
    return Path(path)


class RunDirInUse(atomic.InUse):
    pass


def run_lock(run_dir: str | Path):
    """Hold run_dir/.lock (the owner's pid) while training, so a second run into the same directory stops with a
    clear error instead of interleaving checkpoints; a lock whose process is gone is taken over."""
    return atomic.held(Path(run_dir) / ".lock", f"run_dir {run_dir}", RunDirInUse)


def load(path: str | Path) -> dict:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if ckpt.get("format") != FORMAT:
        raise ValueError(f"{path}: checkpoint format {ckpt.get('format')!r}; expected {FORMAT!r}")
    return ckpt


SPLIT_FILE_SUFFIXES = (".yaml", ".yml", ".json")


def split_of(source: str | Path) -> dict[str, list[str]]:
    """The held-out designs to keep: the split stored in a checkpoint (.pt), or a split file (.yaml / .json,
    conf/held_out/) that lists episode file names under `val` and `test` (and optionally `train`); episodes it does not
    list join train (learn.dataset.extend_split). A file outlives the runs and the machine that made it."""
    path = Path(source)
    if path.suffix not in SPLIT_FILE_SUFFIXES:
        return load(path)["split"]
    from omegaconf import OmegaConf  # yaml is a superset of json

    listed = OmegaConf.to_container(OmegaConf.load(path))
    if not isinstance(listed, dict) or not {"val", "test"} <= set(listed) or set(listed) - {"train", "val", "test"}:
        raise ValueError(f"split file {path}: must map val and test (and optionally train) to lists of episode file "
                         f"names; has {sorted(listed) if isinstance(listed, dict) else type(listed).__name__}")
    for part, names in listed.items():
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError(f"split file {path}: {part} must be a list of episode file names")
    seen = [n for names in listed.values() for n in names]
    if len(seen) != len(set(seen)):
        twice = sorted({n for n in seen if seen.count(n) > 1})
        raise ValueError(f"split file {path}: episodes listed twice: {twice[:5]}")
    return {"train": [], **listed}


def model_from(ckpt: dict) -> Simulator:
    model = Simulator(ckpt["model_args"])
    state = dict(ckpt["state_dict"])
    for step, delta in (("joint_step", "joint_delta"), ("beam_step", "beam_delta")):
        if model.rotated and f"{step}.std" not in state:  # a rotated model saved before session 31: its loss read the
            state.update({f"{step}.{k}": state[f"{delta}.{k}"] for k in ("mean", "std")})  # deltas' stds
    model.load_state_dict(state)
    return model.eval()


def first_passes(ckpt: dict, n: int) -> dict:
    """The checkpoint with its model cut to the first n network passes of a step (the predictor and n - 1
    correctors; conf/train.yaml init_passes): a faster model to fine-tune from a slower one. Each pass is a core of its
    own (learn.model.Simulator.correctors), so the passes kept are the same networks and the rest are dropped."""
    have = int(ckpt["model_args"].get("passes", 1))
    n = integer_in(n, "init_passes", 1, have, f"network passes kept of init_from's {have}; null: all")
    dropped = tuple(f"correctors.{i}." for i in range(n - 1, have - 1))
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith(dropped)}
    return {**ckpt, "model_args": {**ckpt["model_args"], "passes": n}, "state_dict": state}


def load_model(path: str | Path) -> Simulator:
    return model_from(load(path))
