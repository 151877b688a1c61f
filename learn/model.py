"""The learned simulator: per-term PCA encoding, a single or double GN core, and G(t+1) = G(t) + dG."""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from learn import frames, kinematics, stiffness
from learn.checks import integer_in, number_in
from learn.gn import GNBlock, ProcessorBlock, activation_checked, dropout_checked, mlp
from learn.graph import BEAM, JOINT, Block, GraphIndex
from learn.pca import Moments, Normalizer, TermPCA
from learn.symmetry import LATTICE_QUARTER_TURNS

TERMS = ("joint_geometry", "joint_stress", "joint_bc", "beam_geometry", "beam_stress", "beam_bc")
EDGE_FEATURES = 6  # sender centre and receiver centre relative to the beam's middle centre
EDGE_FEATURES_LOCAL = 18  # the same in the beam's frame + the two joints' frames relative to the beam's (6 each)
FRAMES = ("global", "local", "fixed")  # model.frame: the frames features and updates are expressed in
UPDATES = ("additive", "kinematic", "direct", "stiffness")  # model.update: how the network's output makes a state


class SingleGN(nn.Module):
    """One GN block from the input graph straight to the update dG."""

    def __init__(self, joint_in, beam_in, edge_in, joint_out, beam_out, latent: int, widths: list[int],
                 layer_norm: bool = False, global_latent: int = 0, activation: str = "relu", dropout: float = 0.0):
        super().__init__()
        self.gn = GNBlock(joint_in, beam_in, edge_in, latent, widths, joint_out, beam_out, layer_norm,
                          global_latent=global_latent, activation=activation, dropout=dropout)

    def forward(self, joints, beams, edges, g: GraphIndex):
        return self.gn(joints, beams, edges, g)


class DoubleGN(nn.Module):
    """GN1 computes a latent graph G'; GN2 sees cat(G, G') and computes dG (unshared parameters). With n_blocks > 2
    the chain continues: GN_k sees cat(G, G'_{k-1}), so information travels n_blocks hops per step."""

    def __init__(self, joint_in, beam_in, edge_in, joint_out, beam_out, latent: int, widths: list[int],
                 layer_norm: bool = False, n_blocks: int = 2, global_latent: int = 0, activation: str = "relu",
                 dropout: float = 0.0):
        super().__init__()
        assert n_blocks >= 2, "a double GN has at least two blocks"
        shared = dict(global_latent=global_latent, activation=activation, dropout=dropout)
        first = GNBlock(joint_in, beam_in, edge_in, latent, widths, latent, latent, layer_norm, latent_out=True,
                        **shared)
        middle = [GNBlock(joint_in + latent, beam_in + latent, edge_in, latent, widths, latent, latent, layer_norm,
                          latent_out=True, **shared) for _ in range(n_blocks - 2)]
        last = GNBlock(joint_in + latent, beam_in + latent, edge_in, latent, widths, joint_out, beam_out, layer_norm,
                       **shared)
        self.blocks = nn.ModuleList([first, *middle, last])

    def forward(self, joints, beams, edges, g: GraphIndex):
        lj, lb = self.blocks[0](joints, beams, edges, g)
        for block in self.blocks[1:]:
            lj, lb = block(torch.cat([joints, lj], -1), torch.cat([beams, lb], -1), edges, g)
        return lj, lb


class EncodeProcessDecode(nn.Module):
    """MeshGraphNets' core on the joint/beam graph (not in the thesis): MLPs encode joints, beams and directed edges
    to latents of one size, n_blocks residual ProcessorBlocks pass messages (one joint-beam-joint hop each), MLPs
    decode each joint's and beam's latent to dG. Reach grows with n_blocks at little arithmetic per block (its MLPs
    see latents, not the concatenated inputs of every block in the chain), but each block adds a fixed number of small
    operations to every step, which is what a one-design rollout's time follows (docs/learned_simulator.md, session 8)."""

    def __init__(self, joint_in, beam_in, edge_in, joint_out, beam_out, latent: int, widths: list[int],
                 layer_norm: bool = True, n_blocks: int = 6, global_latent: int = 0, activation: str = "relu",
                 dropout: float = 0.0):
        super().__init__()
        a, p = activation, dropout
        self.encode_joint = mlp(joint_in, widths, latent, layer_norm, a, p)
        self.encode_beam = mlp(beam_in, widths, latent, layer_norm, a, p)
        self.encode_edge = mlp(edge_in, widths, latent, layer_norm, a, p)
        self.blocks = nn.ModuleList([ProcessorBlock(latent, widths, layer_norm, global_latent, a, p)
                                     for _ in range(n_blocks)])
        self.decode_joint = mlp(latent, widths, joint_out, activation=a, dropout=p)
        self.decode_beam = mlp(latent, widths, beam_out, activation=a, dropout=p)

    def forward(self, joints, beams, edges, g: GraphIndex):
        hj, hb, he = self.encode_joint(joints), self.encode_beam(beams), self.encode_edge(edges)
        for block in self.blocks:
            hj, hb, he = block(hj, hb, he, g)
        return self.decode_joint(hj), self.decode_beam(hb)


CORES = {"single_gn": SingleGN, "double_gn": DoubleGN, "epd": EncodeProcessDecode}


def output_layers(core: nn.Module) -> tuple[nn.Linear, nn.Linear]:
    """The linear layers that give a core's joint and beam outputs."""
    if isinstance(core, EncodeProcessDecode):
        heads = (core.decode_joint, core.decode_beam)
    else:
        last = core.gn if isinstance(core, SingleGN) else core.blocks[-1]
        heads = (last.joint_update, last.beam_update)
    return tuple(next(m for m in reversed(h) if isinstance(m, nn.Linear)) for h in heads)


@dataclass
class Static:
    """What stays fixed during a rollout: boundary-condition terms and the incidence."""

    joint_bc: torch.Tensor  # [J, JOINT.bc.size]
    beam_bc: torch.Tensor  # [B, BEAM.bc.size]
    index: GraphIndex
    tree: kinematics.Tree | None = None  # built on first use by the kinematic update
    layout: stiffness.Layout | None = None  # built on first use by the stiffness update
    spans: torch.Tensor | None = None  # built on first use by model.span_input

    def beam_spans(self) -> torch.Tensor:
        """[..., B, 1] every beam's span ratio (learn.model.beam_spans), the same at every step."""
        if self.spans is None:
            self.spans = beam_spans(self.joint_bc, self.index)
        return self.spans

    def stiffness_layout(self) -> stiffness.Layout:
        """Where the stiffness update's terms go in its linear systems (the same at every step)."""
        if self.layout is None:
            fixed = self.joint_bc[..., JOINT.bc.slice("fixed")][..., 0] > 0.5
            self.layout = stiffness.layout(self.index, fixed)
        return self.layout

    def kinematic_tree(self) -> kinematics.Tree:
        if self.tree is None:
            fixed = self.joint_bc[..., JOINT.bc.slice("fixed")].detach().cpu().numpy()
            self.tree = kinematics.tree(self.index, fixed)
        return self.tree


def beam_spans(joint_bc: torch.Tensor, g: GraphIndex) -> torch.Tensor:
    """[..., B, 1] log(S_along / S_across) per beam: S_along the extent of its design's flat joint centres (the bc
    positions [..., J, 3] of joint_bc) along the beam's own in-plane direction, S_across the extent across it. A
    grid whose actuators all bend alike cannot bend both ways (the curvature it asks for is not a developable
    surface): it rolls along its longer span or snaps into a bowl (docs/learned_simulator.md, sessions 29-30), so
    > 0 says "I run along the way my grid is longest". Invariant to turning, mirroring and relabelling the design
    (an extent does not change with the beam's sense), so every copy of a design reads the same."""
    p = joint_bc[..., JOINT.bc.slice("position")][..., :2]  # [..., J, 2] mm
    a, c = g.beam_ends()
    d = p.index_select(-2, c) - p.index_select(-2, a)
    along = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # [..., B, 2]
    across = torch.stack([-along[..., 1], along[..., 0]], -1)
    design, local, G, N = stiffness.design_slots(g, p.shape[-2])
    slot = design * N + local
    padded = p.new_zeros(*p.shape[:-2], G * N, 2).index_copy(-2, slot, p).unflatten(-2, (G, N))
    present = torch.zeros(G * N).index_fill(0, slot, 1.0).view(G, N) > 0.5
    beam_design = g.beam_graph if g.beam_graph is not None else torch.zeros(g.n_beams, dtype=torch.long)
    mine, mask = padded.index_select(-3, beam_design), present.index_select(0, beam_design)  # [..., B, N, 2], [B, N]

    def extent(u: torch.Tensor) -> torch.Tensor:
        s = (mine * u[..., None, :]).sum(-1)  # [..., B, N]
        inf = torch.tensor(float("inf"), dtype=s.dtype)
        return torch.where(mask, s, -inf).amax(-1) - torch.where(mask, s, inf).amin(-1)

    return torch.log(extent(along).clamp_min(1e-6) / extent(across).clamp_min(1e-6))[..., None]


def with_current_position(bc: torch.Tensor, state: torch.Tensor, block: Block) -> torch.Tensor:
    """bc [n, D] with its "position" field replaced by the block's current origin point of state [..., n, S]."""
    pos = block.bc.slice("position")
    origin = state[..., block.origin_slice]
    lead = origin.shape[:-1]
    return torch.cat([bc[..., :pos.start].expand(*lead, pos.start), origin,
                      bc[..., pos.stop:].expand(*lead, bc.shape[-1] - pos.stop)], -1)


def local_geometry(geometry: torch.Tensor, block: Block) -> torch.Tensor:
    """[..., n, G] geometry with every point relative to the block's own origin point."""
    return kinematics.relative_to(geometry, geometry[..., block.origin_slice], block)


TERM_KINDS = ("geometry", "stress", "bc")


def rollout_rotations_checked(value, name: str) -> int:
    """A rotation count for answer_unroll: an integer in [1, 64]."""
    return integer_in(value, name, 1, 64, "1 = the network alone")


def rollout_lattice_turns_checked(value, name: str, kinematic: bool = False) -> int:
    """Labellings an answer is averaged over (learn.symmetry.LATTICE_QUARTER_TURNS): 1, 2 or 4; more than one only
    for an additive update (a kinematic model places beams along a tree that a relabelling changes)."""
    if isinstance(value, bool) or not isinstance(value, int) or value not in LATTICE_QUARTER_TURNS:
        raise ValueError(f"{name}={value!r}: must be one of {sorted(LATTICE_QUARTER_TURNS)} (1 = the design as "
                         "labelled; 2 = also from the opposite lattice corner; 4 = from all four corners)")
    if value > 1 and kinematic:
        raise ValueError(f"{name}={value}: needs model.update=additive (a kinematic model places beams along its "
                         "kinematic tree, which a relabelling changes)")
    return int(value)


def passes_checked(value) -> int:
    """model.passes: network passes per step, each with its own core, each reading the state the last one reached."""
    return integer_in(value, "model.passes", 1, 4, "1 = one pass per step, the thesis; 2 = a predictor and a "
                      "corrector that reads where the predictor went")


def global_latent_checked(value) -> int:
    """model.global_latent: length of the design-wide vector of every GN block (0: none, the thesis' block)."""
    return integer_in(value, "model.global_latent", 0, 1024, "0 = no design-wide vector")


def term_retention(retention: float | dict) -> dict[str, float]:
    """pca_retention as {term kind: variance fraction kept}: one number for every term, or a mapping with a value
    per kind (geometry, stress, bc); each in (0, 1]."""
    given = dict(retention) if isinstance(retention, Mapping) else {k: retention for k in TERM_KINDS}
    unknown = sorted(set(given) - set(TERM_KINDS))
    missing = sorted(set(TERM_KINDS) - set(given))
    if unknown or missing:
        raise ValueError(f"pca_retention: keys must be {list(TERM_KINDS)} (unknown {unknown}, missing {missing})")
    return {kind: number_in(value, f"pca_retention.{kind}", 0, 1, "the share of the term's variance kept",
                            low_open=True) for kind, value in given.items()}


class Simulator(nn.Module):
    """States in, next states out; every statistic (PCA, normalisers) is a buffer of this module.

    args: core ("double_gn" | "single_gn" | "epd": encode-process-decode), n_blocks (double_gn: GN blocks in the
          chain, 2 = the thesis; epd: processor blocks),
          latent (int), widths (list[int]), time_input (bool), layer_norm (bool), pin_fixed_joint (bool),
          bc_position ("reference": the boundary-condition position is the block's reference position relative
          to the fixed joint; "current": its current one),
          global_latent (int >= 0: a design-wide vector per GN block, graph_nets' global; 0 = the thesis),
          activation (the MLPs' hidden nonlinearity: relu, the thesis', and what args without the key get | silu,
          conf/model's default since session 9 | gelu | tanh),
          dropout (float in [0, 1): Dropout after every hidden layer of every MLP while training; 0, no layer, is what
          args without the key get),
          frame ("global": features translated to each block's origin, as in the thesis; "local": also rotated
          into each block's own frame, updates predicted there, gravity given per block; implies a current
          bc position; "fixed": also rotated about z into the design's frame, the fixed joint's in-plane axes
          (learn.frames.design_frame), updates predicted there: exactly invariant to rotations of the design
          about z, so the rotation augmentation adds nothing),
          update ("additive": G(t+1) = G(t) + dG, the thesis; "kinematic": geometry updates are
          predicted in each block's parent frame and placed outward from the fixed joint, learn/kinematics.py;
          stress stays additive; "direct": G(t) = G(0) + dG(G(0), t), every frame from the flat design and its
          time, nothing fed back, so no error compounds and the frames are one batched pass; a variant beside
          the thesis' step-by-step update, learn.rollout.unroll; "stiffness": the network also predicts every
          beam's stiffness and natural increment and every joint's anchoring and load, one linear solve per
          design moves the joints rigidly (the matrix stiffness method, learn/stiffness.py) and the beams with
          them, and the additive dG is added on top; with frame local every beam's stiffness and natural increment
          and every joint's anchoring and own motion are read in the block's own frame, a law of what the block
          sees there),
          passes (int in [1, 4], default 1, as checkpoints before session 49 were written; conf/model's default 2:
          network passes per step, each with its own core; a pass after the first, a corrector, reads the state the
          pass before reached and adds its update, additive or stiffness),
          span_input (bool, default false: every beam also reads beam_spans, log of its design's flat span along it
          over the span across it: which way an all-one-kind grid rolls),
          stress_input (bool, default true: the stress terms are network inputs; false:
          predicted and carried in the state, not read back), pca ({term: [D, K]} for every name in TERMS)
          -- all plain types, so they are saved in checkpoints.
    """

    def __init__(self, args: dict):
        super().__init__()
        self.args = dict(args)
        if args.get("frame", "global") not in FRAMES:
            raise ValueError(f"model.frame={args.get('frame')!r}: must be one of {' | '.join(FRAMES)}")
        self.local = args.get("frame", "global") == "local"  # every block in its own frame
        self.rotated = args.get("frame", "global") != "global"  # features and updates in frames R (local or fixed)
        update = args.get("update", "additive")
        if update not in UPDATES:
            raise ValueError(f"model.update={update!r}: must be {' | '.join(UPDATES)}")
        self.kinematic = update == "kinematic"
        self.direct = update == "direct"  # every frame from the design: G(0) + dG(G(0), t)
        self.stiffness = update == "stiffness"
        self.beam_middle = stiffness.beam_middle_checked(args.get("beam_middle", "mean"))
        self.passes = passes_checked(args.get("passes", 1))
        if self.passes > 1 and (self.direct or self.kinematic):
            raise ValueError(f"model.passes={self.passes}: needs model.update=additive or stiffness (a corrector pass "
                             f"adds to the state the last pass reached; got {update!r}): set model.passes=1 with "
                             "this update")
        if self.direct and not args.get("time_input", True):
            raise ValueError("model.update=direct needs model.time_input=true (the time is all that tells its "
                             "frames apart)")
        self.pca = nn.ModuleDict({t: TermPCA(*args["pca"][t]) for t in TERMS})
        self.edge_norm = Normalizer(EDGE_FEATURES_LOCAL if self.local else EDGE_FEATURES)
        self.joint_delta = Normalizer(JOINT.state_size)
        self.beam_delta = Normalizer(BEAM.state_size)
        if self.rotated:  # the deltas above are in the blocks' frames; the loss and noise read the global columns
            self.joint_step = Normalizer(JOINT.state_size)
            self.beam_step = Normalizer(BEAM.state_size)
        if self.kinematic:  # geometry updates in the parent's frame (learn/kinematics.py)
            self.joint_rel_delta = Normalizer(JOINT.geometry.size)
            self.beam_rel_delta = Normalizer(BEAM.geometry.size)
        extra = (1 if args.get("time_input", True) else 0) + (3 if self.local else 0)
        self.span_input = bool(args.get("span_input", False))
        joint_in = sum(self.pca[t].k for t in self.input_terms(JOINT)) + extra
        beam_in = sum(self.pca[t].k for t in self.input_terms(BEAM)) + extra + (1 if self.span_input else 0)
        core_args = dict(layer_norm=bool(args.get("layer_norm", False)),
                         global_latent=global_latent_checked(args.get("global_latent", 0)),
                         activation=activation_checked(args.get("activation", "relu")),
                         dropout=dropout_checked(args.get("dropout", 0.0)))
        if args["core"] not in CORES:
            raise ValueError(f"model.core={args['core']!r}: must be one of {sorted(CORES)}")
        if args["core"] in ("double_gn", "epd"):
            core_args["n_blocks"] = integer_in(args.get("n_blocks", 2), "model.n_blocks",
                                               2 if args["core"] == "double_gn" else 1, 64, "message-passing blocks")
        extra_out = (stiffness.JOINT_OUT, stiffness.BEAM_OUT) if self.stiffness else (0, 0)
        make_core = lambda: CORES[args["core"]](  # noqa: E731
            joint_in, beam_in, self.edge_norm.mean.shape[0], JOINT.state_size + extra_out[0],
            BEAM.state_size + extra_out[1], int(args["latent"]), [int(w) for w in args["widths"]], **core_args)
        self.core = make_core()
        if self.stiffness:  # the rigid solve carries the geometry at first; the additive geometry update starts at 0
            for layer, block in zip(output_layers(self.core), (JOINT, BEAM)):
                with torch.no_grad():
                    layer.weight[block.geometry_slice].zero_()
                    layer.bias[block.geometry_slice].zero_()
        # passes > 1: correctors, each a core of its own reading the state the pass before reached; they start as
        # no correction (every output 0: no additive update, and no stiffness wish, so the solve moves nothing)
        self.correctors = nn.ModuleList([make_core() for _ in range(self.passes - 1)])
        for corrector in self.correctors:
            for layer in output_layers(corrector):
                with torch.no_grad():
                    layer.weight.zero_()
                    layer.bias.zero_()

    # ------------------------------------------------------------------------------------------- features
    def input_terms(self, block: Block) -> tuple[str, ...]:
        """The terms of a block the network sees: geometry, stress and bc, or without stress_input no stress (the
        stress stays in the state and in the loss, predicted but not read back)."""
        return tuple(f"{block.name}_{kind}" for kind in self.input_kinds)

    @property
    def input_kinds(self) -> tuple[str, ...]:
        return TERM_KINDS if self.args.get("stress_input", True) else ("geometry", "bc")

    def frames(self, joint_state, beam_state, static: Static):
        """Block frames [..., J, 3, 3], [..., B, 3, 3] (frame local: each block's own; fixed: its design's) or
        (None, None) (frame global)."""
        if not self.rotated:
            return None, None
        if not self.local:
            return frames.design_frame(joint_state, static.joint_bc[..., JOINT.bc.slice("fixed")], static.index)
        return frames.frame(joint_state, JOINT), frames.frame(beam_state, BEAM)

    def _block_terms(self, state, bc, block: Block, R, kinds=TERM_KINDS) -> dict[str, torch.Tensor]:
        terms = {}
        if "geometry" in kinds:
            geometry = local_geometry(state[..., block.geometry_slice], block)
            terms["geometry"] = geometry if R is None else frames.rotate_vectors(geometry, R, to_local=True)
        if "stress" in kinds:
            stress = state[..., block.stress_slice]
            terms["stress"] = stress if R is None else frames.rotate_stresses(stress, R, to_local=True)
        if "bc" in kinds:
            if self.local or self.args.get("bc_position", "reference") == "current":
                bc = with_current_position(bc, state, block)
            if R is not None:
                pos = block.bc.slice("position")
                bc = bc.expand(*R.shape[:-2], bc.shape[-1])  # a reference bc [n, D] turns with each state's frames
                bc = torch.cat([bc[..., :pos.start], frames.rotate_vectors(bc[..., pos], R, to_local=True),
                                bc[..., pos.stop:]], -1)
            terms["bc"] = bc
        return {f"{block.name}_{kind}": x for kind, x in terms.items()}

    def raw_terms(self, joint_state, beam_state, static: Static, R=(None, None),
                  kinds: tuple[str, ...] = TERM_KINDS) -> dict[str, torch.Tensor]:
        """The terms of `kinds` (every term by default) as the PCA sees them (geometry translated to each block's
        own origin, with frame local or fixed also rotated into the block's frame); R: frames from self.frames,
        computed here when not given."""
        Rj, Rb = R if R[0] is not None or not self.rotated else self.frames(joint_state, beam_state, static)
        return {**self._block_terms(joint_state, static.joint_bc, JOINT, Rj, kinds),
                **self._block_terms(beam_state, static.beam_bc, BEAM, Rb, kinds)}

    def input_geometry(self, joint_state, beam_state, static: Static) -> tuple[torch.Tensor, torch.Tensor]:
        """The states with every block's geometry replaced by what the network sees of it: its local geometry
        through the term's PCA and back (the stress columns are kept). With a PCA that keeps every component this
        is the state itself; the gap is the resolution of the inputs (evaluate reports it as the input floor)."""
        R = self.frames(joint_state, beam_state, static)
        raw = self.raw_terms(joint_state, beam_state, static, R)
        out = []
        for state, block, R_block in ((joint_state, JOINT, R[0]), (beam_state, BEAM, R[1])):
            pca = self.pca[f"{block.name}_geometry"]
            local = pca.inverse(pca(raw[f"{block.name}_geometry"]))
            if R_block is not None:
                local = frames.rotate_vectors(local, R_block, to_local=False)
            g = block.geometry_slice
            placed = kinematics.placed_at(local, state[..., block.origin_slice], block)
            out.append(torch.cat([state[..., :g.start], placed, state[..., g.stop:]], -1))
        return out[0], out[1]

    def edge_features(self, joint_state, beam_state, static: Static, R=(None, None)) -> torch.Tensor:
        """[..., E, De] sender and receiver centres relative to the beam's middle centre (the pair's origin);
        with frames expressed in the beam's frame, in local mode with the joints' frames relative to the beam's."""
        g = static.index
        jc = joint_state[..., JOINT.origin_slice]
        bc = beam_state[..., BEAM.origin_slice].index_select(-2, g.edge_beam)
        rel = torch.cat([jc.index_select(-2, g.senders) - bc, jc.index_select(-2, g.receivers) - bc], -1)
        if not self.rotated:
            return rel
        Rj, Rb = R if R[0] is not None else self.frames(joint_state, beam_state, static)
        Re = Rb.index_select(-3, g.edge_beam)
        if not self.local:
            return frames.rotate_vectors(rel, Re, to_local=True)
        return torch.cat([frames.rotate_vectors(rel, Re, to_local=True),
                          frames.relative_rotation(Re, Rj.index_select(-3, g.senders)),
                          frames.relative_rotation(Re, Rj.index_select(-3, g.receivers))], -1)

    def coefficients(self, joint_state, beam_state, static: Static, R=(None, None),
                     kinds: tuple[str, ...] = TERM_KINDS) -> dict[str, torch.Tensor]:
        return {t: self.pca[t](x) for t, x in self.raw_terms(joint_state, beam_state, static, R, kinds).items()}

    def encode(self, joint_state, beam_state, static: Static, t, R=(None, None)):
        """-> network inputs joints [..., J, Dj], beams [..., B, Db], edges [..., E, De]."""
        if self.rotated and R[0] is None:
            R = self.frames(joint_state, beam_state, static)
        z = self.coefficients(joint_state, beam_state, static, R, self.input_kinds)  # only what the network reads
        lead = joint_state.shape[:-2]
        parts_j = [z[k].expand(*lead, *z[k].shape[-2:]) for k in self.input_terms(JOINT)]
        parts_b = [z[k].expand(*lead, *z[k].shape[-2:]) for k in self.input_terms(BEAM)]
        if self.args.get("time_input", True):
            t = (t if isinstance(t, torch.Tensor) else torch.tensor(t)).to(joint_state.dtype)
            t = t.expand(lead).reshape(*lead, 1, 1)
            parts_j.append(t.expand(*lead, joint_state.shape[-2], 1))
            parts_b.append(t.expand(*lead, beam_state.shape[-2], 1))
        if self.local:
            parts_j.append(frames.gravity(R[0]))
            parts_b.append(frames.gravity(R[1]))
        if self.span_input:
            spans = static.beam_spans()
            parts_b.append(spans.expand(*lead, *spans.shape[-2:]))
        edges = self.edge_norm(self.edge_features(joint_state, beam_state, static, R))
        return torch.cat(parts_j, -1), torch.cat(parts_b, -1), edges

    def step_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every state column's step std in the global frame, joints' and beams': the units of the training loss and
        of its noise. With frame local or fixed the deltas' normalisers hold the stds in the blocks' frames, which
        weigh a global column by a local one's spread (an extrusion's step across itself is ~0 in its joint's frame),
        so those models keep the global ones apart (before session 31 their loss used the local ones)."""
        if self.rotated:
            return self.joint_step.std, self.beam_step.std
        return self.joint_delta.std, self.beam_delta.std

    # ------------------------------------------------------------------------------------------- dynamics
    def forward(self, joint_state, beam_state, static: Static, t, R=(None, None), core: nn.Module | None = None):
        """Normalised updates dG: [..., J, JOINT.state_size], [..., B, BEAM.state_size] (frame local or fixed: in
        the blocks' frames R, which are computed here when not given), of the first pass's core unless given."""
        if self.rotated and R[0] is None:
            R = self.frames(joint_state, beam_state, static)
        return (core or self.core)(*self.encode(joint_state, beam_state, static, t, R), static.index)

    def step(self, joint_state, beam_state, static: Static, t):
        """G(t+1) = G(t) + dG, in raw units (update direct: G(t) = G(0) + dG, called with the design's states G(0)
        and the time t of the frame it answers, learn.rollout.unroll). With pin_fixed_joint the fixed joint's
        geometry does not move (its top face is glued to the support): a boundary condition applied outside the
        network. With passes > 1 each corrector then reads the state reached and adds its own update (the same
        kind, at the same step time t), as a Newton iteration corrects a predictor."""
        joint_state, beam_state = self._pass(self.core, joint_state, beam_state, static, t)
        for corrector in self.correctors:
            joint_state, beam_state = self._pass(corrector, joint_state, beam_state, static, t, correction=True)
        return joint_state, beam_state

    def _pass(self, core: nn.Module, joint_state, beam_state, static: Static, t, correction: bool = False):
        """One network pass of a step: the core's update applied to the states (step). A correction's additive
        update is its output times the step's std, without the mean step (an output of 0 changes nothing)."""
        R = self.frames(joint_state, beam_state, static)
        dj, db = self(joint_state, beam_state, static, t, R, core)
        if self.kinematic:
            return self._kinematic_step(joint_state, beam_state, static, dj, db, R)
        if self.stiffness:  # the grid's rigid compromise first (learn/stiffness.py), then the additive update on it
            dj, joint_raw = dj.split([JOINT.state_size, stiffness.JOINT_OUT], -1)
            db, beam_raw = db.split([BEAM.state_size, stiffness.BEAM_OUT], -1)
            scale = self.step_std()[0][JOINT.origin_slice].mean()  # mm: a joint centre's step
            plan = static.stiffness_layout()  # built at the first step, kept for the rest
            v, omega = stiffness.solve(joint_state[..., JOINT.origin_slice], beam_state[..., BEAM.origin_slice],
                                       joint_raw, beam_raw, None, static.index, scale, plan,
                                       R if self.rotated else None)
            joint_state, beam_state = stiffness.rigidly_moved(joint_state, beam_state, v, omega, plan.ends,
                                                             self.beam_middle)
        if correction:
            dj, db = dj * self.joint_delta.std, db * self.beam_delta.std
        else:
            dj, db = self.joint_delta.inverse(dj), self.beam_delta.inverse(db)
        if self.rotated:
            dj = frames.rotate_state(dj, JOINT, R[0], to_local=False)
            db = frames.rotate_state(db, BEAM, R[1], to_local=False)
        if self.args.get("pin_fixed_joint", False):
            free = 1.0 - static.joint_bc[..., JOINT.bc.slice("fixed")]  # [J, 1]
            geometry = torch.zeros(JOINT.state_size, dtype=dj.dtype)
            geometry[JOINT.geometry_slice] = 1.0
            dj = dj * (1.0 - geometry * (1.0 - free))
        return joint_state + dj, beam_state + db

    def _kinematic_step(self, joint_state, beam_state, static: Static, dj, db, R):
        """Geometry: each block's geometry in its parent's frame plus the predicted change, placed outward from the
        fixed joint (learn/kinematics.py); stress: additive (predicted in the block's own frame R in local mode).
        dj, db: normalised network outputs."""
        tree = static.kinematic_tree()
        G, Gb = JOINT.geometry_slice, BEAM.geometry_slice
        d_rel_j = self.joint_rel_delta.inverse(dj[..., G])
        if self.args.get("pin_fixed_joint", False):
            d_rel_j = d_rel_j * (tree.joint_parent >= 0).to(d_rel_j)[:, None]
        pose = kinematics.parent_pose(joint_state, beam_state, tree)
        rel_j = kinematics.to_parent(joint_state[..., G], *pose[JOINT.name], JOINT) + d_rel_j
        rel_b = kinematics.to_parent(beam_state[..., Gb], *pose[BEAM.name], BEAM) + \
            self.beam_rel_delta.inverse(db[..., Gb])
        roots = kinematics.from_parent(rel_j, *pose[JOINT.name], JOINT)  # only the roots' rows are used
        jg, bg = kinematics.place(roots, rel_j, rel_b, tree)
        dsj = self.joint_delta.inverse(dj)[..., JOINT.stress_slice]
        dsb = self.beam_delta.inverse(db)[..., BEAM.stress_slice]
        if self.rotated:
            dsj, dsb = frames.rotate_stresses(dsj, R[0], False), frames.rotate_stresses(dsb, R[1], False)
        js, bs = joint_state[..., JOINT.stress_slice] + dsj, beam_state[..., BEAM.stress_slice] + dsb
        return torch.cat([jg, js], -1), torch.cat([bg, bs], -1)

    def updates(self, joint_state, beam_state) -> tuple[torch.Tensor, torch.Tensor, slice]:
        """The updates dG the network answers along states [F, n, D] of an episode, and the frames they start from:
        G(k+1) - G(k) from frames :-1, or with update direct G(k) - G(0) for k >= 1, all from frame 0."""
        if self.direct:
            return joint_state[1:] - joint_state[:1], beam_state[1:] - beam_state[:1], slice(0, 1)
        return joint_state.diff(dim=0), beam_state.diff(dim=0), slice(0, -1)

    @classmethod
    def fit(cls, args: dict, joint_state: torch.Tensor, beam_state: torch.Tensor, static: Static,
            retention: float | dict = 1.0, delta_floor: float = 0.01) -> "Simulator":
        """A simulator whose PCA and normalisers are fitted on training states [F, J, Dj], [F, B, Db]."""
        return cls.fit_blocks(args, lambda: [(joint_state, beam_state, static)], retention, delta_floor)

    @classmethod
    def fit_blocks(cls, args: dict, blocks: Callable[[], Iterable[tuple[torch.Tensor, torch.Tensor, Static]]],
                   retention: float | dict = 1.0, delta_floor: float = 0.01) -> "Simulator":
        """As fit, on training states given a block of designs at a time: blocks() yields (joint_state, beam_state,
        static) and is called twice (the moments of every term, then the PCA coefficients' range), so the fit never
        holds more than one block's terms (learn.dataset.TurnedSet.fit_blocks turns each block as it is reached)."""
        probe = cls({**args, "pca": {t: [1, 1] for t in TERMS}})
        moments: dict[str, Moments] = {}

        def add(name: str, x: torch.Tensor) -> None:
            moments.setdefault(name, Moments(x.shape[-1])).add(x.reshape(-1, x.shape[-1]).numpy())

        with torch.no_grad():
            for joint_state, beam_state, static in blocks():
                R = probe.frames(joint_state, beam_state, static)
                for t, x in probe.raw_terms(joint_state, beam_state, static, R).items():
                    add(t, x)
                add("edge_norm", probe.edge_features(joint_state, beam_state, static, R))
                dj, db, start = probe.updates(joint_state, beam_state)
                if probe.rotated:  # updates as the network predicts them: in the frame of the step's start state
                    add("joint_step", dj)
                    add("beam_step", db)
                    dj = frames.rotate_state(dj, JOINT, R[0][start], to_local=True)
                    db = frames.rotate_state(db, BEAM, R[1][start], to_local=True)
                add("joint_delta", dj)
                add("beam_delta", db)
                if probe.kinematic:
                    rj, rb = kinematics.relative(joint_state, beam_state, static.kinematic_tree())
                    add("joint_rel_delta", rj.diff(dim=0))
                    add("beam_rel_delta", rb.diff(dim=0))
        keep = term_retention(retention)
        pcas = {t: TermPCA.from_moments(moments[t], keep[t.split("_", 1)[1]]) for t in TERMS}
        model = cls({**args, "pca": {t: [p.dim, p.k] for t, p in pcas.items()}})
        with torch.no_grad():
            for joint_state, beam_state, static in blocks():  # the coefficients' training range
                for t, x in probe.raw_terms(joint_state, beam_state, static).items():
                    pcas[t].widen_range(x.reshape(-1, x.shape[-1]).numpy())
        for t, p in pcas.items():
            model.pca[t].load_state_dict(p.state_dict())
        steps = (("joint_step", JOINT), ("beam_step", BEAM)) if model.rotated else ()
        for name, block in (("edge_norm", None), ("joint_delta", JOINT), ("beam_delta", BEAM), *steps):
            groups = None if block is None else [block.geometry_slice, block.stress_slice]
            getattr(model, name).load_state_dict(
                Normalizer.from_moments(moments[name], delta_floor if block else 0.0, groups).state_dict())
        if model.kinematic:
            for name in ("joint_rel_delta", "beam_rel_delta"):
                getattr(model, name).load_state_dict(Normalizer.from_moments(moments[name], delta_floor).state_dict())
        return model

    @property
    def rollout_rotations(self) -> int:
        """Rotations about z a rollout is averaged over (learn.rollout.answer_unroll); 1: the network alone."""
        return int(self.args.get("rollout_rotations", 1))

    @property
    def rollout_mirror(self) -> bool:
        """Whether a rollout is also averaged over the mirror image (learn.rollout.answer_unroll)."""
        return bool(self.args.get("rollout_mirror", False))

    @property
    def rollout_lattice_turns(self) -> int:
        """Lattice labellings a rollout is averaged over (learn.rollout.answer_unroll); 1: the design as labelled."""
        return int(self.args.get("rollout_lattice_turns", 1))

    def answer_with(self, rollout_rotations=None, rollout_mirror=None, rollout_lattice_turns=None) -> "Simulator":
        """Override the stored rollout_rotations / rollout_mirror / rollout_lattice_turns (None keeps them); returns
        self."""
        if rollout_lattice_turns is not None:
            self.args["rollout_lattice_turns"] = rollout_lattice_turns_checked(
                rollout_lattice_turns, "rollout_lattice_turns", self.kinematic)
        if rollout_rotations is not None:
            self.args["rollout_rotations"] = rollout_rotations_checked(rollout_rotations, "rollout_rotations")
        if rollout_mirror is not None:
            if not isinstance(rollout_mirror, bool):
                raise ValueError(f"rollout_mirror={rollout_mirror!r}: must be true or false")
            self.args["rollout_mirror"] = rollout_mirror
        return self

    @property
    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def static_from(joint_bc: np.ndarray, beam_bc: np.ndarray, incidence, device="cpu") -> Static:
    return Static(torch.as_tensor(joint_bc, dtype=torch.float32, device=device),
                  torch.as_tensor(beam_bc, dtype=torch.float32, device=device), incidence.tensors(device))
