"""Shared pieces of the FEA benchmarks (scripts/bench_fea.py, scripts/tradeoff.py): launching one solve in its own
`mpirun` process with its wall time and memory peak, reading its statistics, and the node positions every mesh
preset shares (the joints' corner nodes), compared as a fraction of the design size.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def bench_design():
    """The fixed mildly jittered mixed 3x3 design of `make bench-fea` (130 x 120 mm)."""
    from fea_factory.design import lattice_design

    xs, ys = np.meshgrid([0.0, 65.0, 130.0], [0.0, 60.0, 120.0], indexing="ij")
    xy = np.stack([xs, ys], axis=-1) + np.array([[[0, 0], [4, -3], [0, 2]], [[-3, 4], [0, 0], [5, 1]],
                                                  [[2, -4], [-4, 3], [0, 0]]], dtype=float)
    kinds = ["up", "down", "up", "passive", "down", "up", "down", "up", "passive", "down", "up", "down"]
    return lattice_design(xy, kinds, (1, 1), meta={"family": "bench"})


# ------------------------------------------------------------------------------------------------ memory
def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        kids.setdefault(ppid, []).append(int(d))
    return kids


def tree_rss_mb(pid: int) -> float:
    """Resident memory (MB) of a process and all its descendants (Linux /proc)."""
    kids, todo, total = _children(), [pid], 0
    page = os.sysconf("SC_PAGE_SIZE")
    while todo:
        p = todo.pop()
        todo += kids.get(p, [])
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * page
        except (OSError, IndexError, ValueError):
            pass
    return total / 2**20


class PeakMemory:
    """Polls tree_rss_mb(pid) every `interval` s in a thread; .peak_mb is the largest sum seen (mpirun and every
    rank together, so a 2-rank run counts both ranks)."""

    def __init__(self, pid: int, interval: float = 0.1):
        self.pid, self.interval, self.peak_mb = pid, interval, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()

    def _poll(self) -> None:
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, tree_rss_mb(self.pid))
            self._stop.wait(self.interval)

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return self.peak_mb


def descendants(pid: int) -> list[int]:
    kids, todo, out = _children(), [pid], []
    while todo:
        p = todo.pop()
        out += kids.get(p, [])
        todo += kids.get(p, [])
    return out


def stop_tree(proc: subprocess.Popen, grace: float = 10.0) -> None:
    """SIGTERM an mpirun (it forwards the signal to its ranks), then SIGKILL whatever of its tree is left."""
    tree = [(pid, _start_time(pid)) for pid in descendants(proc.pid)]
    proc.terminate()
    try:
        proc.communicate(timeout=grace)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
    for pid, started in tree:  # same pid and start time: still our process, not a reused pid
        if started is not None and _start_time(pid) == started:
            try:
                os.kill(pid, 9)
            except (ProcessLookupError, PermissionError):
                pass


def _start_time(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return None


# ------------------------------------------------------------------------------------------------ solve
def solve_command(design_file: Path, out: Path, overrides: list[str], ranks: int = 1) -> list[str]:
    """`mpirun --bind-to none -n ranks python -m fea_factory.solve ...` (without --bind-to none, concurrent mpiruns
    all bind their rank 0 to core 0)."""
    return ["mpirun", "--bind-to", "none", "-n", str(ranks), sys.executable, "-m", "fea_factory.solve",
            f"design={design_file}", f"out={out}", *overrides]


def run_solve(design_file: Path, out: Path, overrides: list[str], ranks: int = 1, timeout: float | None = None) -> dict:
    """Solve one design in a fresh mpirun (environment from generate.mpirun_env, stdin closed).
    Returns {status, reason?, process_s, peak_mb} + solve_stats(episode) and the episode itself under "episode"
    when the solve succeeded. status: ok | diverged | error | timeout."""
    from fea_factory.generate import mpirun_env

    cmd = solve_command(design_file, out, overrides, ranks)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=mpirun_env(), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    mem = PeakMemory(proc.pid)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        stop_tree(proc)
        return {"status": "timeout", "reason": f"no result after {timeout} s", "peak_mb": mem.stop(),
                "process_s": time.perf_counter() - t0}
    result = {"process_s": time.perf_counter() - t0, "peak_mb": mem.stop()}
    lines = stdout.strip().splitlines()
    try:
        last = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        last = {}
    if proc.returncode != 0 or last.get("status") != "ok":
        reason = last.get("reason") or (stderr or stdout).strip()[-500:]
        return {**result, "status": last.get("status") or "error", "reason": reason}
    from data_schema.episode import read_episode

    ep = read_episode(out)
    return {**result, "status": "ok", **solve_stats(ep), "episode": ep}


def solve_stats(ep) -> dict:
    """Size and solver statistics of an episode (its provenance)."""
    st = ep.solver_stats
    return {"cells": ep.n_cells, "nodes": ep.n_nodes, "wall_total_s": st["wall_total_s"],
            "wall_jit_s": st.get("wall_jit_s"), "wall_solve_s": st.get("wall_solve_s"), "newton": st["newton_total"],
            "increments": st["increments"], "cutbacks": st["cutbacks"]}


# ------------------------------------------------------------------------------------------------ compare
def corner_nodes(ep) -> np.ndarray:
    """Node ids of the joints' corner nodes, keyed (joint, 0|nw-1, 0|nw-1, 0|nh-1): present at every preset, [J * 8]."""
    jn = ep.joint_nodes
    return jn[:, [0, -1]][:, :, [0, -1]][:, :, :, [0, -1]].reshape(-1)


def corner_positions(ep, frame: int | slice = -1) -> np.ndarray:
    """Positions of the joint corner nodes: [J * 8, 3] for one frame (default: the last), [F', J * 8, 3] for a slice."""
    return np.asarray(ep.node_xyz)[frame][..., corner_nodes(ep), :]


def position_error(points: np.ndarray, reference: np.ndarray, size: float) -> tuple[float, float]:
    """(max, mean) distance between matching points, divided by the design size."""
    d = np.linalg.norm(np.asarray(points, float) - np.asarray(reference, float), axis=-1)
    return float(d.max() / size), float(d.mean() / size)


def episode_error(ep, ref, size: float) -> tuple[float, float]:
    """(max, mean) relative corner-node error of `ep` against `ref` over every saved frame after t = 0."""
    if len(ep.t) != len(ref.t) or not np.allclose(ep.t, ref.t):
        raise ValueError(f"frame times differ: {list(ep.t)} vs reference {list(ref.t)}")
    return position_error(corner_positions(ep, slice(1, None)), corner_positions(ref, slice(1, None)), size)
