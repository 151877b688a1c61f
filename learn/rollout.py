"""Rollout: advance a design's initial graph step by step and rebuild points comparable to the FEA nodes."""
from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch

from learn.aot import AOT_BACKENDS, AotSteps, backend_checked
from learn.ensemble import Ensemble, members_of, stack_mean
from learn.dataset import GraphSet
from learn.features import EpisodeFeatures, beams_along_i, extract, rebuild_all_points, welded
from learn.graph import BEAM, JOINT, GraphIndex
from learn.model import Simulator, Static, static_from
from learn.symmetry import (LATTICE_QUARTER_TURNS, lattice_matrices, rotation_angles, rotation_z, state_mirror,
                            state_rotation, term_mirror, term_rotation)


def unroll(model: Simulator, joint_state: torch.Tensor, beam_state: torch.Tensor, static: Static,
           t: torch.Tensor, stepper: AotSteps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """From states [..., J, Dj], [..., B, Db] at t[0], step through t[1:]; -> [F, ..., J, Dj], [F, ..., B, Db].
    A direct model (model.update=direct) answers every frame from the states at t[0] and the frame's time, all
    frames in one batched pass. stepper: each step by the model's compiled step (learn/aot.py), not model.step."""
    step = model.step if stepper is None else stepper.step_of(model)
    if model.direct:
        n, lead = len(t) - 1, joint_state.shape[:-2]
        times = t[1:].reshape(n, *(1,) * len(lead)).expand(n, *lead)
        j, b = step(joint_state.expand(n, *joint_state.shape), beam_state.expand(n, *beam_state.shape),
                    static, times)
        return torch.cat([joint_state[None], j]), torch.cat([beam_state[None], b])
    joints, beams = [joint_state], [beam_state]
    for k in range(len(t) - 1):
        j, b = step(joints[-1], beams[-1], static, t[k])
        joints.append(j)
        beams.append(b)
    return torch.stack(joints), torch.stack(beams)


@functools.lru_cache(maxsize=64)
def _group(block, n: int, mirror: bool, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The n rotations about z (evenly spread over a turn, the first 0), and with `mirror` each also after the
    mirror, as state matrices [g, S, S] (x @ A), their inverses, and the bc matrices [g, D, D]. Built once per
    argument set (~10 ms of numpy each, which an uncompiled answer over copies paid at every call; read only)."""
    mirrors = (False, True) if mirror else (False,)
    elements = [(m, rotation_z(a)) for m in mirrors for a in rotation_angles(n)]
    flip = lambda m, M, size: M if m else np.eye(size)  # noqa: E731
    S, D = block.state_size, block.bc.size
    forward = [flip(m, state_mirror(block), S) @ state_rotation(block, R) for m, R in elements]
    inverse = [state_rotation(block, R.T) @ flip(m, state_mirror(block), S) for m, R in elements]
    bc = [flip(m, term_mirror(block.bc), D) @ term_rotation(block.bc, R) for m, R in elements]
    return _constants(forward, inverse, bc, dtype=dtype)


def _constants(*arrays, dtype) -> tuple[torch.Tensor, ...]:
    """Stacked arrays as tensors made outside inference mode (kept in a cache, they may meet a trace or autograd)."""
    with torch.inference_mode(False):
        return tuple(torch.as_tensor(np.stack(x), dtype=dtype) for x in arrays)


@functools.lru_cache(maxsize=64)
def _lattice(block, turns: int, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The labellings of model.rollout_lattice_turns (learn.symmetry.LATTICE_QUARTER_TURNS) as state matrices
    [L, 2, S, S] (x @ A; [:, 0] for a block that keeps its direction, [:, 1] for one that runs the other way), their
    inverses, and the bc matrices [L, 2, D, D]. Built once per argument set, as _group."""
    state, bc = zip(*(lattice_matrices(block, k) for k in LATTICE_QUARTER_TURNS[turns]))
    return _constants(state, np.linalg.inv(state), bc, dtype=dtype)


def lattice_reversals(turns: int, along_i: torch.Tensor) -> torch.Tensor:
    """[L, B] bool: the beams that run the other way in each labelling of `turns` (none, those along i, all, those
    along j for 0, 1, 2, 3 quarter turns)."""
    by_turns = (torch.zeros_like(along_i), along_i, torch.ones_like(along_i), ~along_i)
    return torch.stack([by_turns[k] for k in LATTICE_QUARTER_TURNS[turns]])


def _relabelled(x: torch.Tensor, A: torch.Tensor, reverse: torch.Tensor | None, lead: int) -> torch.Tensor:
    """x [*, L?, ..., N, D] @ A [L, 2, D, D], each row by A[:, 1] where `reverse` [L, N] is set, else by A[:, 0]. The
    L axis of the result sits after the first `lead` axes of x; x already has it when lead > 0 (mapping back)."""
    pattern = "...nd,lde->l...ne" if lead == 0 else "fl...nd,lde->fl...ne"
    kept = torch.einsum(pattern, x, A[:, 0])
    if reverse is None:
        return kept
    mask = reverse.reshape(*(1,) * lead, reverse.shape[0], *(1,) * (kept.dim() - lead - 3), reverse.shape[1], 1)
    return torch.where(mask, torch.einsum(pattern, x, A[:, 1]), kept)


def answer_unroll(model: Simulator, joint_state: torch.Tensor, beam_state: torch.Tensor, static: Static,
                  t: torch.Tensor, stepper: AotSteps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """unroll as the trained simulator answers: the design is rolled out in several copies at once (one batch) --
    labelled from model.rollout_lattice_turns corners of its lattice (EpisodeFeatures.half_turned, quarter_turned),
    each rotated about z through the fixed joint (the features' origin) by model.rollout_rotations angles, and also
    mirrored with model.rollout_mirror (EpisodeFeatures.mirrored) -- every copy mapped back and the states averaged.
    The average makes the answer exactly equivariant to that group, which the network alone is only approximately
    (it learned it from augmentation, or not at all); training and its validation use the network alone (unroll).
    The relabelled copies keep the design's incidence: a beam that runs the other way only swaps its two directed
    edges, and every core treats its edges alike and sums them; only a stiffness model reads a beam's direction (its
    solve and rigid motion), so its labellings go as one disjoint union, each with its reversed beams' ends swapped
    (GraphIndex.labelled_union). An Ensemble answers with the mean of its members'
    answers, frame by frame. States: one design or one disjoint union of designs (no leading batch axes). stepper:
    every step by its model's compiled step (learn/aot.py)."""
    if isinstance(model, Ensemble):
        return stack_mean([answer_unroll(m, joint_state, beam_state, static, t, stepper) for m in model.members])
    n, mirror, turns = model.rollout_rotations, model.rollout_mirror, model.rollout_lattice_turns
    if n <= 1 and not mirror and turns == 1:
        return unroll(model, joint_state, beam_state, static, t, stepper)
    Lj, Lj_back, Ljbc = _lattice(JOINT, turns, joint_state.dtype)
    Lb, Lb_back, Lbbc = _lattice(BEAM, turns, beam_state.dtype)
    g = static.index
    reverse = lattice_reversals(turns, beams_along_i(joint_state, beam_state, g.beam_starts()))
    Aj, Aj_back, Ajbc = _group(JOINT, n, mirror, joint_state.dtype)
    Ab, Ab_back, Abbc = _group(BEAM, n, mirror, beam_state.dtype)
    copies = Aj.shape[0] * Lj.shape[0]
    to = lambda x, A: torch.einsum("...nd,kde->k...ne", x, A)  # noqa: E731  [..., N, D] -> [k, ..., N, D]
    static_copies = Static(to(_relabelled(static.joint_bc, Ljbc, None, 0), Ajbc),
                           to(_relabelled(static.beam_bc, Lbbc, reverse, 0), Abbc), g,
                           static.kinematic_tree() if model.kinematic else None)  # one tree: one topology
    js, bs = to(_relabelled(joint_state, Lj, None, 0), Aj), to(_relabelled(beam_state, Lb, reverse, 0), Ab)
    if model.stiffness and turns > 1:  # its solve and rigid motion read each beam's start and end joint, which a
        # labelling that reverses a beam swaps: the labellings as one disjoint union, each with those beams reversed
        L = reverse.shape[0]
        union = lambda x: x.movedim(1, -3).flatten(-3, -2)  # noqa: E731  [k, L, ..., N, D] -> [k, ..., L N, D]
        apart = lambda x: x.unflatten(-2, (L, -1)).movedim(-3, 2)  # noqa: E731  [F, k, ..., L N, D] -> [F, k, L, ...]
        js, bs = unroll(model, union(js), union(bs), Static(union(static_copies.joint_bc), union(static_copies.beam_bc),
                                                            g.labelled_union(reverse)), t, stepper)
        js, bs = apart(js), apart(bs)  # [F, k, L, ..., N, S]
    else:
        js, bs = unroll(model, js, bs, static_copies, t, stepper)  # [F, k, L, ..., N, S]
    back = lambda x, A: torch.einsum("fk...nd,kde->f...ne", x, A)  # noqa: E731  summed over k -> [F, L, ..., N, S]
    return (_relabelled(back(js, Aj_back), Lj_back, None, 1).sum(1) / copies,
            _relabelled(back(bs, Ab_back), Lb_back, reverse, 1).sum(1) / copies)


class _Unroll(torch.nn.Module):
    """unroll + rebuild_all_points with the graph passed as tensors, so one trace serves every graph size. With
    n_graphs, the graph is a disjoint union of that many designs (graph_inputs of a list) and the two extra inputs
    say which design each joint and beam belongs to. With a stepper every step is its model's compiled step
    (learn/aot.py); such an _Unroll is run as it is, not traced."""

    def __init__(self, model: Simulator, n_graphs: int | None = None, stepper: AotSteps | None = None):
        super().__init__()
        self.model = model
        self.n_graphs = n_graphs
        self.stepper = stepper

    def forward(self, joint_state, beam_state, joint_bc, beam_bc, senders, receivers, edge_beam, t, joint_graph=None,
                beam_graph=None):
        index = GraphIndex(senders, receivers, edge_beam, joint_state.shape[-2], beam_state.shape[-2], joint_graph,
                           beam_graph, self.n_graphs or 1)
        js, bs = answer_unroll(self.model, joint_state, beam_state, Static(joint_bc, beam_bc, index), t,
                               self.stepper)
        return js, bs, rebuild_all_points(js, bs)


def plain_inputs(f: EpisodeFeatures) -> tuple[torch.Tensor, torch.Tensor, Static, torch.Tensor]:
    """One design's frame 0 on its own plain graph (not a union of one): joint and beam states, the static graph and
    the frame times; what the compiled single-design rollout and learn.evaluate's eager reference start from."""
    return (torch.as_tensor(f.joint_state[0]), torch.as_tensor(f.beam_state[0]),
            static_from(f.joint_bc, f.beam_bc, f.incidence), torch.as_tensor(f.t, dtype=torch.float32))


def graph_inputs(f: EpisodeFeatures | list[EpisodeFeatures]) -> tuple[torch.Tensor, ...]:
    """The positional inputs of a compiled rollout: of one design (frame 0 and the frame times), or of a list of
    designs as one disjoint union (then also which design every joint and beam belongs to). The designs of a list
    share their frame times (the first's are used)."""
    if not isinstance(f, list):
        j0, b0, s, t = plain_inputs(f)
        return j0, b0, s.joint_bc, s.beam_bc, s.index.senders, s.index.receivers, s.index.edge_beam, t
    b = GraphSet.first_frames(f)
    g = b.index
    return (b.joint_state[0], b.beam_state[0], b.static.joint_bc, b.static.beam_bc, g.senders, g.receivers,
            g.edge_beam, torch.as_tensor(f[0].t, dtype=torch.float32), g.joint_graph, g.beam_graph)


def _trace(model: Simulator, inputs: tuple[torch.Tensor, ...], n_graphs: int | None) -> torch.jit.ScriptModule:
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)  # the step count and constant matrices are meant
        traced = torch.jit.trace(_Unroll(model.eval(), n_graphs), inputs, check_trace=False)
        return torch.jit.optimize_for_inference(torch.jit.freeze(traced.eval()))


class CompiledRollout:
    """Compiled rollouts, called like _Unroll with graph_inputs(f): the same numbers as the eager rollout, as many
    steps as the inputs' frame times give. backend "aot": every step of every model (an ensemble's members each) is
    an AOTInductor package (learn/aot.py: compiled once per model and input shapes, kept in `cache`; "aot_tuned" the
    same with each matrix product's kernel picked by timing), the rest of the
    rollout (the copies an answer averages, stacking the frames, rebuilding the points) plain PyTorch: the fastest
    for one design (session 38: x0.67 of the trace). backend "torchscript" (the default): TorchScript rollouts
    (traced, frozen), a fraction of the Python overhead per step, as many steps as the traced example has frames - 1.
    An additive model has one trace that serves every graph; a kinematic model's placement order (learn/kinematics.py)
    is baked into its trace, so it keeps one per graph (incidence and fixed joint), traced on first use; a stiffness
    model's linear system has the graph's size baked in, so it keeps one per size (joints, beams). Called with the
    inputs of a list of designs (graph_inputs), it rolls them out as one disjoint union: one pass of the network for
    all of them, each union's design count and size traced in (one trace per count and size)."""

    def __init__(self, model: Simulator, example: EpisodeFeatures, backend: str = "torchscript",
                 cache: str | None = None):
        self.model = model
        self.backend = backend_checked(backend)
        self.stepper = AotSteps(cache, backend=self.backend) if self.backend in AOT_BACKENDS else None
        self.traces: dict = {}
        with torch.inference_mode():
            self(*graph_inputs(example))

    @staticmethod
    def n_graphs(inputs: tuple[torch.Tensor, ...]) -> int | None:
        """Designs in a union's inputs (graph_inputs of a list); None for one design's."""
        return int(inputs[8][-1]) + 1 if len(inputs) > 8 else None

    def key(self, inputs: tuple[torch.Tensor, ...]):
        n = self.n_graphs(inputs)
        if self.stepper is not None:  # the stepper keeps a package per input shapes; one _Unroll per design count
            return ("aot", n)
        union = () if n is None else ("union", n)  # a union's design count is traced in
        if self.model.kinematic:  # its placement order is traced in: one trace per graph
            joint_bc, senders, receivers, edge_beam = inputs[2], inputs[4], inputs[5], inputs[6]
            fixed = joint_bc[:, JOINT.bc.slice("fixed")]
            return union + tuple(tuple(x.reshape(-1).tolist()) for x in (senders, receivers, edge_beam, fixed))
        # a stiffness model's solve, the beams' spans and a union's design slots have the graph's size traced in
        if n is not None or self.model.stiffness or self.model.span_input:
            return union + tuple(inputs[0].shape[-2:]) + tuple(inputs[1].shape[-2:])
        return None

    def __call__(self, *inputs: torch.Tensor):
        key = self.key(inputs)
        if key not in self.traces:
            self.traces[key] = (_Unroll(self.model.eval(), self.n_graphs(inputs), self.stepper)
                                if self.stepper is not None else _trace(self.model, inputs, self.n_graphs(inputs)))
        return self.traces[key](*inputs)


def compile_rollout(model: Simulator, example: EpisodeFeatures, backend: str = "torchscript",
                    cache: str | None = None) -> CompiledRollout:
    """A compiled rollout, compiled on `example` (see CompiledRollout; backend torchscript | aot | aot_tuned, cache:
    where aot keeps its packages, learn.aot.default_cache when None)."""
    return CompiledRollout(model, example, backend, cache)


@dataclass
class Rollout:
    """Every intermediate graph of a rollout (frame 0 = the input design) and the points rebuilt from it."""

    t: np.ndarray  # [F]
    joint_states: np.ndarray  # [F, J, JOINT.state_size] geometry | stress, translated (fixed joint at origin)
    beam_states: np.ndarray  # [F, B, BEAM.state_size]
    points: np.ndarray  # [F, P, 3] mm, in the episode's own coordinates (comparable to node_xyz[:, point_nodes])
    point_nodes: np.ndarray  # [P] FEA node id each point stands for
    origin: np.ndarray  # [3] translation between the graphs' frame and the episode's coordinates
    features: EpisodeFeatures  # the source, for its incidence, boundary conditions and FEA reference
    member_points: np.ndarray | None = None  # [M, F, P, 3] each ensemble member's own answer (None: one model)

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def graph(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(joint features, beam features) of one frame; the incidence is features.incidence."""
        return self.joint_states[frame], self.beam_states[frame]

    @property
    def local_points(self) -> np.ndarray:
        """[F, P, 3] points in the translated frame (comparable to features.fea_points)."""
        return self.points - self.origin

    def welded(self) -> Rollout:
        """The same rollout with one position per FEA node (learn.features.welded: a beam's end face and its joint's
        face at their mean), ensemble members' points likewise: the answer as one solid. The validity check reads
        the unwelded rollout, whose dislocation is what welding hides."""
        members = None if self.member_points is None else welded(self.member_points, self.point_nodes)
        return replace(self, points=welded(self.points, self.point_nodes), member_points=members)


def as_features(source) -> EpisodeFeatures:
    return source if isinstance(source, EpisodeFeatures) else extract(source)


def rollout(model: Simulator, source, steps: int = 10, t: np.ndarray | None = None) -> Rollout:
    """Run `steps` steps from frame 0 of `source` (an Episode or its EpisodeFeatures; only frame 0 is used).
    Frame times: `t` if given, else the source's own when it has steps + 1 frames, else evenly spaced in [0, 1]."""
    return rollout_many(model, [source], steps, t)[0]


def frame_times(features: list[EpisodeFeatures], steps: int, t: np.ndarray | None) -> np.ndarray:
    """The frame times of a rollout of `features`: `t` if given, else each design's own when it has steps + 1
    frames and evenly spaced in [0, 1] when not, which must then be the same for all of them."""
    if t is None:
        each = [f.t if len(f.t) == steps + 1 else np.linspace(0.0, 1.0, steps + 1) for f in features]
        if any(not np.allclose(x, each[0]) for x in each):
            raise ValueError("the designs' frame times differ: give t, or roll them out apart")
        t = each[0]
    return np.asarray(t, dtype=np.float64)


def rollout_many(model: Simulator, sources: list, steps: int = 10, t: np.ndarray | None = None) -> list[Rollout]:
    """rollout of every source, all designs advanced together as one disjoint union (GraphSet of their frame 0, a
    single design too: a union of one): one network pass per
    step for the lot, so the fixed cost of a step's few hundred small operations is shared (what a design search
    that scores many candidates pays per design); each answer is the one its design gets alone, up to rounding.
    Frame times: frame_times."""
    features = [as_features(s) for s in sources]
    b = GraphSet.first_frames(features)
    t = frame_times(features, steps, t)
    inputs = (b.joint_state[0], b.beam_state[0], b.static, torch.as_tensor(t, dtype=torch.float32))
    members = None
    with torch.inference_mode():
        if isinstance(model, Ensemble):  # the members' answers, kept for their spread; the answer is their mean
            members = [answer_unroll(m, *inputs) for m in model.members]
            js, bs = stack_mean(members)
        else:
            js, bs = answer_unroll(model, *inputs)
    out = []
    for i, f in enumerate(features):
        own = lambda j, s: (b.part(j, i, JOINT), b.part(s, i, BEAM))  # noqa: E731
        member_points = None if members is None else \
            torch.stack([rebuild_all_points(*own(*m)) for m in members]).numpy() + f.origin
        ji, bi = own(js, bs)
        out.append(Rollout(t=t, joint_states=ji.numpy(), beam_states=bi.numpy(),
                           points=rebuild_all_points(ji, bi).numpy() + f.origin, point_nodes=f.point_nodes,
                           origin=f.origin, features=f, member_points=member_points))
    return out


def reference(source) -> Rollout:
    """The FEA episode itself as a Rollout (its features per frame and the points they rebuild): the
    representation's floor for errors, and a known-good input for validity checks."""
    f = as_features(source)
    pts = rebuild_all_points(f.joint_state.astype(np.float64), f.beam_state.astype(np.float64))
    return Rollout(t=f.t, joint_states=f.joint_state, beam_states=f.beam_state, points=pts + f.origin,
                   point_nodes=f.point_nodes, origin=f.origin, features=f)


def input_floor(model: Simulator | Ensemble, source) -> np.ndarray:
    """[F, P] distance between the points rebuilt from the FEA's features and from the same features as the
    network sees them (each block's geometry through its PCA and back, Simulator.input_geometry): how finely
    the inputs resolve the shape, a floor for what any network on them can predict (an ensemble: its coarsest
    member's)."""
    f = as_features(source)
    static = static_from(f.joint_bc, f.beam_bc, f.incidence)
    with torch.inference_mode():
        js, bs = torch.as_tensor(f.joint_state), torch.as_tensor(f.beam_state)
        exact = rebuild_all_points(js, bs)
        return np.max([(rebuild_all_points(*m.input_geometry(js, bs, static)) - exact).norm(dim=-1).numpy()
                       for m in members_of(model)], axis=0)
