"""Grid sampler: determinism, the disk-uniform jitter, conf mix ratios, validity, the CLI and the Hydra configs."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from scipy import stats

from fea_factory.design import Design, DesignLimits, validate
from fea_factory.sample import (GridSpec, SamplerConfigError, beam_ij, disk_jitter, lattice, mirror_orbits,
                                sample_design, sample_designs)

CONF = Path(__file__).resolve().parents[1] / "conf"
GRIDS = sorted(p.stem for p in (CONF / "grid").glob("*.yaml"))
N_BATCH = 300


def conf(*overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("sample", overrides=["out=unused", *overrides])


@pytest.fixture(scope="module")
def cfg():
    return conf()


@pytest.fixture(scope="module")
def batch(cfg):
    return sample_designs(cfg.grid, cfg.blocks, N_BATCH, seed=0)


def grid_dict(cfg, **changes):
    g = OmegaConf.to_container(cfg.grid)
    for key, value in changes.items():
        *path, last = key.split(".")
        node = g
        for p in path:
            node = node[p]
        node[last] = value
    return g


# ------------------------------------------------------------------------------------------ determinism
def test_same_seed_same_designs(cfg, batch):
    again = sample_designs(cfg.grid, cfg.blocks, 20, seed=0)
    assert [d.to_json() for d in again] == [d.to_json() for d in batch[:20]]
    other = sample_designs(cfg.grid, cfg.blocks, 20, seed=1)
    assert sum(a.to_json() == b.to_json() for a, b in zip(other, batch)) == 0
    shard = sample_designs(cfg.grid, cfg.blocks, 5, seed=0, start=7)  # shards reproduce the same stream
    assert [d.to_json() for d in shard] == [d.to_json() for d in batch[7:12]]


def test_design_reproducible_from_its_meta(cfg, batch):
    d = batch[11]
    spec = GridSpec.from_mapping(d.meta["grid"])
    assert spec == GridSpec.from_mapping(cfg.grid)
    again = sample_design(spec, OmegaConf.to_container(cfg.blocks), d.meta["seed"], d.meta["index"])
    assert again.to_json() == d.to_json()
    assert Design.from_json(d.to_json()).meta == d.meta  # meta survives JSON


# ------------------------------------------------------------------------------------------ jitter V(theta, r)
def test_jitter_is_uniform_over_the_disk():
    rng = np.random.default_rng(0)
    v = disk_jitter(rng, 7.0, (20000,))  # [20000, 2]
    r2 = (v ** 2).sum(axis=1) / 7.0 ** 2  # uniform over the disk <=> r^2 / r_max^2 ~ U(0, 1)
    assert r2.max() <= 1.0
    assert stats.kstest(r2, "uniform").pvalue > 0.01
    theta = np.arctan2(v[:, 1], v[:, 0]) % (2 * np.pi)
    assert stats.kstest(theta / (2 * np.pi), "uniform").pvalue > 0.01


def test_uniform_radius_fails_the_same_test():
    """Negative control: r = r_max u crowds the vectors near the origin (thesis: biased to regular grids)."""
    rng = np.random.default_rng(0)
    r2_biased = rng.uniform(0.0, 1.0, 20000) ** 2
    assert stats.kstest(r2_biased, "uniform").pvalue < 1e-6


def test_sampled_jitter_is_uniform_over_the_disk(batch):
    r2 = []
    for d in batch:
        if d.meta["family"] == "random":
            base = lattice(3, 3, *d.meta["spacing"])  # [3, 3, 2]; joints are numbered n = j * nx + i
            shift = d.joint_xy - base.transpose(1, 0, 2).reshape(-1, 2)
            r2.extend((shift ** 2).sum(axis=1) / d.meta["r_max"] ** 2)
    r2 = np.array(r2)
    assert len(r2) > 1000 and r2.max() <= 1.0 + 1e-12
    assert stats.kstest(r2, "uniform").pvalue > 0.01


# ------------------------------------------------------------------------------------------ mix ratios
def close_to(count, n, p):
    """count within 4 standard deviations of a Binomial(n, p)."""
    return abs(count - n * p) <= 4 * np.sqrt(n * p * (1 - p)) + 1


def share(ratios, key):
    return ratios[key] / sum(ratios.values())


def test_families_shapes_and_groups_at_their_conf_ratios(cfg, batch):
    g = OmegaConf.to_container(cfg.grid)
    fam = [d.meta["family"] for d in batch]
    assert close_to(fam.count("regular"), N_BATCH, share(g["family"], "regular"))
    regular = [d for d in batch if d.meta["family"] == "regular"]
    for shape in g["regular"]["shape"]:
        assert close_to(sum(d.meta["shape"] == shape for d in regular), len(regular),
                        share(g["regular"]["shape"], shape)), shape
    for family, ratios in g["actuators"].items():
        members = [d for d in batch if d.meta["family"] == family]
        for group in ratios:
            count = sum(d.meta["actuators"] == group for d in members)
            assert count > 0 and close_to(count, len(members), share(ratios, group)), (family, group)
    kinds = [k for d in batch if d.meta["actuators"] == "random" for k in d.kinds]
    for kind, ratio in g["beam_kind"].items():
        assert close_to(kinds.count(kind), len(kinds), share(g["beam_kind"], kind)), kind


# ------------------------------------------------------------------------------------------ validity
def test_batch_of_100_all_validate(cfg, batch):
    limits = DesignLimits.from_mapping(cfg.blocks.limits)
    for d in batch[:100]:
        validate(d, limits)
        assert (d.beam_width, d.thickness) == (cfg.blocks.beam_width, cfg.blocks.thickness)
        assert d.n_joints == 9 and d.n_beams == 12 and d.fixed_joint == 4  # fixed_joint: center
        assert 90.0 < d.size < 300.0


def test_actuator_groups_have_their_patterns(batch):
    for d in batch:
        group, kinds = d.meta["actuators"], d.kinds
        if group in ("all_up", "all_down"):
            assert set(kinds) == {group[4:]}
        elif group == "symmetric":
            assert mirrored_pairs_agree(d) >= 4
            if d.meta["shape"] == "trapezoid":
                assert d.meta["mirror_axis"] == "i"  # the trapezoid's own mirror line
        elif group == "clustered":
            region = [b for b, k in enumerate(kinds) if k == d.meta["cluster_kind"]]
            assert is_contiguous(region, beam_ij(3, 3))
            rest = {k for b, k in enumerate(kinds) if b not in region}
            assert len(rest) <= 1 and d.meta["cluster_kind"] not in rest


def mirrored_pairs_agree(d):
    """Count the beams whose mirror image across the lattice line through the fixed joint exists; assert that
    both have the same kind."""
    fi, fj = d.meta["fixed_ij"]
    axis = d.meta["mirror_axis"]
    kind = {frozenset(map(tuple, d.joint_ij[[a, c]].tolist())): k for (a, c), k in zip(d.beams, d.kinds)}
    mirror = (lambda i, j: (2 * fi - i, j)) if axis == "i" else (lambda i, j: (i, 2 * fj - j))
    found = 0
    for ends, k in kind.items():
        image = frozenset(mirror(*p) for p in ends)
        if image in kind:
            assert kind[image] == k, (d.meta["index"], sorted(ends), sorted(image))
            found += 1
    return found


def test_beam_order_matches_lattice_design(cfg):
    d = sample_designs(grid_dict(cfg, nx=4, ny=3), cfg.blocks, 1, seed=0)[0]
    assert [tuple(map(tuple, d.joint_ij[[a, c]].tolist())) for a, c in d.beams] == beam_ij(4, 3)
    axis_i = mirror_orbits(3, 3, "i", (1, 1))  # 3 x 3 about the centre column: 2 self-images, 5 pairs
    assert sorted(len(o) for o in axis_i) == [1, 1, 2, 2, 2, 2, 2]


def is_contiguous(region, ends):
    """Beams connected through shared joints."""
    todo, seen = [region[0]], {region[0]}
    while todo:
        b = todo.pop()
        for c in region:
            if c not in seen and set(ends[b]) & set(ends[c]):
                seen.add(c)
                todo.append(c)
    return seen == set(region)


@pytest.mark.parametrize("rule", ["corner", "random"])
def test_fixed_joint_rules(cfg, rule):
    designs = sample_designs(grid_dict(cfg, fixed_joint=rule), cfg.blocks, 30, seed=3)
    fixed = {tuple(d.meta["fixed_ij"]) for d in designs}
    if rule == "corner":
        assert fixed <= {(0, 0), (2, 0), (0, 2), (2, 2)} and len(fixed) > 1
    else:
        assert len(fixed) > 4
    for d in designs:
        i, j = d.meta["fixed_ij"]
        assert d.fixed_joint == j * 3 + i


def test_nx4_ny2(cfg):
    c = conf("grid.nx=4", "grid.ny=2")
    designs = sample_designs(c.grid, c.blocks, 20, seed=0)
    limits = DesignLimits.from_mapping(c.blocks.limits)
    for d in designs:
        validate(d, limits)
        assert d.n_joints == 8 and d.n_beams == 10
        assert d.meta["fixed_ij"][0] in (1, 2)  # nearest the lattice centre (1.5, 0.5)


# ------------------------------------------------------------------------------------------ bad conf
@pytest.mark.parametrize("change, message", [
    ({"nx": 1}, r"grid\.nx = 1: must be an integer >= 2"),
    ({"ny": 2.5}, r"grid\.ny = 2\.5: must be an integer >= 2"),
    ({"spacing_x": [-10.0, 50.0]}, r"grid\.spacing_x = \[-10\.0, 50\.0\]: must be \[low, high\]"),
    ({"spacing_y": [90.0, 60.0]}, r"grid\.spacing_y .* low <= high"),
    ({"jitter": 0.5}, r"grid\.jitter = 0\.5: must lie in \[0\.0, 0\.5\)"),
    ({"jitter": -0.1}, r"grid\.jitter"),
    ({"family": {"random": 0, "regular": 0}}, r"grid\.family: ratios .* must sum to > 0"),
    ({"family": {"random": 1, "fancy": 1}}, r"grid\.family: unknown field\(s\) \['fancy'\]"),
    ({"actuators.random": {"all_up": -1, "random": 1}}, r"grid\.actuators\.random: ratios .* >= 0"),
    ({"actuators.regular": {"spiral": 1}}, r"grid\.actuators\.regular: unknown field"),
    ({"beam_kind": {"up": 0, "down": 0, "passive": 0}}, r"grid\.beam_kind: ratios"),
    ({"regular.taper": [0.5, 1.5]}, r"grid\.regular\.taper .* \(0\.0, 1\.0\]"),
    ({"regular.shear_deg": [10, 50]}, r"grid\.regular\.shear_deg .* \[0\.0, 45\.0\)"),
    ({"clustered.fraction": [0.0, 0.5]}, r"grid\.clustered\.fraction"),
    ({"fixed_joint": "edge"}, r"grid\.fixed_joint = 'edge': must be one of \['center', 'corner', 'random'\]"),
    ({"max_attempts": 0}, r"grid\.max_attempts = 0: must be an integer >= 1"),
    ({"jiter": 0.1}, r"grid: unknown field\(s\) \['jiter'\]"),
])
def test_bad_conf_names_the_field(cfg, change, message):
    with pytest.raises(SamplerConfigError, match=message):
        sample_designs(grid_dict(cfg, **change), cfg.blocks, 1, seed=0)


def test_bad_run_arguments(cfg):
    with pytest.raises(SamplerConfigError, match=r"sample\.n = -1"):
        sample_designs(cfg.grid, cfg.blocks, -1, seed=0)
    with pytest.raises(SamplerConfigError, match=r"sample\.seed = -5"):
        sample_designs(cfg.grid, cfg.blocks, 1, seed=-5)


def test_unsatisfiable_conf_names_the_field(cfg):
    c = conf("grid=g7x3", "grid.spacing_x=[60,70]", "grid.max_attempts=3")  # 6 x 60 mm > 300 mm print bed
    with pytest.raises(SamplerConfigError, match=r"no valid draw in grid\.max_attempts = 3 .* printable area.*"
                                                 r"Change grid\.spacing_x"):
        sample_designs(c.grid, c.blocks, 1, seed=0)


# ------------------------------------------------------------------------------------------ configs and CLI
def test_root_config_composes():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        c = compose("sample", return_hydra_config=True)
    assert OmegaConf.is_missing(c, "out") and c.n >= 1 and c.seed == 0 and c.start == 0
    assert c.hydra.output_subdir is None and c.hydra.run.dir == "."
    assert c.grid.nx == 3 and c.grid.ny == 3 and c.blocks.beam_width == 7.2


@pytest.mark.parametrize("name", GRIDS)
def test_every_grid_option_composes_and_samples(name):
    c = conf(f"grid={name}")
    limits = DesignLimits.from_mapping(c.blocks.limits)
    for d in sample_designs(c.grid, c.blocks, 4, seed=0):
        validate(d, limits)
        assert d.n_joints == c.grid.nx * c.grid.ny


def test_the_large_grid_is_the_default_at_steps_of_75_to_100_mm(cfg):
    """conf/grid/large.yaml (make large-data): only the lattice steps differ from the default sampler, and every
    design draws them from the upper half of the default's range."""
    large = conf("grid=large")
    changed = {k for k in cfg.grid if large.grid[k] != cfg.grid[k]}
    assert changed == {"spacing_x", "spacing_y"}
    designs = sample_designs(large.grid, large.blocks, 40, seed=0)
    spacings = np.array([d.meta["spacing"] for d in designs])
    assert spacings.min() >= 75.0 and spacings.max() <= 100.0


def test_cli_writes_loadable_json(tmp_path):
    out = tmp_path / "designs"
    run = subprocess.run([sys.executable, "-m", "fea_factory.sample", "n=3", f"out={out}", "seed=4"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    files = sorted(out.glob("*.json"))
    assert [f.name for f in files] == ["design_00000.json", "design_00001.json", "design_00002.json"]
    lines = run.stdout.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith(f.name) for line, f in zip(lines, files))
    for k, f in enumerate(files):
        d = Design.load(f)
        validate(d)
        assert (d.meta["seed"], d.meta["index"]) == (4, k)
        assert json.loads(f.read_text())["format"] == "morphsim.design/1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["designs"]  # no outputs/, .hydra/ or log files
