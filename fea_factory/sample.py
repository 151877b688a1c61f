"""Parametric grid sampler (thesis "Data Generation"): jittered and regular lattices with actuator patterns.

A design is drawn in two stages from numpy Generators seeded by (seed, index):
  plan (stream 0):          family ~ grid.family, shape ~ grid.regular.shape, actuator group ~ grid.actuators.<family>
  geometry (stream 1 + a):  spacings, shape parameters, vertex jitter, fixed joint and beam kinds of attempt a.
Only the geometry is redrawn when a draw fails `validate`, so the plan keeps its conf ratios exactly.

Vertex jitter V(theta, r) is uniform over the disk of radius r_max: theta ~ U[0, 2 pi), r = r_max sqrt(u),
u ~ U[0, 1). (Uniform r would crowd the vectors near the origin and bias the data towards regular grids.)

CLI:  .venv/bin/python -m fea_factory.sample n=5 out=DIR [seed=0] [start=0] [grid=g7x3] [grid.jitter=0.1]
Units: mm and degrees.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from fea_factory.checks import integer_in
from fea_factory.design import BEAM_KINDS, Design, DesignError, DesignLimits, lattice_design, validate

SAMPLER_FORMAT = "morphsim.sampler/1"
FAMILIES = ("random", "regular")
SHAPES = ("rectangle", "trapezoid", "parallelogram")
GROUPS = ("all_up", "all_down", "random", "clustered", "symmetric")
FIXED_RULES = ("center", "corner", "random")
CLUSTER_REST = ("passive", "opposite")
# lattice lines a symmetric actuator pattern may mirror across: i -> 2 i_fixed - i ("i") or j -> 2 j_fixed - j ("j");
# a trapezoid is a mirror image of itself only across its centre column
MIRROR_AXES = {"jittered": ("i", "j"), "rectangle": ("i", "j"), "trapezoid": ("i",), "parallelogram": ("i", "j")}


class SamplerConfigError(ValueError):
    """A grid sampler conf value out of range; the message names the conf field and the allowed range."""


# ------------------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class GridSpec:
    """The validated contents of conf/grid/*.yaml (see conf/grid/default.yaml for the meaning of each field)."""

    nx: int
    ny: int
    spacing_x: tuple[float, float]
    spacing_y: tuple[float, float]
    jitter: float
    family: dict[str, float]
    shape: dict[str, float]
    taper: tuple[float, float]
    shear_deg: tuple[float, float]
    actuators: dict[str, dict[str, float]]
    beam_kind: dict[str, float]
    cluster_fraction: tuple[float, float]
    cluster_rest: dict[str, float]
    fixed_joint: str
    max_attempts: int

    @classmethod
    def from_mapping(cls, m: Mapping) -> "GridSpec":
        m = _plain(m)
        _known_keys(m, "grid", ("nx", "ny", "spacing_x", "spacing_y", "jitter", "family", "regular", "actuators",
                                "beam_kind", "clustered", "fixed_joint", "max_attempts"))
        regular, clustered = m.get("regular", {}), m.get("clustered", {})
        _known_keys(regular, "grid.regular", ("shape", "taper", "shear_deg"))
        _known_keys(clustered, "grid.clustered", ("fraction", "rest"))
        family = _ratios(m, "family", FAMILIES, "grid")
        actuators = m.get("actuators")
        if not isinstance(actuators, Mapping):
            raise SamplerConfigError("grid.actuators must map each family to its actuator-group mix ratios")
        _known_keys(actuators, "grid.actuators", FAMILIES)
        return cls(
            nx=_count(m, "nx", "grid"),
            ny=_count(m, "ny", "grid"),
            spacing_x=_range(m, "spacing_x", "grid", lo=0.0, lo_open=True),
            spacing_y=_range(m, "spacing_y", "grid", lo=0.0, lo_open=True),
            jitter=_number(m, "jitter", "grid", 0.0, 0.5, hi_open=True),
            family=family,
            shape=_ratios(regular, "shape", SHAPES, "grid.regular"),
            taper=_range(regular, "taper", "grid.regular", lo=0.0, hi=1.0, lo_open=True),
            shear_deg=_range(regular, "shear_deg", "grid.regular", lo=0.0, hi=45.0, hi_open=True),
            actuators={f: _ratios(actuators, f, GROUPS, "grid.actuators") for f in FAMILIES if family[f] > 0},
            beam_kind=_ratios(m, "beam_kind", BEAM_KINDS, "grid"),
            cluster_fraction=_range(clustered, "fraction", "grid.clustered", lo=0.0, hi=1.0, lo_open=True),
            cluster_rest=_ratios(clustered, "rest", CLUSTER_REST, "grid.clustered"),
            fixed_joint=_choice(m, "fixed_joint", FIXED_RULES, "grid"),
            max_attempts=_count(m, "max_attempts", "grid", lo=1),
        )

    def to_conf(self) -> dict:
        """The conf/grid mapping of this spec (normalised), for design.meta: from_mapping(to_conf()) == self."""
        return {"nx": self.nx, "ny": self.ny, "spacing_x": list(self.spacing_x), "spacing_y": list(self.spacing_y),
                "jitter": self.jitter, "family": dict(self.family),
                "regular": {"shape": dict(self.shape), "taper": list(self.taper), "shear_deg": list(self.shear_deg)},
                "actuators": {f: dict(r) for f, r in self.actuators.items()}, "beam_kind": dict(self.beam_kind),
                "clustered": {"fraction": list(self.cluster_fraction), "rest": dict(self.cluster_rest)},
                "fixed_joint": self.fixed_joint, "max_attempts": self.max_attempts}


def _plain(m: Any) -> Any:
    return OmegaConf.to_container(m, resolve=True) if isinstance(m, DictConfig) else m


def _known_keys(m: Any, where: str, allowed: tuple[str, ...]) -> None:
    if not isinstance(m, Mapping):
        raise SamplerConfigError(f"{where} must be a mapping with keys {list(allowed)}; got {m!r}")
    unknown = sorted(set(m) - set(allowed))
    if unknown:
        raise SamplerConfigError(f"{where}: unknown field(s) {unknown}; allowed fields are {list(allowed)}")


def _get(m: Mapping, key: str, where: str) -> Any:
    if key not in m or m[key] is None:
        raise SamplerConfigError(f"{where}.{key} is missing")
    return m[key]


def _count(m: Mapping, key: str, where: str, lo: int = 2) -> int:
    return integer_in(_get(m, key, where), f"{where}.{key}", SamplerConfigError, lo)


def _number(m: Mapping, key: str, where: str, lo: float, hi: float, hi_open: bool = False) -> float:
    v = _get(m, key, where)
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and lo <= v and (v < hi if hi_open else v <= hi)
    if not ok:
        raise SamplerConfigError(f"{where}.{key} = {v!r}: must lie in [{lo}, {hi}{')' if hi_open else ']'}")
    return float(v)


def _range(m: Mapping, key: str, where: str, lo: float = -np.inf, hi: float = np.inf,
           lo_open: bool = False, hi_open: bool = False) -> tuple[float, float]:
    v = _get(m, key, where)
    allowed = f"{'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    msg = f"{where}.{key} = {v!r}: must be [low, high] with low <= high, both in {allowed}"
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise SamplerConfigError(msg)
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise SamplerConfigError(msg)
    a, b = float(v[0]), float(v[1])
    inside = all((x > lo if lo_open else x >= lo) and (x < hi if hi_open else x <= hi) for x in (a, b))
    if not (inside and a <= b):
        raise SamplerConfigError(msg)
    return a, b


def _ratios(m: Mapping, key: str, names: tuple[str, ...], where: str) -> dict[str, float]:
    v = _get(m, key, where)
    if not isinstance(v, Mapping):
        raise SamplerConfigError(f"{where}.{key} must map names in {list(names)} to mix ratios; got {v!r}")
    _known_keys(v, f"{where}.{key}", names)
    bad = {k: r for k, r in v.items() if isinstance(r, bool) or not isinstance(r, (int, float)) or r < 0}
    if bad:
        raise SamplerConfigError(f"{where}.{key}: ratios {bad} must be numbers >= 0")
    if sum(v.values()) <= 0:
        raise SamplerConfigError(f"{where}.{key}: ratios {dict(v)} must sum to > 0")
    return {k: float(v.get(k, 0.0)) for k in names}


def _choice(m: Mapping, key: str, names: tuple[str, ...], where: str) -> str:
    v = _get(m, key, where)
    if v not in names:
        raise SamplerConfigError(f"{where}.{key} = {v!r}: must be one of {list(names)}")
    return str(v)


# ------------------------------------------------------------------------------------------------ random draws
def rng_for(seed: int, index: int, stream: int) -> np.random.Generator:
    """The Generator of design `index`: stream 0 draws the plan, stream 1 + a the geometry of attempt a."""
    return np.random.default_rng(np.random.SeedSequence([seed, index, stream]))


def pick(rng: np.random.Generator, ratios: Mapping[str, float]) -> str:
    """One name drawn with probability proportional to its mix ratio."""
    names = list(ratios)
    p = np.array([ratios[k] for k in names], dtype=float)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def disk_jitter(rng: np.random.Generator, r_max: float, shape: tuple[int, ...]) -> np.ndarray:
    """Vectors V(theta, r) uniform over the disk of radius r_max: theta ~ U[0, 2 pi), r = r_max sqrt(u)."""
    theta = rng.uniform(0.0, 2.0 * np.pi, shape)
    r = r_max * np.sqrt(rng.uniform(0.0, 1.0, shape))  # P(r < s) = (s / r_max)^2: the area fraction
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=-1)  # [*shape, 2]


# ------------------------------------------------------------------------------------------------ geometry
def lattice(nx: int, ny: int, sx: float, sy: float) -> np.ndarray:
    """Rectangular lattice centred on the origin."""
    i = (np.arange(nx) - 0.5 * (nx - 1)) * sx
    j = (np.arange(ny) - 0.5 * (ny - 1)) * sy
    return np.stack(np.meshgrid(i, j, indexing="ij"), axis=-1)  # [nx, ny, 2]


def trapezoid(xy: np.ndarray, taper: float) -> np.ndarray:
    """Rows shrink linearly in x from width w (j = 0) to taper * w (j = ny - 1), about the centre line x = 0."""
    ny = xy.shape[1]
    scale = 1.0 + (taper - 1.0) * np.arange(ny) / (ny - 1)  # [ny]
    out = xy.copy()
    out[..., 0] *= scale[None, :]
    return out


def parallelogram(xy: np.ndarray, shear_deg: float) -> np.ndarray:
    """The j-direction beams lean by shear_deg from the y axis: x += y tan(shear)."""
    out = xy.copy()
    out[..., 0] += xy[..., 1] * np.tan(np.radians(shear_deg))
    return out


def draw_geometry(rng: np.random.Generator, spec: GridSpec, family: str, shape: str) -> tuple[np.ndarray, dict]:
    """Joint positions [nx, ny, 2] of one draw and the parameters drawn (for design.meta)."""
    sx, sy = uniform(rng, spec.spacing_x), uniform(rng, spec.spacing_y)
    xy = lattice(spec.nx, spec.ny, sx, sy)
    params: dict[str, Any] = {"spacing": [sx, sy]}
    if family == "random":
        r_max = spec.jitter * min(sx, sy)
        xy = xy + disk_jitter(rng, r_max, (spec.nx, spec.ny))
        params["r_max"] = r_max
    elif shape == "trapezoid":
        params["taper"] = uniform(rng, spec.taper)
        xy = trapezoid(xy, params["taper"])
    elif shape == "parallelogram":
        params["shear_deg"] = uniform(rng, spec.shear_deg) * float(rng.choice([-1.0, 1.0]))
        xy = parallelogram(xy, params["shear_deg"])
    return xy, params


def fixed_ij(rng: np.random.Generator, xy: np.ndarray, rule: str) -> tuple[int, int]:
    """The glued joint: nearest the lattice centre (ties: nearest the centroid of the joints), a corner, or any."""
    nx, ny = xy.shape[:2]
    if rule == "corner":
        return int(rng.choice([0, nx - 1])), int(rng.choice([0, ny - 1]))
    if rule == "random":
        return int(rng.integers(nx)), int(rng.integers(ny))
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    lattice_dist = np.hypot(i - 0.5 * (nx - 1), j - 0.5 * (ny - 1))
    xy_dist = np.linalg.norm(xy - xy.reshape(-1, 2).mean(axis=0), axis=-1)
    n = np.lexsort((xy_dist.ravel(), np.round(lattice_dist.ravel(), 9)))[0]
    return int(n // ny), int(n % ny)


# ------------------------------------------------------------------------------------------------ actuators
def beam_ij(nx: int, ny: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Lattice ends of each beam, in lattice_design's beam order (i-direction beams row by row, then j)."""
    beams = [((i, j), (i + 1, j)) for j in range(ny) for i in range(nx - 1)]
    return beams + [((i, j), (i, j + 1)) for j in range(ny - 1) for i in range(nx)]


def mirror_orbits(nx: int, ny: int, axis: str, about: tuple[int, int]) -> list[list[int]]:
    """Beams grouped with their mirror images across the lattice line i = about_i (axis "i") or j = about_j."""
    ends = beam_ij(nx, ny)
    index = {frozenset(e): b for b, e in enumerate(ends)}

    def mirror(p: tuple[int, int]) -> tuple[int, int]:
        return (2 * about[0] - p[0], p[1]) if axis == "i" else (p[0], 2 * about[1] - p[1])

    orbits, seen = [], set()
    for b, (p, q) in enumerate(ends):
        if b in seen:
            continue
        orbit = sorted({b, index.get(frozenset((mirror(p), mirror(q))), b)})
        seen.update(orbit)
        orbits.append(orbit)
    return orbits


def contiguous_region(rng: np.random.Generator, nx: int, ny: int, size: int) -> set[int]:
    """`size` beams grown from a random beam through beams that share a joint."""
    ends = beam_ij(nx, ny)
    at_joint: dict[tuple[int, int], list[int]] = {}
    for b, (p, q) in enumerate(ends):
        at_joint.setdefault(p, []).append(b)
        at_joint.setdefault(q, []).append(b)
    region = {int(rng.integers(len(ends)))}
    while len(region) < size:
        frontier = sorted({c for b in region for p in ends[b] for c in at_joint[p]} - region)
        region.add(frontier[int(rng.integers(len(frontier)))])
    return region


def draw_kinds(rng: np.random.Generator, spec: GridSpec, group: str, fixed: tuple[int, int],
               axes: tuple[str, ...] = ("i", "j")) -> tuple[list[str], dict]:
    """Beam kinds of an actuator group (in lattice_design's beam order) and the parameters drawn.

    symmetric: mirror-image beams across a lattice line through the fixed joint (one of `axes`) share a kind;
    beams whose image falls outside the grid are drawn on their own.
    """
    n_beams = spec.nx * (spec.ny - 1) + spec.ny * (spec.nx - 1)
    if group in ("all_up", "all_down"):
        return [group[4:]] * n_beams, {}
    if group == "random":
        return [pick(rng, spec.beam_kind) for _ in range(n_beams)], {}
    if group == "symmetric":
        axis = str(rng.choice(list(axes)))
        kinds = [""] * n_beams
        for orbit in mirror_orbits(spec.nx, spec.ny, axis, fixed):
            k = pick(rng, spec.beam_kind)
            for b in orbit:
                kinds[b] = k
        return kinds, {"mirror_axis": axis}
    # clustered: one actuator kind on a contiguous region, the rest passive or the opposite kind
    kind = str(rng.choice(["up", "down"]))
    fraction = uniform(rng, spec.cluster_fraction)
    size = int(np.clip(round(fraction * n_beams), 1, n_beams))
    rest_rule = pick(rng, spec.cluster_rest)
    rest = "passive" if rest_rule == "passive" else {"up": "down", "down": "up"}[kind]
    region = contiguous_region(rng, spec.nx, spec.ny, size)
    kinds = [kind if b in region else rest for b in range(n_beams)]
    return kinds, {"cluster_kind": kind, "cluster_fraction": fraction, "cluster_rest": rest_rule}


# ------------------------------------------------------------------------------------------------ designs
def _hint(family: str, shape: str, err: DesignError) -> str:
    """The conf field most likely to fix a draw that keeps failing validation."""
    msg = str(err)
    if "printable area" in msg:
        return "grid.spacing_x / grid.spacing_y (upper bounds) or blocks.limits.printable_width / printable_depth"
    if family == "random":
        if "clear length" in msg:
            return "grid.spacing_x / grid.spacing_y (lower bounds) or grid.jitter"
        return "grid.jitter"
    if shape == "trapezoid":
        return "grid.regular.taper" if "clear length" not in msg else "grid.regular.taper or grid.spacing_x"
    if shape == "parallelogram" and "clear length" not in msg:
        return "grid.regular.shear_deg"
    return "grid.spacing_x / grid.spacing_y (lower bounds) or blocks.beam_width"


def sample_design(spec: GridSpec, blocks: Mapping, seed: int, index: int) -> Design:
    """Design `index` of the stream `seed`; redraws the geometry (bounded) until it passes validate()."""
    limits = DesignLimits.from_mapping(_get(blocks, "limits", "blocks"))
    beam_width, thickness = float(_get(blocks, "beam_width", "blocks")), float(_get(blocks, "thickness", "blocks"))
    plan = rng_for(seed, index, 0)
    family = pick(plan, spec.family)
    shape = pick(plan, spec.shape) if family == "regular" else "jittered"
    group = pick(plan, spec.actuators[family])
    err: DesignError | None = None
    for attempt in range(spec.max_attempts):
        rng = rng_for(seed, index, 1 + attempt)
        xy, geometry = draw_geometry(rng, spec, family, shape)
        fixed = fixed_ij(rng, xy, spec.fixed_joint)
        kinds, actuation = draw_kinds(rng, spec, group, fixed, MIRROR_AXES[shape])
        meta = {"sampler": SAMPLER_FORMAT, "seed": seed, "index": index, "attempt": attempt,
                "family": family, "shape": shape, "actuators": group, "fixed_rule": spec.fixed_joint,
                "fixed_ij": list(fixed), **geometry, **actuation, "grid": spec.to_conf()}
        design = lattice_design(xy, kinds, fixed, beam_width, thickness, meta)
        try:
            validate(design, limits)
            return design
        except DesignError as e:
            err = e
    raise SamplerConfigError(
        f"design {index} (seed {seed}, {family}/{shape}): no valid draw in grid.max_attempts = {spec.max_attempts} "
        f"attempts; last error: {err}. Change {_hint(family, shape, err)}")


def iter_designs(cfg_grid: Mapping, blocks_cfg: Mapping, n: int, seed: int, start: int = 0) -> Iterator[Design]:
    """Designs start, ..., start + n - 1 of the stream `seed`, one at a time."""
    spec = GridSpec.from_mapping(cfg_grid)
    blocks_cfg = _plain(blocks_cfg)
    root = {"n": n, "seed": seed, "start": start}
    for key, lo in (("n", 0), ("seed", 0), ("start", 0)):
        _count(root, key, "sample", lo=lo)
    for index in range(start, start + n):
        yield sample_design(spec, blocks_cfg, seed, index)


def sample_designs(cfg_grid: Mapping, blocks_cfg: Mapping, n: int, seed: int, start: int = 0) -> list[Design]:
    """A batch of n sampled designs (the same designs for the same conf, seed and start)."""
    return list(iter_designs(cfg_grid, blocks_cfg, n, seed, start))


def summary(name: str, d: Design) -> str:
    """One line per design for the CLI."""
    m = d.meta
    counts = " ".join(f"{k}={d.kinds.count(k)}" for k in BEAM_KINDS)
    nx, ny = m["grid"]["nx"], m["grid"]["ny"]
    return (f"{name}  {nx}x{ny} {m['family']}/{m['shape']:<13} actuators={m['actuators']:<9} {counts}  "
            f"fixed={d.fixed_joint} size={d.size:.1f}mm attempt={m['attempt']}")


# ------------------------------------------------------------------------------------------------ CLI
@hydra.main(version_base="1.3", config_path="../conf", config_name="sample")
def main(cfg: DictConfig) -> None:
    """Write cfg.out/design_<index>.json for index = start, ..., start + n - 1 and print one line each."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    for d in iter_designs(cfg.grid, cfg.blocks, cfg.n, cfg.seed, cfg.start):
        name = f"design_{d.meta['index']:05d}.json"
        d.save(out / name)
        print(summary(name, d), flush=True)


if __name__ == "__main__":
    main()
