"""A learned stiffness-method step (model.update=stiffness): joints are rigid bodies, each beam an elastic connector
between its two joints whose stiffness and natural increment the network predicts, and one small linear solve per
design and step finds the joints' increments that balance every beam at once.

Why: in the FEA a beam bends as far as the grid's loops let it (scripts/beam_bends.py, 260 episodes: an up actuator
reaches 20-93 % of its free bend, correlation 0.44 with it), and an FEA increment couples the whole grid through
K du = dF. An additive
step reads each block's increment off two hops of messages; here the network only says, per beam, how it wants its two
joints to move relative to each other and how stiffly, per joint, what holds and loads it, and the solve (the matrix
stiffness method of frame analysis) makes the compromise for the whole grid, as the FEA's does.

Unknowns per joint: a translation v (mm) and a rotation omega (rad), as x = (v, r omega) with r = ROTATION_ARM mm so
both are lengths. A beam from joint a to joint c with middle centre q sees its ends' relative motion at q and their
relative rotation,
    D_b x = (v_c + omega_c x (q - p_c) - v_a - omega_a x (q - p_a),  r (omega_c - omega_a)),
and stores 1/2 (D_b x - e_b)^T W_b (D_b x - e_b): W_b = L L^T + EPS I (SPD from 21 outputs), e_b its natural increment
(6 outputs, in units of the step scale, bounded by WISH_BOUND). Each joint adds 1/2 (x - u_j)^T diag(m_j) (x - u_j):
a motion u_j of its own (what loads it alone, e.g. its share of the weight) held at stiffness m_j, so that every term
is a wish with a weight and the answer a compromise between wishes, never larger than they are for want of stiffness.
The fixed joint is held: its unknowns are eliminated. The minimum over the free joints,
    K x = f,  K = sum_b D_b^T W_b D_b + diag(m),  f = sum_b D_b^T W_b e_b + m u,
is solved per design (dense [6J, 6J], SPD, float64: 48 free unknowns for a 3x3 grid). Every stiffness is bounded
(BOUND) and floored (EPS), so no network output makes the system singular or its answer unbounded. The joints move
rigidly by x; a beam's start and end sections move with their joints and its middle section with the mean of the two
motions (model.beam_middle=mean) or as an elastic beam's middle does (hermite: the cubic Hermite interpolation of its
ends' motions, below). learn.model adds the network's additive update dG on top, for what the rigid motion does not
carry (the beams' own bend, the stress).

The middle of a beam whose ends s_a, s_c turn by omega_a, omega_c: Euler-Bernoulli with end loads only (and the
circular arc of a uniformly curved actuator, to first order) deflects its middle by the cubic Hermite shape,
    u(1/2) = (u_a + u_c) / 2 + L/8 (omega_a - omega_c) x t     (t the unit chord, L its length),
while the mean of the two joints' rigid motions at the middle centre q gives L/4 for L/8: twice the bow. Hence
    u_mid = (u_a(q) + u_c(q)) / 2 - (R_a - R_c)(s_c - s_a) / 8,
with u_j(x) joint j's rigid motion of a point x and R_j its rotation; exact for any rigid motion of the whole (R_a =
R_c: no correction, whether or not the beam is straight) and rotated with the design.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from learn.graph import BEAM, JOINT, GraphIndex, SECTIONS
from learn.kinematics import POINTS

JOINT_OUT = 12  # per joint: anchoring stiffness m (6, positive) | own motion u (6, in units of the step scale)
BEAM_OUT = 27  # per beam: stiffness W (21, Cholesky factor, positive diagonal) | natural increment e (6)
ROTATION_ARM = 20.0  # mm: r, the lever that makes a rotation a length (about half a beam)
EPS = 1e-2  # W = L L^T + EPS I and m + EPS: every beam and joint resists every motion a little
BOUND = 10.0  # entries of L and the anchorings m stay below this (smoothly), so K's condition stays below ~1e6
WISH_BOUND = 10.0  # step scales: e and u are WISH_BOUND tanh(raw / WISH_BOUND) step scales, so that no step can wish
                   # for more than that however far outside its training range a network is driven (linear near 0)
BEAM_MIDDLES = ("mean", "hermite")  # model.beam_middle: how a beam's middle section follows its joints (module doc)
_TRIL = torch.tril_indices(6, 6)
_ON_DIAGONAL = _TRIL[0] == _TRIL[1]


def _skew_map() -> torch.Tensor:
    """[3, 9]: d @ it = skew(d) flattened, skew(d) @ w = d x w (the Levi-Civita symbol)."""
    E = torch.zeros(3, 3, 3)
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):  # skew(d)[i, j] = -eps_ijk d_k
        E[k, i, j], E[k, j, i] = -1.0, 1.0
    return E.flatten(1)


_SKEW = _skew_map()


def skew(d: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> [..., 3, 3] with skew(d) @ w = d x w."""
    return (d @ _SKEW.to(d.dtype)).unflatten(-1, (3, 3))


def bounded(raw: torch.Tensor, bound: float = BOUND) -> torch.Tensor:
    """raw -> (-bound, bound), the identity near 0."""
    return bound * torch.tanh(raw / bound)


def positive(raw: torch.Tensor) -> torch.Tensor:
    """raw -> (0, BOUND): softplus, smoothly capped."""
    return bounded(F.softplus(raw))


def spd(raw: torch.Tensor) -> torch.Tensor:
    """[..., 21] -> [..., 6, 6] L L^T + EPS I, L lower triangular (raw in torch.tril_indices order) with bounded
    entries and a positive diagonal."""
    entries = torch.where(_ON_DIAGONAL, positive(raw), bounded(raw))
    L = raw.new_zeros(*raw.shape[:-1], 6, 6)
    L[..., _TRIL[0], _TRIL[1]] = entries
    return L @ L.transpose(-1, -2) + EPS * torch.eye(6, dtype=raw.dtype)


def wish(raw: torch.Tensor) -> torch.Tensor:
    """A network output as a wished motion in step scales: raw near 0, never beyond WISH_BOUND."""
    return bounded(raw, WISH_BOUND)


def _connection_maps() -> tuple[torch.Tensor, torch.Tensor]:
    """D = D0 + (q - p_a, q - p_c) @ T (the connection below is affine in the two lever arms): D0 [6, 12], T [6, 72]."""
    eye = torch.eye(3)
    D0 = torch.zeros(6, 12)
    D0[:3, :3], D0[:3, 6:9], D0[3:, 3:6], D0[3:, 9:] = -eye, eye, -eye, eye
    T = torch.zeros(6, 6, 12)  # omega x d = -d x omega = -skew(d) omega, omega = (r omega) / r
    T[:3, :3, 3:6] = _SKEW.view(3, 3, 3) / ROTATION_ARM
    T[3:, :3, 9:] = -_SKEW.view(3, 3, 3) / ROTATION_ARM
    return D0, T.flatten(1)


_D0, _T = _connection_maps()


def connection(p_a: torch.Tensor, p_c: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Joint centres [..., B, 3] at a beam's start and end, its middle centre q -> D [..., B, 6, 12] mapping
    (v_a, r omega_a, v_c, r omega_c) to the relative motion at q and r times the relative rotation:
    (v_c + omega_c x (q - p_c) - v_a - omega_a x (q - p_a), r (omega_c - omega_a))."""
    arms = torch.cat([q - p_a, q - p_c], -1)
    return _D0.to(q.dtype) + (arms @ _T.to(q.dtype)).unflatten(-1, (6, 12))


def design_slots(g: GraphIndex, n_joints: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """Design [J] and index within it [J] of every joint, the number of designs and the most joints one has."""
    if g.joint_graph is None:
        return torch.zeros(n_joints, dtype=torch.long), torch.arange(n_joints), 1, n_joints
    counts = torch.bincount(g.joint_graph, minlength=g.n_graphs)
    starts = torch.cumsum(counts, 0) - counts
    return g.joint_graph, torch.arange(n_joints) - starts[g.joint_graph], g.n_graphs, int(counts.max())


@dataclass
class Layout:
    """Where each joint's and beam's terms go in the stacked designs' systems: the same at every step of a rollout,
    so built once per graph (Static.stiffness_layout). G designs of n = 6 N unknowns (N: the most joints of one)."""
    ends: tuple[torch.Tensor, torch.Tensor]  # [B] twice: every beam's start and end joint (GraphIndex.beam_ends)
    joint_dof: torch.Tensor  # [J * 6] each joint's unknowns among all designs' stacked G * n
    free: torch.Tensor  # [..., G, n] 1 for the unknowns solved for, 0 for the fixed joint's and the padding's
    n_designs: int
    n: int
    # K's entries in the stacked G * n * n matrices: every beam's 12 x 12 block, then every joint's anchoring, either on
    # the diagonal [J * 6] (global outputs) or as its two 3 x 3 diagonal blocks [J * 18] (read in the joint's frame)
    stiffness_at: tuple[torch.Tensor, torch.Tensor]
    loads_at: torch.Tensor  # f's entries: every beam's two joints' unknowns [B * 12], then every joint's [J * 6]
    kept: torch.Tensor  # [..., G, n, n] free_i free_j: K's rows and columns of the solved unknowns
    eliminated: torch.Tensor  # [..., G, n, n] diag(1 - free): the identity on the held and padding unknowns


def layout(g: GraphIndex, fixed: torch.Tensor) -> Layout:
    """The Layout of a graph whose fixed flags are `fixed` [..., J]."""
    a, c = g.beam_ends()
    design, local, G, N = design_slots(g, fixed.shape[-1])
    n = 6 * N
    k6 = torch.arange(6)
    joint_dof = design[:, None] * n + 6 * local[:, None] + k6  # [J, 6]
    beam_dof = torch.cat([joint_dof.index_select(0, a), joint_dof.index_select(0, c)], -1)  # [B, 12]
    pairs = (beam_dof // n)[:, :, None] * n * n + (beam_dof % n)[:, :, None] * n + (beam_dof % n)[:, None, :]
    diagonal = design[:, None] * n * n + (6 * local[:, None] + k6) * (n + 1)
    own = (6 * local[:, None] + k6).view(-1, 2, 3)  # [J, 2, 3] each joint's translations | rotations in its design
    joint_blocks = design[:, None, None, None] * n * n + own[:, :, :, None] * n + own[:, :, None, :]  # [J, 2, 3, 3]
    held = (1.0 - fixed.double())[..., None].expand(*fixed.shape, 6).reshape(*fixed.shape[:-1], -1)
    free = torch.zeros(*fixed.shape[:-1], G * n, dtype=torch.float64).index_add(-1, joint_dof.reshape(-1), held)
    joint_dof, pairs, free = joint_dof.reshape(-1), pairs.reshape(-1), free.unflatten(-1, (G, n))
    return Layout((a, c), joint_dof, free, G, n,
                  (torch.cat([pairs, diagonal.reshape(-1)]), torch.cat([pairs, joint_blocks.reshape(-1)])),
                  torch.cat([beam_dof.reshape(-1), joint_dof]),
                  free[..., :, None] * free[..., None, :], torch.diag_embed(1.0 - free))


def solve(centres: torch.Tensor, middles: torch.Tensor, joint_raw: torch.Tensor, beam_raw: torch.Tensor,
          fixed: torch.Tensor | None, g: GraphIndex, scale: torch.Tensor,
          plan: Layout | None = None, frames: tuple[torch.Tensor, torch.Tensor] | None = None
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint centres [..., J, 3], beam middle centres [..., B, 3], the network's stiffness outputs [..., J, JOINT_OUT]
    and [..., B, BEAM_OUT], the fixed flags [..., J] (broadcast; only read to make the layout), the step scale (mm),
    and the systems' layout (layout(g, fixed): the beams' ends and where every term goes), made here when not
    given -> every joint's translation v [..., J, 3] (mm) and rotation omega [..., J, 3] (rad) at the minimum (module
    doc); the fixed joint's unknowns are eliminated (held at 0 exactly). Assembled and solved in float64 outside
    autocast (a few 54 x 54 SPD systems, by Cholesky). frames (model.frame local or fixed): every joint's and beam's
    axes [..., J, 3, 3] and [..., B, 3, 3] (learn.frames), in which the outputs are read: a beam's stiffness and
    natural increment, a joint's anchoring and own motion are its own, turned into the global frame by T =
    diag(R, R) (W -> T W T^T, e -> T e; a joint's anchoring then two full 3 x 3 blocks), so that a law that depends
    only on what a block sees in its frame is the same law at every orientation of the block. A beam's term is
    assembled as (T^T D)^T W (T^T D), the same product with its connection turned into its frame instead."""
    out_dtype = centres.dtype
    plan = layout(g, fixed) if plan is None else plan
    a, c = plan.ends
    with torch.autocast("cpu", enabled=False):
        centres, middles = centres.double(), middles.double()
        joint_raw, beam_raw, scale = joint_raw.double(), beam_raw.double(), scale.double()
        lead, J, G, n = centres.shape[:-2], centres.shape[-2], plan.n_designs, plan.n
        W = spd(beam_raw[..., :21])
        e = wish(beam_raw[..., 21:27]) * scale
        m = positive(joint_raw[..., :6]) + EPS
        u = wish(joint_raw[..., 6:12]) * scale
        D = connection(centres.index_select(-2, a), centres.index_select(-2, c), middles)
        if frames is None:  # the outputs are global: the anchorings diagonal
            anchor, load = m.flatten(-2), (m * u).flatten(-2)
        else:  # D^T T W T^T D = (T^T D)^T W (T^T D): D's rows turned into the beam's frame, W and e kept in it
            Rj, Rb = (R.double()[..., None, :, :] for R in frames)  # [..., n, 1, 3, 3]: for both halves of T
            D = (Rb.transpose(-1, -2) @ D.unflatten(-2, (2, 3))).flatten(-3, -2)
            m3, mu3 = m.unflatten(-1, (2, 3)), (m * u).unflatten(-1, (2, 3))  # translation | rotation halves
            M = Rj * m3[..., None, :] @ Rj.transpose(-1, -2)  # T diag(m) T^T: diag(R diag(m_v) R^T, R diag(m_w) R^T)
            anchor, load = M.flatten(-4), (Rj @ mu3[..., None]).flatten(-4)
        DtW = D.transpose(-1, -2) @ W  # [..., B, 12, 6]
        K = torch.zeros(*lead, G * n * n, dtype=torch.float64).index_add(
            -1, plan.stiffness_at[frames is not None], torch.cat([(DtW @ D).flatten(-3), anchor], -1))
        f = torch.zeros(*lead, G * n, dtype=torch.float64).index_add(
            -1, plan.loads_at, torch.cat([(DtW @ e[..., None]).flatten(-3), load], -1))
        K = K.unflatten(-1, (G, n, n)) * plan.kept + plan.eliminated
        x = torch.cholesky_solve((f.unflatten(-1, (G, n)) * plan.free)[..., None], torch.linalg.cholesky_ex(K)[0])
        x = x.reshape(*lead, G * n).index_select(-1, plan.joint_dof).unflatten(-1, (J, 6)).to(out_dtype)
        return x[..., :3], x[..., 3:] / ROTATION_ARM


def rotation(omega: torch.Tensor) -> torch.Tensor:
    """[..., 3] rotation vectors -> [..., 3, 3] rotation matrices, exp(skew(omega)) by Rodrigues' formula
    I + sin(t)/t K + (1 - cos(t))/t^2 K^2 (t = |omega|, Taylor terms below t^2 = 1e-6, so gradients stay finite)."""
    K = skew(omega)
    t2 = (omega * omega).sum(-1)[..., None, None]
    small = t2 < 1e-6
    safe = torch.where(small, torch.ones_like(t2), t2)
    t = safe.sqrt()
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / safe)
    return torch.eye(3, dtype=omega.dtype) + a * K + b * (K @ K)


def beam_middle_checked(value) -> str:
    """model.beam_middle: one of BEAM_MIDDLES."""
    if value not in BEAM_MIDDLES:
        raise ValueError(f"model.beam_middle={value!r}: must be {' | '.join(BEAM_MIDDLES)} (how a beam's middle "
                         "section follows its two joints' rigid motions)")
    return value


def rigidly_moved(joint_state: torch.Tensor, beam_state: torch.Tensor, v: torch.Tensor, omega: torch.Tensor,
                  ends: tuple[torch.Tensor, torch.Tensor], middle: str = "mean") -> tuple[torch.Tensor, torch.Tensor]:
    """The states with every joint moved rigidly by (v, omega) about its centre, each beam's start and end sections
    (ends: GraphIndex.beam_ends) with their joints and its middle section with the mean of its two joints' motions
    (middle "mean") or by their cubic Hermite interpolation ("hermite", module doc); stress columns unchanged.
    Outside autocast: the states are carried in float32, never rounded to bfloat16."""
    hermite = beam_middle_checked(middle) == "hermite"
    with torch.autocast("cpu", enabled=False):
        return _rigidly_moved(joint_state, beam_state, v.to(joint_state.dtype), omega.to(joint_state.dtype), *ends,
                              hermite)


# each beam section's share of its start and its end joint's motion: start (1, 0), middle (1/2, 1/2), end (0, 1)
_SHARES = torch.tensor([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])
_SHARE_WEIGHTS = _SHARES.T[:, None, :, None]  # [2 (start, end joint), 1, section, 1], as motions [..., 2, B, section, 3]
_MIDDLE = torch.tensor([0.0, 1.0, 0.0])[:, None]  # the section that bows


def _rigidly_moved(joint_state, beam_state, v, omega, a, c, hermite):
    J, B = omega.shape[-2], len(a)
    ac = torch.cat([a, c])
    R_all = rotation(torch.cat([omega, 0.5 * omega.index_select(-2, ac).unflatten(-2, (2, B)).sum(-3)], -2))
    R, R_mid = R_all[..., :J, :, :], R_all[..., J:, :, :]  # [..., J, 3, 3] every joint's; [..., B, 3, 3] the mean
    p = joint_state[..., JOINT.origin_slice]
    jg = joint_state[..., JOINT.geometry_slice].unflatten(-1, (-1, 3))  # [..., J, fields, 3]
    point = POINTS[JOINT.name].to(jg)  # the centre (the joint's origin) moves by v, its vectors turn
    jg = point * (jg + v[..., None, :]) + (1.0 - point) * (jg @ R.transpose(-1, -2))

    bg = beam_state[..., BEAM.geometry_slice].unflatten(-1, (len(SECTIONS), 3, 3))  # [..., B, section, field, 3]
    centres = bg[..., 0, :]  # [..., B, section, 3]
    R_ends = R.index_select(-3, ac).unflatten(-3, (2, B))  # [..., 2 (start and end joint), B, 3, 3]
    arms = centres[..., None, :, :, :] - p.index_select(-2, ac).unflatten(-2, (2, B))[..., None, :]
    # each end joint's rigid displacement of every section centre: v + R (x - p) - (x - p)  [..., 2, B, section, 3]
    motions = (v.index_select(-2, ac).unflatten(-2, (2, B))[..., None, :] - arms
               + arms @ R_ends.transpose(-1, -2))
    moved = centres + (_SHARE_WEIGHTS.to(centres) * motions).sum(-4)  # sum over k of shares[s, k] motions[k, b, s]
    if hermite:  # half the rigid motions' bow: - (R_a - R_c)(s_c - s_a) / 8, on the middle section
        chord = centres[..., SECTIONS.index("end"), :] - centres[..., SECTIONS.index("start"), :]
        bow = torch.einsum("...bij,...bj->...bi", R_ends[..., 0, :, :, :] - R_ends[..., 1, :, :, :], chord)
        moved = moved - 0.125 * _MIDDLE.to(moved) * bow[..., None, :]
    R_sections = torch.stack([R_ends[..., 0, :, :, :], R_mid, R_ends[..., 1, :, :, :]], -3)  # in SECTIONS order
    vectors = bg[..., 1:, :] @ R_sections.transpose(-1, -2)
    bg = torch.cat([moved[..., None, :], vectors], -2).flatten(-3)
    return (torch.cat([jg.flatten(-2), joint_state[..., JOINT.stress_slice]], -1),
            torch.cat([bg, beam_state[..., BEAM.stress_slice]], -1))


def layout_checked() -> None:
    """The beam geometry this module moves: per section (start, middle, end) a centre point, then two vectors."""
    names = [(f.name, f.kind) for f in BEAM.geometry.fields]
    want = [(f"{s}_{n}", k) for s in SECTIONS for n, k in (("center", "point"), ("width", "vector"),
                                                           ("height", "vector"))]
    if names != want or SECTIONS != ("start", "middle", "end"):  # _SHARES and _MIDDLE are in this order
        raise RuntimeError(f"learn.stiffness expects beam geometry fields {want} of sections start, middle, end; "
                           f"got {names}")


layout_checked()
