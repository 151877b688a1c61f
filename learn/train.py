"""Train the learned simulator: `.venv/bin/python -m learn.train [key=value ...]` (conf/train.yaml); resumable."""
from __future__ import annotations

import csv
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from learn import checkpoint, publish
from learn.checks import integer_in, number_in
from learn.conditions import envelope
from learn.dataset import (GraphSet, TurnedSet, augment, augment_angles, episode_paths, extend_split,
                           extra_dirs_checked, load_features, split_missing_checked, split_names)
from learn.features import EpisodeFeatures
from learn.gn import dropout_checked, fraction_checked
from learn.metrics import (ITEM_POWER_RANGE, multistep_loss, noise_placement_checked, noise_shape_checked,
                           rollout_errors)
from learn.model import (Simulator, passes_checked, rollout_lattice_turns_checked,
                         rollout_rotations_checked, term_retention)
from learn.stiffness import beam_middle_checked
from learn.rollout import input_floor

log = logging.getLogger(__name__)
LAST, BEST = "last.pt", "best.pt"


def augmented(features: list, cfg, rotations: int | None = None) -> list:
    """The training designs as conf/train.yaml augments them (learn.dataset.augment): rotations (cfg.rotations
    unless given), mirror, lattice_turns."""
    return augment(features, cfg.rotations if rotations is None else rotations, cfg.seed, flag_checked(cfg, "mirror"),
                   cfg.get("lattice_turns", 1))


def training_sets(designs: list, cfg) -> tuple[GraphSet | TurnedSet, Callable]:
    """-> (what train_epoch draws batches from, the blocks the PCA and normalisers are fitted on: Simulator.fit_blocks).
    rotations_stored=true: one GraphSet of every augmented copy, both. rotations_stored=false (the default): the
    labelled copies once, turned per batch by the angles augment would draw (TurnedSet: the same batches, 1/rotations
    of the memory); the fit turns them a block at a time. rotations_redraw: the labelled copies once, turned per
    batch by new angles (the fit: the angles augment draws)."""
    stored = flag_checked(cfg, "rotations_stored")
    redraw = cfg.get("rotations_redraw", False)
    if stored or cfg.rotations <= 1:
        fit_set = GraphSet.build(augmented(designs, cfg))
        return (GraphSet.build(augmented(designs, cfg, rotations=1)) if redraw else fit_set), fit_set.fit_blocks()
    base = GraphSet.build(augmented(designs, cfg, rotations=1))
    turned = TurnedSet(base, augment_angles(len(base), cfg.rotations, cfg.seed))
    return (base if redraw else turned), turned.fit_blocks()


def model_args(cfg_model: DictConfig) -> dict:
    return {"core": str(cfg_model.core), "latent": int(cfg_model.latent),
            "widths": [int(w) for w in cfg_model.widths], "time_input": bool(cfg_model.time_input),
            "bc_position": str(cfg_model.get("bc_position", "reference")),
            "layer_norm": bool(cfg_model.get("layer_norm", False)),
            "stress_input": bool(cfg_model.get("stress_input", True)), "n_blocks": int(cfg_model.get("n_blocks", 2)),
            "global_latent": int(cfg_model.get("global_latent", 0)),
            "activation": str(cfg_model.get("activation", "relu")),
            "dropout": dropout_checked(cfg_model.get("dropout", 0.0)),
            "pin_fixed_joint": bool(cfg_model.get("pin_fixed_joint", False)),
            "frame": str(cfg_model.get("frame", "global")), "update": str(cfg_model.get("update", "additive")),
            "beam_middle": beam_middle_checked(cfg_model.get("beam_middle", "mean")),
            "passes": passes_checked(cfg_model.get("passes", 1)),
            "span_input": bool(cfg_model.get("span_input", False)),
            "rollout_rotations": rollout_rotations_checked(cfg_model.get("rollout_rotations", 1),
                                                           "model.rollout_rotations"),
            "rollout_mirror": bool(cfg_model.get("rollout_mirror", False)),
            "rollout_lattice_turns": rollout_lattice_turns_checked(
                cfg_model.get("rollout_lattice_turns", 1), "model.rollout_lattice_turns",
                str(cfg_model.get("update", "additive")) == "kinematic")}


def retention_of(cfg: DictConfig):
    """pca_retention as a float or a plain {kind: float} (learn.model.term_retention checks it)."""
    value = cfg.pca_retention
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


SCHEDULES = ("step", "cosine")


def schedule_checked(name) -> str:
    if name not in SCHEDULES:
        raise ValueError(f"optim.schedule={name!r}: must be one of {' | '.join(SCHEDULES)}")
    return name


def learning_rate(cfg: DictConfig, epoch: int) -> float:
    """step (the thesis): the base rate, times lr_drop_factor from lr_drop_at * epochs on; cosine: from the base
    rate down to base * lr_drop_factor along half a cosine over the epochs (lr_drop_at unused)."""
    base, factor = float(cfg.optim.lr), float(cfg.optim.lr_drop_factor)
    if schedule_checked(cfg.optim.get("schedule", "step")) == "cosine":
        done = min(epoch / max(int(cfg.epochs) - 1, 1), 1.0)
        return base * (factor + (1.0 - factor) * 0.5 * (1.0 + math.cos(math.pi * done)))
    drop = epoch >= int(cfg.optim.lr_drop_at * cfg.epochs)
    return base * (factor if drop else 1.0)


def weight_decay_checked(decay) -> float:
    return fraction_checked(decay, "optim.weight_decay")


def optimiser(model: Simulator, optim: DictConfig) -> torch.optim.Adam:
    """Adam; with optim.decoupled_weight_decay (AdamW, Loshchilov & Hutter 2019) every weight shrinks by
    lr * weight_decay per step apart from the gradient's moments; without it the decay is an L2 term added to the
    gradient (and so divided by Adam's running scale). Configs written before the option read as L2."""
    return torch.optim.Adam(model.parameters(), lr=optim.lr, weight_decay=weight_decay_checked(optim.weight_decay),
                            decoupled_weight_decay=bool(optim.get("decoupled_weight_decay", False)))


def ema_decay_checked(decay) -> float:
    return fraction_checked(decay, "optim.ema_decay")


def weight_average(model: Simulator, decay: float) -> AveragedModel | None:
    """An exponential moving average of the model's weights, updated after every optimiser step:
    w_avg <- decay * w_avg + (1 - decay) * w (torch.optim.swa_utils; the PCA and normaliser buffers are the model's,
    fixed). None when decay is 0 (off)."""
    if ema_decay_checked(decay) == 0:
        return None
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(float(decay)), use_buffers=False)


PRECISIONS = ("fp32", "bf16", "auto")
NATIVE_BF16 = ("avx512_bf16", "amx_bf16")  # /proc/cpuinfo flags of CPUs that multiply bfloat16 matrices natively


def precision_checked(name) -> str:
    if name not in PRECISIONS:
        raise ValueError(f"precision={name!r}: must be one of {' | '.join(PRECISIONS)} (bf16: the training loss's "
                         "forward pass in bfloat16 autocast; validation and every answer stay float32; auto: bf16 "
                         "where the CPU multiplies bfloat16 natively, else fp32)")
    return name


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> set[str]:
    """The CPU's feature flags (empty where /proc/cpuinfo is not there)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return set()
    return {f for line in text.splitlines() if line.startswith("flags") for f in line.split(":", 1)[1].split()}


def precision_of(name, flags: set[str] | None = None) -> str:
    """precision as trained: fp32 | bf16, auto resolved by the CPU's flags. Without native bfloat16 (AVX2 only: an
    EPYC 7003, session 28) a bfloat16 matrix product is emulated, 20x slower than float32 (4096 x 256 @ 256 x 128,
    one thread: 180 vs 8.7 ms), so auto picks fp32 there; with AVX512-BF16 bf16 trains alike at 1.25x the speed."""
    name = precision_checked(name)
    if name != "auto":
        return name
    return "bf16" if set(NATIVE_BF16) & (cpu_flags() if flags is None else flags) else "fp32"


def loss_terms(cfg: DictConfig) -> dict:
    """What the loss weighs besides the state columns (learn.metrics.multistep_loss keywords), for training and
    validation alike."""
    terms = {"geometry": cfg.get("loss_geometry", "columns"),
             "point_weight": weight_checked(cfg, "point_weight", "no point term (loss_geometry=both)"),
             "chord_weight": weight_checked(cfg, "chord_weight", "no chord term"),
             "final_weight": weight_checked(cfg, "final_weight", "the final frame weighs as every other"),
             "noise_every_step": flag_checked(cfg, "noise_every_step"),
             "noise_start": flag_checked(cfg, "noise_start", absent=True),
             "noise_shape": noise_shape_checked(cfg.get("noise_shape", "columns"))}
    noise_placement_checked(cfg.get("noise_std", 0.0), terms["noise_start"], terms["noise_every_step"])
    return terms


AUTO_ROTATIONS = 10  # rotations: auto for a model that reads the global frame (the thesis' augmentation)


def rotations_of(cfg: DictConfig) -> int:
    """conf/train.yaml rotations: a count >= 0, or auto: AUTO_ROTATIONS for model.frame=global, 1 (none) for local and
    fixed, whose inputs are exactly invariant to turning a design about z (each block read in its own frame, or in
    the fixed joint's; gravity is along z), so that a turned copy is the same sample again, not new data."""
    value = cfg.get("rotations", 1)
    if value == "auto":
        return AUTO_ROTATIONS if cfg.model.get("frame", "global") == "global" else 1
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"rotations={value!r}: must be a count >= 0 or auto (10 in the global frame, 1 in the "
                         "local and fixed ones, which turning about z does not change)")
    return value


def flag_checked(cfg: DictConfig, name: str, absent: bool = False) -> bool:
    """A true/false key of conf/train.yaml (`absent` when absent, as in configs saved before it), else an error
    naming it."""
    value = cfg.get(name, absent)
    if not isinstance(value, bool):
        raise ValueError(f"{name}={value!r}: must be true or false")
    return value


def gradient_carry(cfg: DictConfig) -> float:
    """conf/train.yaml rollout_gradient as the fraction of the gradient a step passes back to the state it started
    from: through = 1, stop = 0, or a number in between; else an error naming the key."""
    value = cfg.get("rollout_gradient", "through")
    named = {"through": 1.0, "stop": 0.0}
    if isinstance(value, str) and value in named:
        return named[value]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
        raise ValueError(f"rollout_gradient={value!r}: must be through | stop | a number in [0, 1] "
                         "(the fraction of the gradient carried back between steps)")
    return float(value)


def extra_designs(dirs: list[Path], names: set[str], key: str) -> list[EpisodeFeatures]:
    """The episodes of conf/train.yaml's train_extra_dirs (all training designs, never held out, e.g. extra designs
    of one region of the design space) or val_extra_dirs (all validation designs, never trained on: more designs for
    the monitor than the split's few). Their file names must differ from data_dir's and each other's (a split holds
    names, and a name read twice could be one design trained on and validated on): generate them with another
    `start=`. `names`: the names read so far, added to."""
    extra: list[EpisodeFeatures] = []
    for d in dirs:
        for f in load_features(episode_paths(d)):
            if f.name in names:
                raise ValueError(f"{key}: {d}/{f.name} has the name of an episode already read (data_dir or an "
                                 "earlier extra directory); generate extra designs with another start=")
            names.add(f.name)
            extra.append(f)
    return extra


def weight_checked(cfg: DictConfig, name: str, meaning: str) -> float:
    """A loss weight from conf/train.yaml: a number in [0, 100], else an error naming the key."""
    return number_in(cfg.get(name, 0.0), name, 0, 100, f"0 = {meaning}")


MONITORS = ("val_rollout", "val_loss")


def run_options_checked(cfg: DictConfig) -> None:
    """The run's counts, rates and the monitor (conf/train.yaml, conf/optim/), each refused with its key and range
    before any data are read: a bad one would otherwise stop the run an epoch in (monitor), be read as something
    else (a negative noise_std or batch_size as none) or train with a negative loss weight (stress_weight)."""
    item_power_checked(cfg)
    integer_in(cfg.epochs, "epochs", 0, 10**6, "passes over the augmented training set; 0 = the run prepared "
               "(split, PCA, normalisers, start weights) without one")
    if cfg.batch_size is not None:
        integer_in(cfg.batch_size, "batch_size", 0, 10**9, "episode rotations per mini-batch; 0 = the whole set")
    integer_in(cfg.patience, "patience", 1, 10**6, "epochs without improvement before stopping")
    integer_in(cfg.rollout_horizon, "rollout_horizon", 1, 1000, "steps unrolled per sample; at most an episode's")
    integer_in(cfg.checkpoint_every, "checkpoint_every", 1, 10**6, "epochs between last.pt saves")
    integer_in(cfg.log_every, "log_every", 1, 10**6, "epochs between log lines")
    if cfg.monitor not in MONITORS:
        raise ValueError(f"monitor={cfg.monitor!r}: must be one of {' | '.join(MONITORS)}")
    number_in(cfg.get("noise_std", 0.0), "noise_std", 0, 10, "input noise in step stds; 0 = none")
    weight_checked(cfg, "stress_weight", "stress not fitted")
    weight_checked(cfg, "teacher_weight", "no one-step term")
    number_in(cfg.optim.lr, "optim.lr", 0, math.inf, "Adam's base learning rate", low_open=True)
    number_in(cfg.optim.lr_drop_factor, "optim.lr_drop_factor", 0, 1, "the rate's factor late; 1 = no drop",
              low_open=True)
    number_in(cfg.optim.lr_drop_at, "optim.lr_drop_at", 0, 1, "the fraction of the epochs the drop comes at")
    number_in(cfg.optim.get("grad_clip", 0.0), "optim.grad_clip", 0, math.inf, "the largest gradient norm; 0 = off")
    if cfg.get("time_limit_min") is not None:
        number_in(cfg.time_limit_min, "time_limit_min", 0, math.inf, "minutes before a resumable pause",
                  low_open=True)


def training_loss(model: Simulator, batch: GraphSet, cfg: DictConfig, generator: torch.Generator) -> torch.Tensor:
    """The loss a training step descends: the multi-step loss over `rollout_horizon` steps, plus, at
    `teacher_weight`, the one-step loss from every FEA frame (teacher forcing), which holds each step to the FEA's
    next state, where the rollout loss alone lets the steps trade their errors (docs/learned_simulator.md,
    session 18)."""
    terms = {**loss_terms(cfg), "item_power": item_power_checked(cfg)}  # the power: training's alone (val_loss: 1)
    loss = multistep_loss(model, batch, cfg.rollout_horizon, cfg.noise_std, cfg.stress_weight, generator,
                          carry=gradient_carry(cfg), **terms)
    teacher = weight_checked(cfg, "teacher_weight", "no one-step term")
    if teacher > 0:
        loss = loss + teacher * multistep_loss(model, batch, 1, cfg.noise_std, cfg.stress_weight, generator, **terms)
    return loss


def item_power_checked(cfg: DictConfig) -> float:
    """conf/train.yaml item_power: the power mean of the batch items' losses, in ITEM_POWER_RANGE."""
    return number_in(cfg.get("item_power", 1.0), "item_power", *ITEM_POWER_RANGE,
                     "1 = the plain mean over a batch's items; > 1 weighs the worst-answered items more")


def train_epoch(model: Simulator, opt: torch.optim.Optimizer, train_set: GraphSet, cfg: DictConfig,
                epoch: int, average: AveragedModel | None = None) -> list[float]:
    """One pass over shuffled mini-batches at the epoch's learning rate (and the weight average after every step,
    when there is one); the batch losses."""
    for group in opt.param_groups:
        group["lr"] = learning_rate(cfg, epoch)
    gen = torch.Generator().manual_seed(int(cfg.seed) * 100003 + epoch)
    losses = []
    redrawn = cfg.rotations if cfg.get("rotations_redraw", False) else 1  # else augment turned the set once
    # bf16: matrix products of the forward pass in bfloat16 (CPU autocast); the states, the loss and the weights
    # stay float32, so the update dG is rounded to bfloat16 but never accumulated in it
    bf16 = precision_of(cfg.get("precision", "fp32")) == "bf16"
    for batch in train_set.batches(cfg.batch_size, gen, redrawn):
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss = training_loss(model, batch, cfg, gen)
        opt.zero_grad()
        loss.backward()
        if cfg.optim.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.optim.grad_clip)
        opt.step()
        if average is not None:
            average.update_parameters(model)
        losses.append(float(loss.detach()))
    return losses


def worst_rollout_errors(model: Simulator, data: GraphSet) -> np.ndarray:
    """[items] each design's max error / design size over the frames of its rollout, the model in eval mode."""
    model.eval()
    max_err, _ = rollout_errors(model, data)
    model.train()
    return max_err.max(axis=1)


def evaluate_split(model: Simulator, data: GraphSet, cfg: DictConfig) -> dict:
    model.eval()
    with torch.no_grad():
        loss = float(multistep_loss(model, data, cfg.rollout_horizon, 0.0, cfg.stress_weight, **loss_terms(cfg)))
    worst = worst_rollout_errors(model, data)
    return {"val_loss": loss, "val_rollout": float(worst.mean()), "val_rollout_worst": float(worst.max())}


def fit_rollout(model: Simulator, probe: GraphSet | None) -> dict:
    """The validation rollout measure on training designs (`train_probe` of them, as labelled): beside val_rollout
    it says whether a run is limited by how well it fits (both high) or by how it generalises (a gap)."""
    return {} if probe is None else {"train_rollout": float(worst_rollout_errors(model, probe).mean())}


def append_result(path: str | Path, row: dict) -> None:
    """One row per run; the header is written by the first run."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not path.exists() or path.stat().st_size == 0
    with path.open("a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(row))
        if new:
            w.writeheader()
        w.writerow(row)


def train(cfg: DictConfig) -> dict:
    """Fit PCA and normalisers on the training split, train with early stopping; returns the run summary."""
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with checkpoint.run_lock(run_dir):
        return _train(cfg, run_dir)


def _train(cfg: DictConfig, run_dir: Path) -> dict:
    if cfg.get("init_required") and not cfg.get("init_from"):  # an experiment that carries a trained model on
        raise ValueError("init_from: required by this experiment: the trained checkpoint it carries on, e.g. "
                         "init_from=runs/<start>/best.pt")
    if cfg.get("init_passes") is not None and not cfg.get("init_from"):
        raise ValueError(f"init_passes={cfg.init_passes!r}: needs init_from (the checkpoint whose first passes are kept)")
    term_retention(retention_of(cfg))  # a bad value stops here, before any data is read
    ema_decay_checked(cfg.optim.get("ema_decay", 0.0))
    weight_decay_checked(cfg.optim.weight_decay)
    schedule_checked(cfg.optim.get("schedule", "step"))
    precision = precision_of(cfg.get("precision", "fp32"))
    if cfg.get("precision", "fp32") == "auto":  # the checkpoint's config records what was used
        log.info("precision auto: %s (native bfloat16 %s)", precision, "found" if precision == "bf16" else "absent")
        cfg.precision = precision
    cfg.rotations = rotations_of(cfg)  # the checkpoint's config records the count auto resolved to
    gradient_carry(cfg)
    split_missing_checked(cfg.get("split_missing", "error"))
    n_probe = integer_in(cfg.get("train_probe", 0), "train_probe", 0, 10**6,
                         "training designs whose rollout error is logged every epoch; 0 = none")
    run_options_checked(cfg)
    loss_terms(cfg)  # its weights checked before any data are read
    last = run_dir / LAST
    resumed = checkpoint.load(last) if cfg.resume and last.exists() else None
    if resumed is not None and resumed.get("finished"):
        log.info("run in %s has already finished (epoch %d); nothing to do", run_dir, resumed["epoch"])
        return resumed["summary"]

    init = None if resumed or not cfg.get("init_from") else checkpoint.load(
        publish.one_checkpoint(cfg.init_from, "init_from"))  # a run's checkpoint or a published models/<name>
    if init and cfg.get("init_passes") is not None:  # a faster model from a slower one: its first passes only
        init = checkpoint.first_passes(init, cfg.init_passes)
    extra_dirs = extra_dirs_checked(cfg.get("train_extra_dirs"))  # before any episode is read
    val_dirs = extra_dirs_checked(cfg.get("val_extra_dirs"), "val_extra_dirs", "make validation-data")
    features = load_features(episode_paths(cfg.data_dir))
    names = {f.name for f in features}
    extra = extra_designs(extra_dirs, names, "train_extra_dirs")
    val_extra = extra_designs(val_dirs, names, "val_extra_dirs")  # kept out of the split: evaluations never see them
    by_name = {f.name: f for f in features + extra}
    if resumed:
        split = resumed["split"]
    elif cfg.get("split_from") or init:  # keep an earlier run's held-out designs; new episodes join train
        kept = (checkpoint.split_of(publish.one_checkpoint(cfg.split_from, "split_from")) if cfg.get("split_from")
                else init["split"])
        split = extend_split(kept, by_name, cfg.get("split_missing", "error"))
        extra_names = {f.name for f in extra}  # join after the cut below, once (session 44: they came in twice)
        split = {**split, "train": [n for n in split["train"] if n not in extra_names]}
    else:
        split = split_names(features, cfg.split, cfg.seed)
    missing = [n for s in split.values() for n in s if n not in by_name]
    if missing:
        raise FileNotFoundError(f"episodes of the checkpoint's split are missing from {cfg.data_dir}: {missing[:5]}")
    if not resumed and cfg.get("train_designs") is not None:  # a resumed split is already cut
        keep = integer_in(cfg.train_designs, "train_designs", 1, len(split["train"]),
                          f"the first of the split's {len(split['train'])} training designs to train on; null: all")
        split = {**split, "train": split["train"][:keep]}
    if not resumed and extra:  # after the cut: train_designs counts data_dir's designs only
        split = {**split, "train": split["train"] + [f.name for f in extra]}
        log.info("train_extra_dirs: %d more training designs", len(extra))
    log.info("episodes: %s", {s: len(v) for s, v in split.items()})
    train_envelope = envelope([by_name[n].conditions for n in split["train"]])  # physics the graphs do not carry
    train_set, fit_blocks = training_sets([by_name[n] for n in split["train"]], cfg)
    if val_extra:
        log.info("val_extra_dirs: %d more validation designs (the monitor's; not in the split)", len(val_extra))
    val_set = GraphSet.build([by_name[n] for n in split["val"]] + val_extra or [by_name[n] for n in split["train"]])
    probe = GraphSet.build([by_name[n] for n in split["train"][:n_probe]]) if n_probe and split["train"] else None

    torch.manual_seed(cfg.seed)
    if resumed or init:  # init_from: its weights, PCA, normalisers and model args; a fresh optimiser and history
        model = checkpoint.model_from(resumed or init).train()
        if init:
            log.info("initialised from %s (epoch %d); model args from it, conf model ignored", cfg.init_from,
                     init["epoch"])
    else:
        model = Simulator.fit_blocks(model_args(cfg.model), fit_blocks, retention_of(cfg), cfg.delta_std_floor)
    log.info("PCA dims %s; %d parameters", {t: p.k for t, p in model.pca.items()}, model.n_parameters)
    floor = max(float(input_floor(model, f).max() / f.design_size) for f in val_set.items)
    log.info("input floor: the PCA'd geometry inputs rebuild the validation designs' points within %.3g %% of the "
             "design size", 100 * floor)
    opt = optimiser(model, cfg.optim)
    average = weight_average(model, cfg.optim.get("ema_decay", 0.0))
    if resumed and "trained_state_dict" in resumed:  # state_dict holds the average; the optimiser's weights apart
        model.load_state_dict(resumed["trained_state_dict"])
        if average is not None:
            average.module.load_state_dict(resumed["state_dict"])
            average.n_averaged.fill_(int(resumed["n_averaged"]))
    answer = model if average is None else average.module  # what validation, best.pt and rollouts use
    history, best, bad, start = [], math.inf, 0, 0
    if resumed:
        opt.load_state_dict(resumed["optimizer"])
        history, best, bad, start = resumed["history"], resumed["best"], resumed["bad_epochs"], resumed["epoch"] + 1
        log.info("resumed from %s at epoch %d", last, start)
    config = OmegaConf.to_container(cfg, resolve=True)
    if resumed or init:  # the network is the checkpoint's: record its model settings, not the conf's; say what differs
        # the checkpoint's settings as the network reads them: a key it predates takes the model's default
        stored = model_args(OmegaConf.create({k: v for k, v in (resumed or init)["model_args"].items() if k != "pca"}))
        asked = model_args(cfg.model)
        differ = sorted(k for k in asked if asked[k] != stored[k])
        if differ:
            log.warning("%s keeps the checkpoint's model; conf model differs in %s (ignored)",
                        "resuming" if resumed else "init_from",
                        ", ".join(f"{k} (conf {asked[k]!r}, checkpoint {stored[k]!r})" for k in differ))
        config["model"] = {**config["model"], **{k: stored[k] for k in differ}}
    t0 = time.perf_counter() - (history[-1]["seconds"] if history else 0.0)

    def save(path: Path, epoch: int, finished: bool = False, summary: dict | None = None) -> None:
        averaged = {} if average is None else {"trained_state_dict": model.state_dict(),
                                               "n_averaged": int(average.n_averaged)}
        checkpoint.save(path, answer, optimizer=opt.state_dict(), config=config, split=split, envelope=train_envelope,
                        epoch=epoch, best=best, bad_epochs=bad, history=history, finished=finished,
                        summary=summary or {}, **averaged)

    epoch = start - 1
    stop_reason, diverged = "epochs", False
    for epoch in range(start, int(cfg.epochs)):
        losses = train_epoch(model, opt, train_set, cfg, epoch, average)
        row = {"epoch": epoch, "lr": learning_rate(cfg, epoch), "train_loss": float(np.mean(losses)),
               **evaluate_split(answer, val_set, cfg), **fit_rollout(answer, probe),
               "seconds": time.perf_counter() - t0}
        history.append(row)
        if not all(math.isfinite(row[k]) for k in ("train_loss", "val_loss", cfg.monitor)):
            diverged = True
            kept = ("last.pt and best.pt keep the best finite epoch's weights" if math.isfinite(best) else
                    "no finite epoch: nothing saved")
            stop_reason = (f"diverged at epoch {epoch}: non-finite loss (train {row['train_loss']:.3g}, val "
                           f"{row['val_loss']:.3g}); {kept}")
            log.error("%s", stop_reason)
            if math.isfinite(best):  # best.pt holds it: never leave non-finite weights as the run's answer
                # (a run resumed from a parked last.pt alone, scripts/record.py, has no best.pt: its last.pt holds
                # the last finite epoch saved)
                restored = checkpoint.load(run_dir / BEST if (run_dir / BEST).exists() else run_dir / LAST)
                answer.load_state_dict(restored["state_dict"])
                model.load_state_dict(restored.get("trained_state_dict", restored["state_dict"]))
            break
        if row[cfg.monitor] < best:
            best, bad = row[cfg.monitor], 0
            save(run_dir / BEST, epoch)
        else:
            bad += 1
        if epoch % int(cfg.log_every) == 0 or epoch == int(cfg.epochs) - 1:
            fit = f" train_rollout {row['train_rollout']:.4f}" if "train_rollout" in row else ""
            log.info("epoch %d lr %.1e train %.4g val %.4g val_rollout %.4f (best %.4f)%s %.0fs", epoch, row["lr"],
                     row["train_loss"], row["val_loss"], row["val_rollout"], best, fit, row["seconds"])
        if bad >= int(cfg.patience):
            stop_reason = f"early stop: no {cfg.monitor} improvement in {bad} epochs"
            break
        epoch_s = row["seconds"] - (history[-2]["seconds"] if len(history) > 1 else 0.0)
        last_epoch = epoch + 1 >= int(cfg.epochs)  # no next epoch to pause before: the run is finished
        if cfg.get("time_limit_min") and not last_epoch and row["seconds"] + epoch_s > 60 * float(cfg.time_limit_min):
            stop_reason = f"time limit {cfg.time_limit_min} min"  # the next epoch, as long as this one, would end
            break                                                 # past it: paused now, not killed mid-epoch
        if (epoch + 1) % int(cfg.checkpoint_every) == 0:
            save(last, epoch)

    best_row = min(history, key=lambda r: r[cfg.monitor]) if history else {}
    summary = {"run_dir": str(run_dir), "stop": stop_reason, "epochs_run": epoch + 1,
               "best_epoch": best_row.get("epoch", -1), "monitor": cfg.monitor, "best": best,
               "best_val_loss": best_row.get("val_loss", math.nan),
               "best_val_rollout": best_row.get("val_rollout", math.nan),
               "train_rollout_at_best": best_row.get("train_rollout", math.nan),
               "train_seconds": history[-1]["seconds"] if history else 0.0, "n_parameters": model.n_parameters,
               "input_floor": floor,
               "core": model.args["core"], "latent": model.args["latent"],
               "widths": "x".join(map(str, model.args["widths"])),
               "pca_dims": " ".join(f"{t}={p.k}" for t, p in model.pca.items())}
    # a time limit is an interruption, not an end: re-run with a larger time_limit_min to continue
    finished = not stop_reason.startswith("time limit")
    if not diverged or math.isfinite(best):  # no non-finite weights are saved
        save(last, epoch, finished=finished, summary=summary)
    log.info("%s (%s): %s", "done" if finished else "paused, resumable", stop_reason, summary)
    if cfg.get("results_csv"):
        append_result(cfg.results_csv, {**summary, "overrides": cfg.get("overrides_label", "")})
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> None:
    train(cfg)


if __name__ == "__main__":
    main()
