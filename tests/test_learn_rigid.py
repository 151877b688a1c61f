"""learn.rigid: Kabsch rotations and the split of a block's error into orientation, placement and shape."""
import numpy as np
import pytest

from learn.rigid import best_rotation, block_parts, rotation_angle_deg, shape_error


def rotation(axis, angle_deg: float) -> np.ndarray:
    """Rodrigues: the rotation by angle_deg about axis."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


@pytest.fixture
def block():
    return np.random.default_rng(0).normal(scale=5.0, size=(12, 3))  # mm, a block's points


def test_best_rotation_recovers_a_rotation_and_its_angle(block):
    R = rotation([1.0, -2.0, 0.5], 37.0)
    moved = block @ R.T + np.array([3.0, -1.0, 7.0])
    np.testing.assert_allclose(best_rotation(block, moved), R, atol=1e-10)
    assert rotation_angle_deg(best_rotation(block, moved)) == pytest.approx(37.0, abs=1e-6)
    batch = best_rotation(np.stack([block, block]), np.stack([moved, block]))  # broadcasts over leading axes
    np.testing.assert_allclose(batch[1], np.eye(3), atol=1e-10)


def test_best_rotation_is_proper_even_for_a_mirror_image(block):
    R = best_rotation(block, block * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-10)


def test_block_parts_separate_turn_placement_and_shape(block):
    truth = block @ rotation([0, 1, 1], 30.0).T + np.array([10.0, 0.0, 0.0])
    centre = truth.mean(0)
    off = np.array([0.3, -0.4, 0.0])  # mm, 0.5 mm away
    turned = (truth - centre) @ rotation([1, 0, 0], 5.0).T + centre + off
    parts = block_parts(turned, truth, block)
    assert parts["orientation_error_deg"] == pytest.approx(5.0, abs=1e-6)
    assert parts["turn_deg"] == pytest.approx(30.0, abs=1e-6)
    assert parts["placement"] == pytest.approx(0.5, abs=1e-9)
    assert parts["shape"] == pytest.approx(0.0, abs=1e-9)
    swollen = centre + 1.1 * (truth - centre)  # no turn, no move: all shape
    parts = block_parts(swollen, truth, block)
    assert parts["orientation_error_deg"] == pytest.approx(0.0, abs=1e-5)
    assert parts["placement"] == pytest.approx(0.0, abs=1e-9)
    assert parts["shape"] == pytest.approx(0.1 * np.linalg.norm(truth - centre, axis=1).max(), rel=1e-9)


def test_a_beams_bend_is_its_turn_relative_to_its_start_joint(block):
    """learn.diagnose.relative_turns: a beam turned 30 deg against its joint bends 30 deg; a prediction that turns
    joint and beam alike by 15 deg more has no bend error (its error is carried, not the beam's own); one whose beam
    turns 20 deg against its joint errs by 10 deg."""
    from learn.diagnose import relative_turns
    joint, beam = block[:6], block[6:] + 20.0
    A = rotation([0.2, 1.0, 0.3], 40.0)  # the whole grid's turn
    B = rotation([1.0, 0.0, 0.0], 30.0)  # the beam's own bend about its axis
    frames = lambda bend, extra: (  # noqa: E731  [F=2, 1 block, N, 3]: flat, then turned
        np.stack([joint, joint @ (extra @ A).T])[:, None], np.stack([beam, beam @ (extra @ A @ bend).T])[:, None])
    truth = frames(B, np.eye(3))
    error, bend = relative_turns(truth, truth, np.array([0]))
    assert bend[0, 0] == pytest.approx(30.0, abs=1e-6) and error[0, 0] == pytest.approx(0.0, abs=1e-5)
    carried = frames(B, rotation([0.0, 1.0, 0.0], 15.0))
    assert relative_turns(carried, truth, np.array([0]))[0][0, 0] == pytest.approx(0.0, abs=1e-5)
    short = frames(rotation([1.0, 0.0, 0.0], 20.0), np.eye(3))
    assert relative_turns(short, truth, np.array([0]))[0][0, 0] == pytest.approx(10.0, abs=1e-5)


def test_shape_error_is_what_no_rigid_motion_of_the_whole_answer_explains(block):
    """learn.evaluate's shape_rel_error: an answer that is the truth turned and moved has no shape error (however
    large its point error); one swollen about its centroid keeps the swelling; frames broadcast."""
    truth = np.stack([block, block @ rotation([0, 1, 1], 30.0).T])  # [F=2, N, 3]
    moved = truth @ rotation([1.0, 0.2, 0.0], 12.0).T + np.array([5.0, -2.0, 1.0])
    assert np.linalg.norm(moved - truth, axis=-1).max() > 1.0  # mm: the point error is not small
    np.testing.assert_allclose(shape_error(moved, truth), [0.0, 0.0], atol=1e-9)
    centre = truth.mean(-2, keepdims=True)
    swollen = centre + 1.1 * (truth - centre)
    expected = 0.1 * np.linalg.norm(truth - centre, axis=-1).max(-1)  # the fit of a swelling is the identity
    np.testing.assert_allclose(shape_error(swollen, truth), expected, rtol=1e-9)
