"""Training curves of several runs side by side: `.venv/bin/python -m learn.curves 'runs=[runs/a,runs/b]'
out_dir=reports/curves` (conf/curves.yaml; `make curves RUNS=runs/a,runs/b`).

Reads each run's history from its last.pt (best.pt when a run has no last.pt) and writes curves.md (one row per run:
the settings that differ between the runs, "-" where a run predates one; the best validation rollout error and when
it came, in epochs and hours; the training designs' error at that epoch; seconds per epoch), curves.json and
curves.png (the validation rollout error, and the training designs' error where the run logged it, against epochs
and against hours of training: a faster recipe is judged by what it reaches in the same time).
"""
from __future__ import annotations

import math
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from learn import checkpoint
from learn.compare import write_outputs

SETTINGS = ("epochs", "batch_size", "precision", "optim.lr", "optim.schedule", "optim.lr_drop_at", "lattice_turns",
            "rotations", "mirror", "seed", "model.latent", "model.widths", "model.n_blocks", "model.layer_norm")


def run_history(run_dir: str | Path) -> tuple[list[dict], dict]:
    """(history rows, config) of a run directory's last.pt, or best.pt when there is no last.pt."""
    run_dir = Path(run_dir)
    for name in ("last.pt", "best.pt"):
        if (run_dir / name).exists():
            ckpt = checkpoint.load(run_dir / name)
            return list(ckpt["history"]), dict(ckpt.get("config") or {})
    raise FileNotFoundError(f"runs: {run_dir} holds no last.pt or best.pt (a learn.train run directory?)")


def setting(config: dict, dotted: str):
    """config value at a dotted key; None when the run's config predates it."""
    value = config
    for key in dotted.split("."):
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return value


def run_row(label: str, history: list[dict], config: dict) -> dict:
    """A run's best validation rollout error (epoch, hours), the training designs' error then, seconds per epoch."""
    if not history:
        return {"label": label, "epochs_run": 0}
    val = np.array([r["val_rollout"] for r in history])
    i = int(np.argmin(val))
    seconds = np.array([r["seconds"] for r in history])
    return {"label": label, "epochs_run": len(history), "best_val_rollout": float(val[i]),
            "best_epoch": int(history[i]["epoch"]), "best_hours": float(seconds[i] / 3600),
            "train_rollout_at_best": float(history[i].get("train_rollout", math.nan)),
            "last_val_rollout": float(val[-1]), "hours": float(seconds[-1] / 3600),
            "seconds_per_epoch": float(np.median(np.diff(seconds, prepend=0.0)))}


def curves(runs: list[tuple[str, list[dict], dict]]) -> dict:
    """One row per (label, history, config); `differs`: the SETTINGS whose values are not the same in every run."""
    values = {k: [setting(c, k) for _, _, c in runs] for k in SETTINGS}
    differs = [k for k, v in values.items() if any(x != v[0] for x in v)]
    rows = [{**run_row(label, h, c), "settings": {k: setting(c, k) for k in differs}} for label, h, c in runs]
    series = [{"label": label, "epoch": [r["epoch"] for r in h], "hours": [r["seconds"] / 3600 for r in h],
               "val_rollout": [r["val_rollout"] for r in h],
               "train_rollout": [r.get("train_rollout", math.nan) for r in h]} for label, h, _ in runs]
    return {"differs": differs, "rows": rows, "series": series}


def markdown(result: dict) -> str:
    pct = lambda x: "" if x is None or not math.isfinite(x) else f"{100 * x:.2f} %"  # noqa: E731
    head = ["run", *result["differs"], "epochs run", "best validation rollout", "at epoch", "at hours",
            "training designs then", "last", "s / epoch"]
    lines = ["# Training curves: max error / design size over the validation designs (mean), and over the "
             "training probe where logged", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in result["rows"]:
        if not r["epochs_run"]:
            lines.append(f"| {r['label']} |" + " |" * (len(head) - 1))
            continue
        shown = ("-" if r["settings"][k] is None else str(r["settings"][k]) for k in result["differs"])
        cells = [r["label"], *shown, str(r["epochs_run"]),
                 pct(r["best_val_rollout"]), str(r["best_epoch"]), f"{r['best_hours']:.2f}",
                 pct(r["train_rollout_at_best"]), pct(r["last_val_rollout"]), f"{r['seconds_per_epoch']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    """Validation rollout error (solid) and training designs' error (dashed) against epochs and hours, log y."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for n, s in enumerate(result["series"]):
        colour = f"C{n % 10}"
        for ax, x in zip(axes, ("epoch", "hours")):
            ax.plot(s[x], 100 * np.asarray(s["val_rollout"]), color=colour, label=s["label"])
            train = 100 * np.asarray(s["train_rollout"], dtype=float)
            if np.isfinite(train).any():
                ax.plot(s[x], train, color=colour, ls="--", lw=0.9)
    for ax, x in zip(axes, ("epoch", "hours of training")):
        ax.set(xlabel=x, yscale="log")
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("max error / design size (%)")
    fig.suptitle("validation designs (solid), training probe (dashed)", fontsize=10)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


@hydra.main(version_base="1.3", config_path="../conf", config_name="curves")
def main(cfg: DictConfig) -> None:
    paths = [str(p) for p in cfg.runs]
    labels = [str(v) for v in cfg.labels] if cfg.labels else paths
    if len(labels) != len(paths):
        raise ValueError(f"labels: {len(labels)} given for {len(paths)} runs")
    result = curves([(label, *run_history(p)) for label, p in zip(labels, paths)])
    write_outputs(cfg.out_dir, "curves", result, markdown, plot if cfg.plots else None)


if __name__ == "__main__":
    main()
