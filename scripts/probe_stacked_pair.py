"""Probe: a two-member ensemble's step as one network over stacked weights, against the members' own steps.

`python scripts/probe_stacked_pair.py --checkpoint a.pt,b.pt --out reports/stacked_pair` (stiffness models, the
default): the members' parameters and buffers stacked (torch.func.stack_module_state), Simulator.step run under
torch.func.vmap over them, (1) eagerly and (2) exported and compiled as one AOTInductor package; each rollout of the
checkpoints' first test designs compared with the members' own (learn.rollout.unroll eagerly, learn.aot.AotSteps
compiled: max |difference| over the joint states of every frame) and timed on one thread (median of --repeats calls,
learn.evaluate.median_seconds), --rounds times alternately. Writes stacked_pair.md (machine, load, command, table).
A measurement, not a rollout backend: learn.rollout does not use it (docs/learned_simulator.md, session 50).
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile
from pathlib import Path

import torch
from torch import nn
from torch.func import functional_call, stack_module_state, vmap

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from data_schema import atomic  # noqa: E402
from learn import ensemble  # noqa: E402
from learn.aot import AotSteps, _layout_tensors  # noqa: E402
from learn.dataset import load_features  # noqa: E402
from learn.evaluate import median_seconds  # noqa: E402
from learn.graph import GraphIndex  # noqa: E402
from learn.model import Static  # noqa: E402
from learn.rollout import plain_inputs, unroll  # noqa: E402
from learn.stiffness import Layout  # noqa: E402
from tradeoff import machine  # noqa: E402  (scripts/tradeoff.py)


class StepOf(nn.Module):
    """model.step as a forward, so functional_call can swap the model's tensors for one member's."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, joint_state, beam_state, static, t):
        return self.model.step(joint_state, beam_state, static, t)


class StackedStep(nn.Module):
    """The members' steps at once: states [M, ..., N, D] (member first), one graph, the stiffness Layout's tensors."""

    def __init__(self, members, sizes: tuple[int, int]):
        super().__init__()
        params, buffers = stack_module_state([StepOf(m) for m in members])
        self.names = [*params, *buffers]
        for i, x in enumerate([*params.values(), *buffers.values()]):
            self.register_buffer(f"w{i}", x.detach().clone())
        self.step = StepOf(copy.deepcopy(members[0]))
        self.sizes = sizes

    def forward(self, js, bs, joint_bc, beam_bc, senders, receivers, edge_beam, t, a, c, joint_dof, free, at_global,
                at_local, loads_at, kept, eliminated):
        g = GraphIndex(senders, receivers, edge_beam, js.shape[-2], bs.shape[-2], None, None, 1)
        static = Static(joint_bc, beam_bc, g)
        static.layout = Layout((a, c), joint_dof, free, *self.sizes, (at_global, at_local), loads_at, kept,
                               eliminated)
        weights = {n: getattr(self, f"w{i}") for i, n in enumerate(self.names)}
        return vmap(lambda w, j, b: functional_call(self.step, w, (j, b, static, t)))(weights, js, bs)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", required=True, help="two checkpoints joined by ',' (stiffness models)")
    p.add_argument("--data-dir", help="default: the first checkpoint's data_dir")
    p.add_argument("--designs", type=int, default=4, help="test designs (the first by name)")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--rounds", type=int, default=3, help="timing rounds, the two ways alternately")
    p.add_argument("--out", default="reports/stacked_pair")
    a = p.parse_args()
    for name in ("designs", "repeats", "rounds"):
        if getattr(a, name) < 1:
            raise SystemExit(f"--{name} {getattr(a, name)}: must be an integer >= 1")
    torch.set_num_threads(1)
    model, ckpt = ensemble.load(a.checkpoint.split(","))
    members = [m.eval() for m in ensemble.members_of(model)]
    if len(members) != 2 or not all(m.stiffness for m in members):
        raise SystemExit(f"--checkpoint {a.checkpoint}: give two checkpoints of stiffness models")
    data_dir = Path(a.data_dir or ckpt["config"]["data_dir"])
    features = load_features([data_dir / n for n in sorted(ckpt["split"]["test"])[: a.designs]])
    load_before = "/".join(f"{x:.2f}" for x in os.getloadavg())
    stepper = AotSteps(tempfile.mkdtemp(prefix="stacked_pair_aot_"), log=None)
    member_steps = [stepper.step_of(m) for m in members]
    rows = []
    for f in features:
        j0, b0, static, t = plain_inputs(f)
        plan = static.stiffness_layout()
        layout = [x.contiguous() for x in _layout_tensors(plan)]
        g = static.index
        graph = (static.joint_bc.contiguous(), static.beam_bc.contiguous(), g.senders, g.receivers, g.edge_beam)
        stacked = StackedStep(members, (plan.n_designs, plan.n)).eval()
        start = (j0.expand(2, *j0.shape).contiguous(), b0.expand(2, *b0.shape).contiguous())
        with torch.no_grad():
            exported = torch.export.export(stacked, (*start, *graph, t[0].clone(), *layout))
            package = Path(stepper.cache) / f"stacked_{len(rows)}.pt2"
            torch._inductor.aoti_compile_and_package(exported, package_path=str(package))
        compiled = torch._inductor.aoti_load_package(str(package))

        def roll(step):
            js, bs = start
            frames = [js]
            for k in range(len(t) - 1):
                js, bs = step(js, bs, *graph, t[k], *layout)
                frames.append(js)
            return torch.stack(frames, 1)  # [M, F, J, D]

        def members_roll(steps):
            return torch.stack([unroll(m, j0, b0, static, t)[0] if s is None else
                                torch.stack(_frames(s, j0, b0, static, t)) for m, s in zip(members, steps)])

        with torch.inference_mode():
            eager_ref, aot_ref = members_roll([None, None]), members_roll(member_steps)
            eager_dev = float((roll(stacked) - eager_ref).abs().max())
            aot_dev = float((roll(compiled) - aot_ref).abs().max())
        times = {"members eager": [], "stacked eager": [], "members aot": [], "stacked aot": []}
        for _ in range(a.rounds):
            times["members eager"].append(median_seconds(lambda: members_roll([None, None]), max(3, a.repeats // 6)))
            times["stacked eager"].append(median_seconds(lambda: roll(stacked), max(3, a.repeats // 6)))
            times["members aot"].append(median_seconds(lambda: members_roll(member_steps), a.repeats))
            times["stacked aot"].append(median_seconds(lambda: roll(compiled), a.repeats))
        rows.append((f.name, eager_dev, aot_dev, {k: [1e3 * x for x in v] for k, v in times.items()}))
        print(rows[-1])
    load_after = "/".join(f"{x:.2f}" for x in os.getloadavg())
    lines = [f"# A two-member ensemble's step over stacked weights ({a.checkpoint})", "",
             f"Machine: {machine()}; 1 torch thread; load average before/after {load_before} / {load_after}.",
             f"Command: `python scripts/probe_stacked_pair.py {' '.join(sys.argv[1:])}`; per design the median of "
             f"{a.repeats} calls (eager: {max(3, a.repeats // 6)}), {a.rounds} rounds, the two ways alternately.", "",
             "| design | max dev. eager | max dev. aot | members eager ms | stacked eager ms | members aot ms | "
             "stacked aot ms |", "|---|---|---|---|---|---|---|"]
    for name, e, c, tm in rows:
        fmt = lambda k: " / ".join(f"{x:.2f}" for x in tm[k])  # noqa: E731
        lines.append(f"| {name} | {e:.3g} | {c:.3g} | {fmt('members eager')} | {fmt('stacked eager')} | "
                     f"{fmt('members aot')} | {fmt('stacked aot')} |")
    lines += ["", "max dev.: the largest |stacked - members| over the joint states of every frame (state-column "
              "units: mm, MPa), eager against learn.rollout.unroll, aot against learn.aot.AotSteps."]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "stacked_pair.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


def _frames(step, j0, b0, static, t) -> list[torch.Tensor]:
    js, bs = j0, b0
    frames = [js]
    for k in range(len(t) - 1):
        js, bs = step(js, bs, static, t[k])
        frames.append(js)
    return frames


if __name__ == "__main__":
    main()
