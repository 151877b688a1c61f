"""The training envelope of conditions the graphs do not carry (learn.conditions)."""
import numpy as np

from learn.conditions import envelope, episode_conditions, outside

CFG = """material:
  law: marlow
  poisson: 0.49
  residual_stress: {sigma: 0.0658, joint_model: average}
scene: {gravity: true, g: 9810.0}
mesh: {nodes_length: 9}
"""
SQUARE = np.array([[0, 0], [60, 0], [60, 80], [0, 80]], float)
RING = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])


def test_conditions_read_the_config_and_the_design():
    c = episode_conditions(CFG, SQUARE, RING)
    assert c["material.residual_stress.sigma"] == 0.0658 and c["scene.g"] == 9810.0
    assert c["material.law"] == "marlow" and c["scene.gravity"] == "True"
    assert c["design.n_joints"] == 4.0 and c["design.beam_length"] == [60.0, 80.0]
    assert "scene.buoyancy" not in c  # absent from the config: not invented
    assert episode_conditions("", SQUARE, RING)["design.n_joints"] == 4.0


def test_inside_the_envelope_passes_and_each_kind_of_departure_is_named():
    env = envelope([episode_conditions(CFG, SQUARE, RING), episode_conditions(CFG, SQUARE * 1.5, RING)])
    assert env["design.beam_length"] == [60.0, 120.0] and env["material.law"] == ["marlow"]
    assert outside(episode_conditions(CFG, SQUARE * 1.2, RING), env) == []
    assert outside(episode_conditions(CFG, SQUARE * 1.54, RING), env) == []  # 123 mm: within the 5 % slack
    long = outside(episode_conditions(CFG, SQUARE * 2.0, RING), env)
    assert len(long) == 1 and long[0].startswith("design.beam_length = [120, 160] outside")
    hot = outside(episode_conditions(CFG.replace("0.0658", "0.1316"), SQUARE, RING), env)
    assert hot == ["material.residual_stress.sigma = 0.1316 outside the training range [0.0658, 0.0658]"]
    other = outside(episode_conditions(CFG.replace("marlow", "yeoh"), SQUARE, RING), env)
    assert other == ["material.law = yeoh not among the training values ['marlow']"]
