"""Ahead-of-time compiled steps (AOTInductor): a model's step as one C++ package per graph shape.

A one-design rollout is ~600 small tensor operations per step (learn.rollout), so its TorchScript trace pays the
dispatch of each; `torch.export` + `torch._inductor.aoti_compile_and_package` turn the whole step into generated C++
(the pointwise work fused, the matrix products and the solve as library calls) that a rollout calls once per step.
Same numbers (float32 rounding; learn.evaluate checks every compiled rollout against the eager one).

A package (~6 MB: the code and the weights) is compiled once per model and input shapes (20-60 s on 2 cores) and kept
on disk under a key of the model's weights, statistics and args, the shapes, the torch version and the CPU (its code
is built for the machine it runs on), so a design
session or the next evaluation loads it in milliseconds; removing the cache directory only costs recompiling.
Kinematic models are not compiled this way (their placement order is a Python tree).

Backend "aot_tuned" compiles the same step with inductor's max_autotune: every matrix product is timed on this
machine against inductor's own C++ micro-kernel for its shape and the faster kept. A step's products are small
(9-24 rows by 4-256 columns for one 3 x 3 design), where a library call's dispatch (~5 us) outweighs the arithmetic,
so the micro-kernels win most of them (0.4-1.5 us against 5-6 us); a two-pass pair's rollout took x0.87-0.96 of aot's
on an idle 2-core EPYC (session 51, scripts/bench_rollout.py). Since session 61 it also freezes the weights (inductor's
`freezing`): they are constants of the package, laid out once at compile time in the micro-kernels' blocks, where an
unfrozen product copies its weight matrix into those blocks on every call (MKL's sgemm did the same: in a profile of
an aot step, copying the weights took 22 % of the time and the multiply-adds 18 %). Compiling takes ~3-5x longer (each
candidate is compiled and timed), once per model and shapes like every package, kept apart from the untuned ones.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import weakref
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn
from torch.export.graph_signature import InputKind, InputSpec

from learn.graph import GraphIndex
from learn.model import Simulator, Static
from learn.stiffness import Layout

AOT_BACKENDS = {"aot": {},  # inductor options of each backend (part of a tuned package's key)
                "aot_tuned": {"max_autotune": True, "freezing": True, "autotune_num_choices_displayed": 0}}
BACKENDS = ("torchscript", *AOT_BACKENDS)  # rollout_backend: how learn.rollout.compile_rollout compiles a rollout


def backend_checked(value) -> str:
    """rollout_backend: one of BACKENDS."""
    if value not in BACKENDS:
        raise ValueError(f"rollout_backend={value!r}: must be one of {' | '.join(BACKENDS)} (torchscript: a traced "
                         "rollout; aot: every step an AOTInductor-compiled C++ package, learn/aot.py; aot_tuned: "
                         "the same with its matrix products' kernels chosen by timing on this machine)")
    return value


def default_cache() -> Path:
    """Where packages are kept unless told: $MORPHSIM_AOT_CACHE, else ~/.cache/morphsim/aot."""
    return Path(os.environ.get("MORPHSIM_AOT_CACHE") or Path.home() / ".cache" / "morphsim" / "aot")


def _layout_tensors(plan: Layout) -> tuple[torch.Tensor, ...]:
    return (*plan.ends, plan.joint_dof, plan.free, *plan.stiffness_at, plan.loads_at, plan.kept, plan.eliminated)


class _Step(nn.Module):
    """model.step with every input a tensor, as torch.export takes them: the states, the bc terms, the graph's
    index (and with a union, which design each joint and beam belongs to), the step's time, then what a rollout
    builds once per graph (a stiffness model's Layout, a span model's beam spans). The counts that shape the step
    (designs in a union, a Layout's design and system sizes) are fixed per package."""

    def __init__(self, model: Simulator, union: bool, n_graphs: int, layout_sizes: tuple[int, int] | None,
                 spans: bool):
        super().__init__()
        self.model, self.union, self.n_graphs = model, union, n_graphs
        self.layout_sizes, self.spans = layout_sizes, spans

    def forward(self, joint_state, beam_state, joint_bc, beam_bc, senders, receivers, edge_beam, t, *rest):
        rest = list(rest)
        joint_graph, beam_graph = (rest.pop(0), rest.pop(0)) if self.union else (None, None)
        g = GraphIndex(senders, receivers, edge_beam, joint_state.shape[-2], beam_state.shape[-2], joint_graph,
                       beam_graph, self.n_graphs)
        static = Static(joint_bc, beam_bc, g)
        if self.layout_sizes is not None:
            a, c, joint_dof, free, at_global, at_local, loads_at, kept, eliminated = rest[:9]
            rest = rest[9:]
            static.layout = Layout((a, c), joint_dof, free, *self.layout_sizes, (at_global, at_local), loads_at,
                                   kept, eliminated)
        if self.spans:
            static.spans = rest.pop(0)
        return self.model.step(joint_state, beam_state, static, t)


def machine_key() -> str:
    """What a package's machine code was compiled for: inductor builds it with -march=native, so a package from
    another CPU (a shared cache, a copied home directory) could stop at an illegal instruction. The CPU's model name
    and flags (Linux /proc/cpuinfo, else the platform) and torch's CPU capability."""
    import platform
    cpu = ""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = "|".join(next((ln for ln in lines if ln.startswith(k)), "") for k in ("model name", "flags"))
    except OSError:
        pass
    return "|".join([platform.machine(), cpu or platform.processor(), torch.backends.cpu.get_cpu_capability()])


STEP_MODULES = ("aot", "model", "gn", "stiffness", "frames", "kinematics", "pca", "graph", "symmetry", "checks")


def step_code() -> bytes:
    """sha256 of the source of every learn module a compiled step is made of (STEP_MODULES): a package compiled
    before a change to how a step computes is not taken for one of the changed code (session 61's interactions
    summed before their last layer, learn.gn.summed_over_edges, were such a change, under the same weights)."""
    h = hashlib.sha256()
    for name in STEP_MODULES:
        h.update((Path(__file__).parent / f"{name}.py").read_bytes())
    return h.digest()


def fingerprint(model: Simulator) -> str:
    """sha256 of a model's args (but the rollout_* settings of its answers, which the step does not read), every
    parameter and buffer (name, dtype, shape, bytes), the torch version and the step's code (step_code): two models
    with the same fingerprint compute the same step."""
    args = {k: v for k, v in model.args.items() if not k.startswith("rollout_")}
    h = hashlib.sha256(json.dumps(args, sort_keys=True, default=str).encode())
    h.update(torch.__version__.encode())
    h.update(_STEP_CODE)
    for name, x in model.state_dict().items():
        h.update(f"{name}|{x.dtype}|{tuple(x.shape)}".encode())
        h.update(x.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


_STEP_CODE = step_code()  # read once: the code this process computes steps with


class AotSteps:
    """The compiled steps of every model it is asked for (an ensemble's members each), one package per model and
    input shapes, loaded from `cache` when there and compiled into it (atomically) when not. step_of(model) is
    called like model.step. A model's fingerprint is taken at its first use here: change its weights after that and
    make a new AotSteps (a CompiledRollout makes its own)."""

    def __init__(self, cache: str | Path | None = None, log: Callable[[str], None] | None = print,
                 backend: str = "aot"):
        if backend not in AOT_BACKENDS:
            raise ValueError(f"AotSteps backend={backend!r}: must be one of {' | '.join(AOT_BACKENDS)}")
        self.backend, self.options = backend, AOT_BACKENDS[backend]
        self.cache = Path(cache) if cache else default_cache()
        self.log = log or (lambda _: None)
        self.runners: dict = {}
        self.fingerprints: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> fingerprint
        self.seen: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> {input signature: runner}
        self.options_key = json.dumps(self.options, sort_keys=True)
        self.compiled = 0  # packages compiled (not found in the cache) by this object
        self.machine = machine_key()

    def step_of(self, model: Simulator) -> Callable:
        if model.kinematic:
            raise ValueError(f"rollout_backend={self.backend}: a kinematic model (model.update=kinematic) places beams "
                             "along a Python tree the export cannot follow; use rollout_backend=torchscript")

        def step(joint_state, beam_state, static: Static, t):
            g = static.index
            inputs = [joint_state, beam_state, static.joint_bc, static.beam_bc, g.senders, g.receivers, g.edge_beam,
                      torch.as_tensor(t, dtype=joint_state.dtype)]
            union = g.joint_graph is not None
            if union:
                inputs += [g.joint_graph, g.beam_graph]
            sizes = None
            if model.stiffness:
                plan = static.stiffness_layout()
                sizes = (plan.n_designs, plan.n)
                inputs += list(_layout_tensors(plan))
            if model.span_input:
                inputs.append(static.beam_spans())
            # contiguous, as when compiled: a package reads its inputs at the strides it was compiled with
            inputs = [x.contiguous() for x in inputs]
            seen = self.seen.setdefault(model, {})  # the same as key's shapes, without formatting them every step
            signature = (union, g.n_graphs, sizes, *((x.shape, x.dtype) for x in inputs))
            if signature not in seen:
                key = self.key(model, inputs, union, g.n_graphs, sizes)
                if key not in self.runners:
                    self.runners[key] = self._runner(model, key, inputs, union, g.n_graphs, sizes)
                seen[signature] = self.runners[key]
            out = seen[signature](*inputs)
            return out[0], out[1]

        return step

    def key(self, model: Simulator, inputs: list[torch.Tensor], union: bool, n_graphs: int | None,
            sizes: tuple[int, int] | None) -> tuple:
        """A package's key: the model's fingerprint, the machine, the graph counts, every input's shape and dtype,
        and when tuned the backend and its inductor options (aot's keys are those written before aot_tuned existed;
        an aot_tuned package compiled with other options, e.g. unfrozen before session 61, is not taken for one)."""
        if model not in self.fingerprints:
            self.fingerprints[model] = fingerprint(model)
        shapes = tuple((tuple(x.shape), str(x.dtype)) for x in inputs)
        key = (self.fingerprints[model], self.machine, union, n_graphs, sizes, bool(model.span_input), shapes)
        return key if self.backend == "aot" else key + (self.backend, self.options_key)

    def package_path(self, key) -> Path:
        """Where the package of a key (model fingerprint, machine, graph counts, input shapes) is kept."""
        return self.cache / f"step_{hashlib.sha256(repr(key).encode()).hexdigest()[:32]}.pt2"

    def _runner(self, model: Simulator, key, inputs, union, n_graphs, sizes):
        path = self.package_path(key)
        if not path.exists():
            self.cache.mkdir(parents=True, exist_ok=True)
            self.log(f"{self.backend}: compiling the step for shapes {[tuple(x.shape) for x in inputs[:2]]} "
                     f"into {path} (once per model and graph size, ~{'1' if self.backend == 'aot' else '3-5'} min)")
            module = _Step(model.eval(), union, n_graphs, sizes, bool(model.span_input)).eval()
            example = tuple(x.detach().clone() for x in inputs)
            with torch.inference_mode(False), torch.no_grad():
                exported = torch.export.export(module, example)
                if self.options.get("freezing"):
                    exported = constants_as_buffers(exported)
                fd, tmp = tempfile.mkstemp(suffix=".pt2", dir=self.cache)
                os.close(fd)
                try:
                    torch._inductor.aoti_compile_and_package(exported, package_path=tmp,
                                                             inductor_configs=dict(self.options))
                    os.chmod(tmp, 0o644)  # mkstemp's 0600 would keep a shared cache from other users
                    os.replace(tmp, path)  # atomic: a package is whole or absent
                finally:
                    if os.path.exists(tmp):
                        os.unlink(tmp)
            self.compiled += 1
        return direct_call(torch._inductor.aoti_load_package(str(path)), len(inputs))


def constants_as_buffers(exported: torch.export.ExportedProgram) -> torch.export.ExportedProgram:
    """The program with its lifted tensor constants (tensors a step makes from module-level ones, e.g.
    learn.stiffness's maps) turned into buffers, in place. Inductor's freezing unlifts each use of a constant as its
    own attribute read, and its constant folding, dropping a read it folded away, deletes the attribute the others
    still read ("references nonexistent attribute _tensor_constant0", torch 2.13); buffers are frozen like weights."""
    specs = []
    for spec in exported.graph_signature.input_specs:
        if spec.kind == InputKind.CONSTANT_TENSOR:
            exported.state_dict[spec.target] = exported.constants.pop(spec.target)
            spec = InputSpec(kind=InputKind.BUFFER, arg=spec.arg, target=spec.target, persistent=True)
        specs.append(spec)
    exported.graph_signature.input_specs[:] = specs
    return exported


def direct_call(package, n_inputs: int) -> Callable:
    """A loaded package called with its flat list of input tensors, as its own __call__ ends up doing after parsing
    its input and output tree specs from JSON and flattening the arguments on every call (~0.16 ms, ~7 % of a step);
    the package's own __call__ when the loader is not there or its spec is not n_inputs tensors in, two out."""
    loader = getattr(package, "loader", None)
    try:
        from torch.utils import _pytree as pytree
        in_spec, out_spec = (pytree.treespec_loads(s) for s in loader.get_call_spec())
        plain = in_spec.num_leaves == n_inputs and out_spec.num_leaves == 2
    except (AttributeError, TypeError, ValueError, RuntimeError):  # another torch's package: its own call
        plain = False
    if not plain:
        return package
    return lambda *inputs: loader.boxed_run(list(inputs))
