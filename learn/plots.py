"""Evaluation plots (matplotlib, Agg): FEA vs prediction overlays and error vs step."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from learn.rollout import Rollout  # noqa: E402


def equal_axes(ax, points: np.ndarray) -> None:
    """A 3D axis cube around points [..., 3] (mm), so shapes are not stretched."""
    pts = points.reshape(-1, 3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    c, half = 0.5 * (lo + hi), 0.5 * (hi - lo).max()
    ax.set(xlim=(c[0] - half, c[0] + half), ylim=(c[1] - half, c[1] + half), zlim=(c[2] - half, c[2] + half),
           xlabel="x mm", ylabel="y mm", zlabel="z mm")


def plot_overlays(report: dict, rollouts: list[Rollout], path: Path) -> None:
    """Final frame of the best, median and worst design: FEA nodes (blue) and rebuilt predictions (red)."""
    order = np.argsort([d["max_rel_error"] for d in report["designs"]])
    picks = {"best": order[0], "median": order[len(order) // 2], "worst": order[-1]}
    fig = plt.figure(figsize=(15, 5))
    for n, (label, i) in enumerate(picks.items()):
        ax = fig.add_subplot(1, 3, n + 1, projection="3d")
        r, d = rollouts[i], report["designs"][i]
        fea, pred = r.features.fea_points[-1], r.local_points[-1]
        ax.scatter(*fea.T, s=3, c="tab:blue", label="FEA")
        ax.scatter(*pred.T, s=3, c="tab:red", label="learned")
        ax.set_title(f"{label}: {d['name']}\nmax error {100 * d['max_rel_error']:.2f}% of {d['design_size_mm']:.0f} mm")
        equal_axes(ax, fea)
        if n == 0:
            ax.legend(loc="upper left")
    fig.subplots_adjust(left=0.02, right=0.97, bottom=0.05, top=0.86, wspace=0.1)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_error_vs_step(report: dict, path: Path) -> None:
    """Max error / design size per frame: median, 95th percentile and worst over the designs."""
    e = 100 * np.array([d["max_rel_error_per_frame"] for d in report["designs"]])  # [designs, F]
    steps = np.arange(e.shape[1])
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(steps, np.median(e, axis=0), "o-", label="median")
    ax.plot(steps, np.percentile(e, 95, axis=0), "s--", label="95th percentile")
    ax.plot(steps, e.max(axis=0), "^:", label="worst")
    ax.set_xlabel("rollout step")
    ax.set_ylabel("max position error / design size (%)")
    ax.set_title(f"{report['n_designs']} held-out designs")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_report(report: dict, rollouts: list[Rollout], out_dir: Path) -> None:
    plot_overlays(report, rollouts, out_dir / "overlay_best_median_worst.png")
    plot_error_vs_step(report, out_dir / "error_vs_step.png")
