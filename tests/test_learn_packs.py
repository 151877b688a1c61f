"""learn.packs: a feature pack reads back exactly what learn.features.extract gives, and a data directory lists and
reads the episodes its packs hold where their files are gone (a fresh machine), the files winning where present."""
from dataclasses import fields
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from data_schema.episode import read_episode, write_episode
from data_schema.testing import synthetic_episode
from learn.dataset import design_paths, episode_paths, has_episode, load_features
from learn.features import EpisodeFeatures, extract
from learn.packs import PackError, pack_dir, pack_manifest, pack_names, read_pack, write_pack


def assert_same_features(a: EpisodeFeatures, b: EpisodeFeatures) -> None:
    """Every field equal: arrays bit for bit and of the same dtype, the incidence's arrays, NaN as NaN."""
    for f in fields(EpisodeFeatures):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "incidence":
            for k in ("senders", "receivers", "edge_beam"):
                assert np.array_equal(getattr(x, k), getattr(y, k)), k
            assert (x.n_joints, x.n_beams) == (y.n_joints, y.n_beams)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f.name
        elif isinstance(x, float) and np.isnan(x):
            assert np.isnan(y), f.name
        else:
            assert x == y, f.name


@pytest.fixture
def episodes(tmp_path):
    """Three episodes of different sizes (3x3, 2x3, 2x2 joints; 11, 11, 3 frames)."""
    d = tmp_path / "data"
    for s, (nx, ny, frames) in enumerate([(3, 3, 11), (2, 3, 11), (2, 2, 3)]):
        write_episode(d / f"episode_{s:05d}.h5", synthetic_episode(nx, ny, 5, 3, 3, frames=frames, seed=s))
    return d


def test_a_pack_reads_back_exactly_what_extract_gives(episodes, tmp_path):
    paths = sorted(episodes.glob("*.h5"))
    features = [extract(read_episode(p), name=p.name) for p in paths]
    records = [{"episode": i, "status": "ok"} for i in range(3)] + [{"episode": 3, "status": "contact"}]
    pack = write_pack(tmp_path / "p.h5", features, records)
    assert pack_names(pack) == [p.name for p in paths]
    assert pack_manifest(pack) == records
    back = read_pack(pack)
    for f in features:
        assert_same_features(f, back[f.name])
    back[features[0].name].joint_state[:] = 0  # every read gives fresh arrays: a caller's change stays its own
    assert_same_features(features[0], read_pack(pack)[features[0].name])


def test_a_data_directory_reads_its_packs_where_the_files_are_gone_and_its_files_where_present(episodes, tmp_path):
    paths = sorted(episodes.glob("*.h5"))
    extracted = {p.name: extract(read_episode(p), name=p.name) for p in paths}
    write_pack(pack_dir(episodes) / "part_0.h5", list(extracted.values()))
    gone = paths[1]
    gone.unlink()
    assert [p.name for p in episode_paths(episodes)] == [p.name for p in paths]  # listed although its file is gone
    assert has_episode(episodes, gone.name) and not has_episode(episodes, "episode_00009.h5")
    for f in load_features(episode_paths(episodes)):
        assert_same_features(extracted[f.name], f)
    # an episode file wins over a pack holding its name: the episode is the source of truth
    other = extract(synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=7), name=paths[0].name)
    write_pack(pack_dir(episodes) / "part_1.h5", [other])
    assert_same_features(extracted[paths[0].name], load_features([paths[0]])[0])
    # design_paths finds a packed episode in a train_extra_dir
    extra = tmp_path / "extra"
    write_pack(pack_dir(extra) / "part_0.h5", [extract(synthetic_episode(2, 2, 5, 3, 3, seed=9), name="x.h5")])
    assert design_paths(["x.h5", gone.name], episodes, {"train_extra_dirs": [str(extra)]}) == [extra / "x.h5", gone]


def test_an_episode_in_neither_a_file_nor_a_pack_is_named(episodes):
    write_pack(pack_dir(episodes) / "part_0.h5", load_features(sorted(episodes.glob("*.h5"))[:1]))
    with pytest.raises(FileNotFoundError, match="episode_00042.h5.*part_0.h5"):
        load_features([episodes / "episode_00042.h5"])


def test_a_pack_made_with_another_feature_layout_is_refused(episodes, tmp_path):
    pack = write_pack(tmp_path / "p.h5", load_features(sorted(episodes.glob("*.h5"))))
    with h5py.File(pack, "a") as h5:
        h5.attrs["layout"] = h5.attrs["layout"].replace('"extract_version": 1', '"extract_version": 0')
    with pytest.raises(PackError, match="another feature layout.*extract_version"):
        read_pack(pack)


@pytest.mark.parametrize("names", [["a.h5", "a.h5"], [""]])
def test_a_pack_needs_distinct_names(episodes, tmp_path, names):
    f = load_features(sorted(episodes.glob("*.h5"))[:1])[0]
    from dataclasses import replace
    with pytest.raises(PackError, match="distinct, non-empty names"):
        write_pack(tmp_path / "p.h5", [replace(f, name=n) for n in names])
    assert not (tmp_path / "p.h5").exists() and not list(tmp_path.glob("p.h5.*"))


def test_training_on_the_packs_alone_is_training_on_the_episodes(tmp_path):
    """learn.train on a directory whose episode files are gone (its packs only) trains on the same features: the
    same split and the same losses, epoch by epoch, as on the episode files."""
    from tests.test_learn_train import cfg_for, tiny
    from learn.train import train

    files, packs = tmp_path / "files", tmp_path / "packs"
    for s in range(4):
        write_episode(files / f"ep{s:03d}.h5", synthetic_episode(3, 3, 5, 3, 3, frames=11, seed=s))
    write_pack(pack_dir(packs) / "part_0.h5", load_features(sorted(files.glob("*.h5"))))
    runs = [train(cfg_for("train", tiny(d, tmp_path / f"run_{d.name}", "epochs=2"))) for d in (files, packs)]
    ckpts = [torch.load(tmp_path / f"run_{d.name}" / "last.pt", weights_only=True) for d in (files, packs)]
    assert ckpts[0]["split"] == ckpts[1]["split"]
    for a, b in zip(ckpts[0]["history"], ckpts[1]["history"]):
        assert a["train_loss"] == b["train_loss"] and a["val_loss"] == b["val_loss"]
    assert runs[0]["best"] == runs[1]["best"]


REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("part", sorted(REPO.glob("packs/*/*.h5")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_the_repository_packs_read_with_this_code(part):
    """Every committed part reads as this code's features (its layout and EXTRACT_VERSION), each of its episodes a
    design of finite states whose manifest record says it was solved: a change to learn.features that would make
    them unreadable fails here, not on a fresh machine."""
    features = read_pack(part)
    solved = {f"episode_{int(r['episode']):05d}.h5" for r in pack_manifest(part) if r["status"] in ("ok", "skipped")}
    assert set(features) == solved
    for f in features.values():
        assert np.isfinite(f.joint_state).all() and np.isfinite(f.beam_state).all() and f.design_size > 0


def test_a_pack_of_refusals_only_keeps_them_and_holds_no_episodes(tmp_path):
    """A batch the solver refused entirely (contact, divergence) is packed too, so a fresh machine does not solve it
    again; a pack with neither episodes nor records is refused."""
    records = [{"episode": 7, "status": "contact"}]
    pack = write_pack(tmp_path / "p.h5", [], records)
    assert pack_names(pack) == [] and read_pack(pack) == {} and pack_manifest(pack) == records
    with pytest.raises(PackError, match="or refusals"):
        write_pack(tmp_path / "q.h5", [], [])
