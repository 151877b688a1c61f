"""A graph-network block over joints and beams: interaction MLPs per directed edge, sum per receiver, update MLPs."""
from __future__ import annotations

import torch
from torch import nn

from learn.checks import number_in
from learn.graph import GraphIndex


ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "gelu": nn.GELU, "tanh": nn.Tanh}


def activation_checked(name) -> str:
    """model.activation: the hidden layers' nonlinearity, one of ACTIVATIONS."""
    if name not in ACTIVATIONS:
        raise ValueError(f"model.activation={name!r}: must be one of {sorted(ACTIVATIONS)}")
    return name


def fraction_checked(value, name: str) -> float:
    """A rate in [0, 1) (0 = off), or a ValueError naming the field."""
    return number_in(value, name, 0, 1, "0 = off", high_open=True)


def dropout_checked(p) -> float:
    """model.dropout: the probability of zeroing a hidden unit while training, in [0, 1)."""
    return fraction_checked(p, "model.dropout")


def mlp(n_in: int, widths: list[int], n_out: int, layer_norm: bool = False, activation: str = "relu",
        dropout: float = 0.0) -> nn.Sequential:
    """MLP n_in -> widths... -> n_out with `activation` (ACTIVATIONS) after every hidden layer, followed by
    Dropout(dropout) when dropout > 0 (active in training mode only); linear output, then LayerNorm if asked;
    pyramid-shaped when widths decrease."""
    nonlinearity = ACTIVATIONS[activation_checked(activation)]
    p = dropout_checked(dropout)
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(n_in, w), nonlinearity()] + ([nn.Dropout(p)] if p > 0 else [])
        n_in = w
    layers.append(nn.Linear(n_in, n_out))
    if layer_norm:
        layers.append(nn.LayerNorm(n_out))
    return nn.Sequential(*layers)


def sum_to(messages: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """[..., E, H] summed over the edges sharing a receiver -> [..., n, H]."""
    out = messages.new_zeros(*messages.shape[:-2], n, messages.shape[-1])
    return out.index_add_(-2, index, messages)


def summed_over_edges(m: nn.Sequential, first: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """sum_to(m's output on every edge, index, n), given m's first layer on every edge (`first`, before its
    activation). When m ends in a Linear after hidden layers, the sum goes before that layer:
    sum_e (W h_e + b) = W (sum_e h_e) + n_r b, so the last layer runs once per receiver (9 joints, 12 beams of a 3 x 3
    grid) instead of once per directed edge (24); the same sum to float32 rounding. Otherwise (a LayerNorm after the
    last layer, no hidden layer) every edge's output is made and summed."""
    last = m[-1]
    if len(m) < 3 or not isinstance(last, nn.Linear):
        return sum_to(m[1:](first), index, n)
    hidden = sum_to(m[1:-1](first), index, n)  # [..., n, H]
    count = sum_to(first.new_ones(first.shape[-2], 1), index, n)  # [n, 1] edges per receiver
    return last(hidden) + (count - 1.0) * last.bias


def design_means(x: torch.Tensor, graph: torch.Tensor | None, n_graphs: int) -> torch.Tensor:
    """[..., n, H] rows -> [..., n_graphs, H] the mean of each design's rows (graph: the design of every row in a
    disjoint union; None: all rows are one design)."""
    if graph is None:
        return x.mean(-2, keepdim=True)
    # rows per design as a sum of ones into n_graphs slots (not bincount, whose length depends on the data): a
    # compiled step (learn/aot.py) has every shape fixed by its inputs' shapes
    count = x.new_zeros(n_graphs).index_add_(0, graph, x.new_ones(graph.shape[0])).clamp_min(1)[:, None]
    return sum_to(x, graph, n_graphs) / count


def to_rows(u: torch.Tensor, graph: torch.Tensor | None, n: int) -> torch.Tensor:
    """[..., n_graphs, H] per design -> [..., n, H] per row of the design (inverse of design_means' grouping)."""
    return u.expand(*u.shape[:-2], n, u.shape[-1]) if graph is None else u.index_select(-2, graph)


def update_inputs(design: nn.Module | None, joints: torch.Tensor, beams: torch.Tensor, to_joints: torch.Tensor,
                  to_beams: torch.Tensor, g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
    """The update MLPs' inputs cat(X_joint, sum of I_joint) and cat(X_beam, sum of I_beam); with a `design` MLP
    (graph_nets' global attribute) also the design-wide vector u = design(mean of I_joint over the design's joints,
    mean of I_beam over its beams), appended to every joint's and beam's row."""
    joint_in, beam_in = [joints, to_joints], [beams, to_beams]
    if design is not None:
        u = design(torch.cat([design_means(to_joints, g.joint_graph, g.n_graphs),
                              design_means(to_beams, g.beam_graph, g.n_graphs)], -1))
        joint_in.append(to_rows(u, g.joint_graph, joints.shape[-2]))
        beam_in.append(to_rows(u, g.beam_graph, beams.shape[-2]))
    return torch.cat(joint_in, -1), torch.cat(beam_in, -1)


class GNBlock(nn.Module):
    """The thesis' GN block (its Figure 34): f_I-joint and f_I-beam see cat(X_beam, X_sender, X_receiver, X_edge)
    of each directed edge; f_U-beam sees cat(X_beam, sum of I_beam), f_U-joint cat(X_joint, sum of I_joint).

    With global_latent > 0 (graph_nets' global attribute, not in the thesis) a design-wide vector
    u = f_G(mean of I_joint over the design's joints, mean of I_beam over its beams) is appended to both update
    MLPs' inputs, so one block reaches the whole grid instead of one hop."""

    def __init__(self, joint_in: int, beam_in: int, edge_in: int, latent: int, widths: list[int],
                 joint_out: int, beam_out: int, layer_norm: bool = False, latent_out: bool = False,
                 global_latent: int = 0, activation: str = "relu", dropout: float = 0.0):
        """layer_norm: LayerNorm after the interaction MLPs, and after the update MLPs too when their output is a
        latent graph (latent_out) rather than the final update; activation, dropout: the MLPs' (mlp)."""
        super().__init__()
        self.pair_split = [beam_in, joint_in, joint_in, edge_in]  # X_beam | X_sender | X_receiver | X_edge
        pair = sum(self.pair_split)
        a, p = activation, dropout
        self.joint_interaction = mlp(pair, widths, latent, layer_norm, a, p)
        self.beam_interaction = mlp(pair, widths, latent, layer_norm, a, p)
        self.design = mlp(2 * latent, widths, global_latent, layer_norm, a, p) if global_latent > 0 else None
        self.beam_update = mlp(beam_in + latent + global_latent, widths, beam_out, layer_norm and latent_out, a, p)
        self.joint_update = mlp(joint_in + latent + global_latent, widths, joint_out, layer_norm and latent_out, a, p)

    def interactions(self, joints: torch.Tensor, beams: torch.Tensor, edges: torch.Tensor,
                     g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
        """f_I-joint(pair) and f_I-beam(pair) of every directed edge, pair = cat(X_beam, X_sender, X_receiver,
        X_edge) (received sums them without making them)."""
        joint_first, beam_first = self.first_layers(joints, beams, edges, g)
        return self.joint_interaction[1:](joint_first), self.beam_interaction[1:](beam_first)

    def received(self, joints: torch.Tensor, beams: torch.Tensor, edges: torch.Tensor,
                 g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
        """The interactions summed per receiver: f_I-joint over each joint's incoming edges [..., J, latent],
        f_I-beam over each beam's two edges [..., B, latent] (summed_over_edges)."""
        joint_first, beam_first = self.first_layers(joints, beams, edges, g)
        return (summed_over_edges(self.joint_interaction, joint_first, g.receivers, joints.shape[-2]),
                summed_over_edges(self.beam_interaction, beam_first, g.edge_beam, beams.shape[-2]))

    def first_layers(self, joints: torch.Tensor, beams: torch.Tensor, edges: torch.Tensor,
                     g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
        """The first layers of f_I-joint and f_I-beam (before their activation) on every directed edge's pair. They
        are linear in the pair, so each is applied to every beam and joint once and the
        products gathered per edge: W pair = W_b X_beam + W_s X_sender + W_r X_receiver + W_e X_edge, the same sum
        with about half the multiply-adds (a graph has twice as many directed edges as beams and 3x as many as
        joints); the two MLPs share those products as one matrix."""
        mlps = (self.joint_interaction, self.beam_interaction)
        weight = torch.cat([m[0].weight for m in mlps])  # [2 H, P]: both first layers
        bias = torch.cat([m[0].bias for m in mlps])
        # split sizes from the module, not the inputs' shapes, so a frozen trace folds these weights into constants
        w_beam, w_sender, w_receiver, w_edge = weight.split(self.pair_split, dim=1)
        per_joint = joints @ torch.cat([w_sender, w_receiver]).T  # [..., J, 4 H]: as sender | as receiver
        as_sender, as_receiver = per_joint.split(weight.shape[0], dim=-1)
        hidden = ((beams @ w_beam.T).index_select(-2, g.edge_beam) + as_sender.index_select(-2, g.senders)
                  + as_receiver.index_select(-2, g.receivers) + edges @ w_edge.T + bias)  # [..., E, 2 H]
        joint_hidden, beam_hidden = hidden.split([m[0].out_features for m in mlps], dim=-1)
        return joint_hidden, beam_hidden

    def forward(self, joints: torch.Tensor, beams: torch.Tensor, edges: torch.Tensor,
                g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor]:
        # joints [..., J, Dj], beams [..., B, Db], edges [..., E, De] -> [..., J, joint_out], [..., B, beam_out]
        to_joints, to_beams = self.received(joints, beams, edges, g)  # [..., J, latent], [..., B, latent]
        joint_in, beam_in = update_inputs(self.design, joints, beams, to_joints, to_beams, g)
        return self.joint_update(joint_in), self.beam_update(beam_in)


class ProcessorBlock(nn.Module):
    """One message-passing step of an encode-process-decode core (MeshGraphNets' processor, on the joint/beam
    graph), every update residual: a directed edge's latent e += f_E(e, h_beam, h_sender, h_receiver); then
    h_joint += f_J(h_joint, sum of its incoming edges' e) and h_beam += f_B(h_beam, sum of its two edges' e).
    With global_latent > 0 the joint and beam updates also see a design-wide vector from the mean edge sums, as in
    GNBlock."""

    def __init__(self, latent: int, widths: list[int], layer_norm: bool = True, global_latent: int = 0,
                 activation: str = "relu", dropout: float = 0.0):
        super().__init__()
        a, p = activation, dropout
        self.edge = mlp(4 * latent, widths, latent, layer_norm, a, p)
        self.design = mlp(2 * latent, widths, global_latent, layer_norm, a, p) if global_latent > 0 else None
        self.joint = mlp(2 * latent + global_latent, widths, latent, layer_norm, a, p)
        self.beam = mlp(2 * latent + global_latent, widths, latent, layer_norm, a, p)

    def forward(self, joints: torch.Tensor, beams: torch.Tensor, edges: torch.Tensor,
                g: GraphIndex) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # latents joints [..., J, L], beams [..., B, L], edges [..., E, L] -> the same, updated
        edges = edges + self.edge(torch.cat([edges, beams.index_select(-2, g.edge_beam),
                                             joints.index_select(-2, g.senders),
                                             joints.index_select(-2, g.receivers)], -1))
        to_joints = sum_to(edges, g.receivers, joints.shape[-2])
        to_beams = sum_to(edges, g.edge_beam, beams.shape[-2])
        joint_in, beam_in = update_inputs(self.design, joints, beams, to_joints, to_beams, g)
        return joints + self.joint(joint_in), beams + self.beam(beam_in), edges
