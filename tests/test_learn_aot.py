"""learn.aot: a rollout whose every step is an AOTInductor package gives the eager rollout's numbers -- one design,
designs rolled out together, an answer averaged over mirror and lattice copies (whose states reach the step at other
strides than a package's first call), an ensemble -- keeps its packages on disk so that a second stepper compiles
nothing, tells weights apart, and refuses what it cannot compile with the field named."""
import copy
import re

import pytest
import torch
from torch.export.graph_signature import InputKind

from data_schema.testing import synthetic_episode

import learn.aot
from learn.aot import AotSteps, backend_checked, constants_as_buffers, fingerprint, machine_key
from learn.dataset import GraphSet
from learn.ensemble import Ensemble
from learn.features import extract, rebuild_all_points
from learn.model import Simulator, Static
from learn.rollout import answer_unroll, compile_rollout, graph_inputs, plain_inputs

torch.set_num_threads(1)
SCALE = 0.02  # weights drawn around the fit: the solve moves the joints 15-45 mm in 10 steps


@pytest.fixture(scope="module")
def features():
    return [extract(synthetic_episode(3, 3, 5, 3, 3, 5, seed=s), name=f"ep{s}.h5") for s in range(3)]


def small_model(features, seed: int = 0, **args) -> Simulator:
    """A small local-frame stiffness simulator (the default kind) fitted to the features' statistics, its weights
    drawn by `seed` and scaled up so that the solve moves the joints."""
    data = GraphSet.build(features)
    args = {"core": "double_gn", "latent": 8, "widths": [16, 8], "update": "stiffness", "frame": "local",
            "stress_input": False, "pin_fixed_joint": True, "global_latent": 4, **args}
    torch.manual_seed(seed)
    model = Simulator.fit(args, data.joint_state, data.beam_state, data.static)
    with torch.no_grad():
        for p in model.core.parameters():
            p.add_(SCALE * torch.randn(p.shape))
    return model.eval()


def first_frames(features) -> tuple:
    """The eager rollout's inputs for one design or (a list) their disjoint union."""
    if not isinstance(features, list):
        return plain_inputs(features)
    b = GraphSet.first_frames(features)
    return b.joint_state[0], b.beam_state[0], b.static, torch.as_tensor(features[0].t, dtype=torch.float32)


def assert_as_exact_as_eager(got: torch.Tensor, model, features) -> None:
    """A compiled rollout's points are as close to the exact (float64) eager rollout as the float32 eager rollout is:
    within 1e-4 of the design size (learn.evaluate's check) plus 3x the float32 eager rollout's own gap. A random
    model amplifies rounding over the steps (one here: 0.01 mm between float32 and float64), and a compiled step sums
    in another order, so its gap is of that size; a step read wrongly is off by millimetres (a package fed its states
    at other strides than compiled: 150 mm)."""
    j, b, static, t = first_frames(features)
    with torch.inference_mode():
        eager = rebuild_all_points(*answer_unroll(model, j, b, static, t))
        exact = copy.deepcopy(model).double()
        exact = rebuild_all_points(*answer_unroll(exact, j.double(), b.double(), Static(
            static.joint_bc.double(), static.beam_bc.double(), static.index), t.double())).float()
    size = max(f.design_size for f in (features if isinstance(features, list) else [features]))
    rounding = float((eager - exact).abs().max())
    torch.testing.assert_close(got, exact, atol=1e-4 * size + 3 * rounding, rtol=0.0)


def test_aot_steps_give_the_eager_rollout_alone_together_with_copies_and_in_an_ensemble(features, tmp_path):
    model = small_model(features)
    compiled = compile_rollout(model, features[0], "aot", tmp_path)
    with torch.inference_mode():
        for f in features[1:]:  # a package compiled on one design answers another of its size
            assert_as_exact_as_eager(compiled(*graph_inputs(f))[2], model, f)
        assert_as_exact_as_eager(compiled(*graph_inputs(features))[2], model, features)  # a union: its own package
        j, b, static, t = first_frames(features[1])
        moved = (answer_unroll(model, j, b, static, t)[0][-1] - j).abs().max()
    assert compiled.stepper.compiled == 2
    assert moved > 1.0, f"the joints moved {moved:.3g} mm: too little to tell a wrong step from a right one"

    model.answer_with(1, True, 4)  # 8 copies: states [2, 4 J, S], made by movedim, not contiguous
    copies = compile_rollout(model, features[0], "aot", tmp_path)
    assert_as_exact_as_eager(copies(*graph_inputs(features[1]))[2], model, features[1])

    pair = Ensemble([small_model(features, seed=0), small_model(features, seed=1)])
    again = compile_rollout(pair, features[0], "aot", tmp_path)  # member 0's package is on disk already
    assert_as_exact_as_eager(again(*graph_inputs(features[2]))[2], pair, features[2])
    assert again.stepper.compiled == 1  # member 1's
    assert compile_rollout(model.answer_with(1, False, 1), features[0], "aot", tmp_path).stepper.compiled == 0


def test_a_package_is_keyed_by_the_weights_and_bad_backends_are_refused(features, monkeypatch):
    a, b = small_model(features, seed=0), small_model(features, seed=0)
    assert fingerprint(a) == fingerprint(b)
    assert fingerprint(a) == fingerprint(small_model(features, seed=0).answer_with(4, True, 4))  # answers: not the step
    with torch.no_grad():
        next(b.core.parameters())[0, 0] += 1e-6
    assert fingerprint(a) != fingerprint(b)
    before = fingerprint(a)
    monkeypatch.setattr(learn.aot, "_STEP_CODE", b"another step")  # the same weights, the step's code changed
    assert fingerprint(a) != before
    monkeypatch.undo()
    assert fingerprint(a) == before
    with pytest.raises(ValueError, match=re.escape("rollout_backend='tensorrt': must be one of torchscript | aot | "
                                                   "aot_tuned")):
        backend_checked("tensorrt")
    steps = AotSteps(log=None)
    assert steps.machine == machine_key() and "|" in steps.machine  # the CPU its code is built for (-march=native)
    key = ("model", steps.machine, False, 1, None, False, ())
    assert steps.package_path(key) != steps.package_path(("model", "another CPU", *key[2:]))
    kinematic = small_model(features, update="kinematic", frame="global")
    with pytest.raises(ValueError, match="rollout_backend=aot: a kinematic model"):
        AotSteps(log=None).step_of(kinematic)
    with pytest.raises(ValueError, match=re.escape("AotSteps backend='torchscript': must be one of aot | aot_tuned")):
        AotSteps(log=None, backend="torchscript")


def test_a_tuned_package_is_kept_apart_from_an_untuned_one(features):
    """aot_tuned's packages hold other machine code (kernels picked by timing, weights frozen) than aot's for the
    same model and shapes: their keys, hence their files, differ, aot's keys are those written before aot_tuned
    existed, and a tuned key names its inductor options (an unfrozen package of session 51-60 is not taken)."""
    model = small_model(features)
    inputs = [x.contiguous() for x in graph_inputs(features[0])]
    aot, tuned = (AotSteps(log=None, backend=b) for b in ("aot", "aot_tuned"))
    key = aot.key(model, inputs, False, 1, None)
    assert key == (fingerprint(model), machine_key(), False, 1, None, False,
                   tuple((tuple(x.shape), str(x.dtype)) for x in inputs))
    options = '{"autotune_num_choices_displayed": 0, "freezing": true, "max_autotune": true}'
    assert tuned.key(model, inputs, False, 1, None) == key + ("aot_tuned", options)
    assert aot.package_path(key) != tuned.package_path(key + ("aot_tuned", options))
    assert tuned.package_path(key + ("aot_tuned",)) != tuned.package_path(key + ("aot_tuned", options))


class _Scaled(torch.nn.Module):
    """x times a module-level tensor, used twice: torch.export lifts it as a constant read in two places."""

    def forward(self, x):
        return x * _GAINS + _GAINS.sum()


_GAINS = torch.tensor([1.0, 2.0, 3.0])


def test_constants_become_buffers_that_freezing_can_fold():
    """Inductor's freezing fails on a program whose lifted constant is read twice (its constant folding deletes the
    attribute after folding one read away, torch 2.13); as a buffer the constant is frozen like a weight, and the
    program computes what it did."""
    x = torch.tensor([[1.0, -1.0, 0.5]])
    exported = torch.export.export(_Scaled(), (x,))
    assert exported.constants
    converted = constants_as_buffers(exported)
    assert not converted.constants and len(converted.state_dict) == 1
    assert [s.kind for s in converted.graph_signature.input_specs] == [InputKind.BUFFER, InputKind.USER_INPUT]
    torch.testing.assert_close(converted.module()(x), _Scaled()(x), rtol=0, atol=0)


@pytest.mark.slow
def test_tuned_aot_steps_give_the_eager_rollout(features, tmp_path):
    """max_autotune's micro-kernels sum in their own order: the tuned rollout stays as close to the exact one as
    the untuned one must (~2 min: each kernel candidate is compiled and timed)."""
    model = small_model(features)
    compiled = compile_rollout(model, features[0], "aot_tuned", tmp_path)
    with torch.inference_mode():
        assert_as_exact_as_eager(compiled(*graph_inputs(features[1]))[2], model, features[1])
    assert compiled.stepper.compiled == 1 and compiled.stepper.backend == "aot_tuned"
