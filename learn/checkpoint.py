"""Checkpoints: plain tensors and containers only (torch.load(weights_only=True)), written atomically."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from learn.model import Simulator

FORMAT = "morphsim.learn/1"


def save(path: str | Path, model: Simulator, **extra) -> Path:
    """state_dict (PCA and normalisers included) + model args + anything plain in `extra` (config, split, ...)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, "model_args": model.args, "state_dict": model.state_dict(), **extra}, tmp)
    os.replace(tmp, path)
    return path


def load(path: str | Path) -> dict:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if ckpt.get("format") != FORMAT:
        raise ValueError(f"{path}: checkpoint format {ckpt.get('format')!r}; expected {FORMAT!r}")
    return ckpt


def model_from(ckpt: dict) -> Simulator:
    model = Simulator(ckpt["model_args"])
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


def load_model(path: str | Path) -> Simulator:
    return model_from(load(path))
