"""Published models: a trained checkpoint, or an ensemble's members, kept in the repository beside a card.

`.venv/bin/python -m learn.publish 'checkpoints=[runs/a/last_e3.pt,runs/b/last_e3.pt]' name=pair1040
report=reports/s52_ft5_pair/102` (conf/publish.yaml; `make publish`) writes models/pair1040/:

- member_0.pt, member_1.pt: what answers (weights, PCA, normalisers, model args) and what it was trained with (config,
  split, envelope, history); the optimiser's moments and a weight average's raw weights, which only resuming reads,
  are left out. Still loadable with torch.load(weights_only=True), still a start for `init_from`.
- card.json: each member's sha256 and bytes, its training data and start, and the figures of the named evaluation;
- report.json: that evaluation's report, every design in it, so that a later model is compared with this one design
  by design (learn.compare 'reports=[models/<name>/report.json,...]') on a machine that never evaluated it.

runs/ live on the machine that trained them; a fresh machine has none, and every result they carried was lost with
them ten times (sessions 21-53). A committed directory is not. Wherever a checkpoint is read
(learn.ensemble.checkpoint_paths: learn.evaluate, learn.predict, make reference-evaluate), `models/<name>` stands for
its members, each checked against the card's sha256 first.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import logging
import re
import secrets
import shutil
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from data_schema import atomic
from learn import checkpoint

log = logging.getLogger(__name__)
CARD = "card.json"
REPORT = "report.json"  # the named evaluation's report, copied beside the card: learn.compare reads it design by design
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
# what only resuming a training reads: the optimiser's moments, a weight average's raw weights, the patience count
RESUME_ONLY = ("optimizer", "trained_state_dict", "n_averaged", "bad_epochs")
REPORT_FIGURES = ("n_designs", "rollout_ms_per_design", "rollout_ms_per_design_batched", "rollout_backend",
                  "fea_s_per_episode", "fea_load_per_cpu_mean", "speedup", "speedup_batched", "n_invalid", "threads",
                  "load_average")


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def is_published(path: str | Path) -> bool:
    return Path(path).is_dir() and (Path(path) / CARD).is_file()


def members(directory: str | Path) -> list[str]:
    """The member files of a published model, in the card's order, each checked against its sha256: a file changed
    after publishing is refused by name, never answered with."""
    directory = Path(directory)
    if not is_published(directory):
        raise FileNotFoundError(f"{directory}: not a published model (no {CARD}); give a checkpoint file or a "
                                "models/<name> written by learn.publish")
    card = json.loads((directory / CARD).read_text())
    paths = []
    for m in card.get("members", []):
        path = directory / m["file"]
        if not path.is_file():
            raise FileNotFoundError(f"{directory}: member {m['file']} listed in {CARD} is missing")
        got = sha256(path)
        if got != m["sha256"]:
            raise ValueError(f"{path}: sha256 {got[:12]}... differs from {CARD}'s {m['sha256'][:12]}...: the file was "
                             "changed after publishing; publish it again under a new name (learn.publish)")
        paths.append(str(path))
    if not paths:
        raise ValueError(f"{directory / CARD}: lists no members")
    return paths


def one_checkpoint(value: str | Path, key: str) -> str:
    """A conf key that names one model (init_from, split_from, diagnose's checkpoint): a path, or a published
    models/<name> of one member; a published ensemble is refused naming its member files."""
    if not Path(value).is_dir():
        return str(value)
    paths = members(value)
    if len(paths) != 1:
        raise ValueError(f"{key}={value}: a published ensemble of {len(paths)} members; {key} takes one model: name "
                         f"a member ({', '.join(paths)})")
    return paths[0]


def stripped(ckpt: dict) -> dict:
    """The checkpoint without what only resuming reads."""
    return {k: v for k, v in ckpt.items() if k not in RESUME_ONLY}


def member_entry(source: str, ckpt: dict, file: Path, n_parameters: int) -> dict:
    config = ckpt.get("config") or {}
    split = ckpt.get("split") or {}
    return {
        "file": file.name, "sha256": sha256(file), "bytes": file.stat().st_size, "source": source,
        "epoch": ckpt.get("epoch"), "finished": ckpt.get("finished"),
        "n_parameters": int(n_parameters),
        "split_sizes": {part: len(names) for part, names in split.items()},
        "training": {k: config.get(k) for k in ("data_dir", "train_extra_dirs", "val_extra_dirs", "init_from",
                                                 "split_from", "train_designs", "seed", "epochs", "run_dir")},
        "training_seconds": (ckpt.get("history") or [{}])[-1].get("seconds"),
    }


def report_entry(path: str | Path, report: dict, sources: list[str]) -> dict:
    """The evaluation's figures, refused unless the report was measured with exactly these checkpoints."""
    measured = report.get("checkpoint")
    measured = [measured] if isinstance(measured, str) else list(measured or [])
    if [Path(p).resolve() for p in measured] != [Path(p).resolve() for p in sources]:
        raise ValueError(f"report={path}: measured with {measured}, not with checkpoints={sources}: a card carries "
                         "the figures of its own model only")
    out = {"source": str(path), "file": REPORT, **{k: report.get(k) for k in REPORT_FIGURES}}
    for key in ("max_rel_error", "mean_rel_error", "shape_rel_error"):
        if key == "shape_rel_error" and key not in report:
            continue  # a report from before session 65
        dist = report.get(key) or {}
        out[key] = {k: dist.get(k) for k in ("median", "p95", "worst", "n", "per_family", "per_actuators")}
    return out


def publish(sources: list[str], name: str, out_dir: str | Path = "models", report: str | Path | None = None,
            overwrite: bool = False) -> Path:
    """Copy `sources` into out_dir/name with a card; nothing is written unless every member and the report pass."""
    from learn import ensemble

    if not isinstance(name, str) or not NAME.match(name):
        raise ValueError(f"name={name!r}: letters, digits, '.', '_' or '-' (at most 100, not starting with '.' or '-')")
    target = Path(out_dir) / name
    if target.exists() and not overwrite:
        raise FileExistsError(f"name={name}: {target} exists; choose a new name (results quote the old one) or "
                              "overwrite=true")
    from learn.combine import read_report  # here, not at the top: learn.combine -> evaluate -> ensemble -> publish

    model, _ = ensemble.load(sources)  # every member loads; an ensemble's members share their held-out designs
    measured = None if report is None else read_report(report)
    figures = None if report is None else report_entry(report, measured, sources)
    tmp = Path(out_dir) / f".{name}.{secrets.token_hex(4)}{atomic.TMP_SUFFIX}"
    tmp.mkdir(parents=True)
    try:
        entries = []
        for i, src in enumerate(sources):
            ckpt = checkpoint.load(src)
            file = tmp / f"member_{i}.pt"
            buffer = io.BytesIO()  # not the temporary's name inside the archive: the same model, the same bytes
            torch.save(stripped(ckpt), buffer)
            with atomic.replacing(file) as t:
                t.write_bytes(buffer.getvalue())
            entries.append(member_entry(src, ckpt, file, ensemble.members_of(model)[i].n_parameters))
        args = {k: v for k, v in model.args.items() if k != "pca"}
        card = {
            "name": name, "published_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "format": checkpoint.FORMAT, "members": entries, "n_parameters": model.n_parameters,
            "model": json.loads(json.dumps(args, default=str)), "report": figures,
            "use": {"evaluate": f"make reference-evaluate CKPT={target}",
                    "predict": f"make predict DESIGN=my_design.json CKPT={target}",
                    "init_from": [f"{target}/{e['file']}" for e in entries]},
        }
        if measured is not None:
            atomic.write_text(tmp / REPORT, json.dumps(measured, indent=1))
        atomic.write_text(tmp / CARD, json.dumps(card, indent=1, allow_nan=False))
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


@hydra.main(version_base="1.3", config_path="../conf", config_name="publish")
def main(cfg: DictConfig) -> None:
    from learn.ensemble import checkpoint_paths

    sources = checkpoint_paths(cfg.checkpoints)
    target = publish(sources, cfg.name, cfg.out_dir, cfg.get("report"), bool(cfg.get("overwrite", False)))
    card = json.loads((target / CARD).read_text())
    size = sum(m["bytes"] for m in card["members"]) / 2**20
    log.info("published %s: %d member(s), %.1f MiB; commit it (git add %s)", target, len(card["members"]), size,
             target)
    if card["report"]:
        e = card["report"]["max_rel_error"]
        log.info("its report: %s designs, max error / design size median %.3g %%, p95 %.3g %%, %s ms a design",
                 card["report"]["n_designs"], 100 * e["median"], 100 * e["p95"],
                 card["report"]["rollout_ms_per_design"])


if __name__ == "__main__":
    main()
