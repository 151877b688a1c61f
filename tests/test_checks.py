"""learn.checks: the range checks every count, rate and weight of learn.train / evaluate / predict / diagnose uses."""
from __future__ import annotations

import math
import re

import pytest

from learn.checks import integer_in, number_in


@pytest.mark.parametrize("value", [0, 3, 5, 4.0])
def test_an_integer_in_range_comes_back_as_an_int(value):
    got = integer_in(value, "epochs", 0, 5, "passes")
    assert got == value and type(got) is int


@pytest.mark.parametrize("value", [-1, 6, 2.5, True, "3", None, math.nan, math.inf])
def test_anything_else_is_refused_naming_key_range_and_meaning(value):
    with pytest.raises(ValueError, match=re.escape(f"epochs={value!r}: must be an integer in [0, 5] (passes)")):
        integer_in(value, "epochs", 0, 5, "passes")


@pytest.mark.parametrize("low_open, high_open, bracket, inside, outside", [
    (False, False, "[0, 1]", [0, 0.5, 1], [-1e-9, 1.0001]),
    (True, False, "(0, 1]", [1e-12, 1], [0, 0.0, -0.1]),
    (False, True, "[0, 1)", [0, 0.999], [1, 1.0]),
    (True, True, "(0, 1)", [0.1, 0.9], [0, 1]),
])
def test_each_end_can_be_closed_or_open(low_open, high_open, bracket, inside, outside):
    for value in inside:
        got = number_in(value, "rate", 0, 1, "meaning", low_open=low_open, high_open=high_open)
        assert got == value and type(got) is float
    for value in outside + [math.nan, math.inf, True, "0.5", None]:
        with pytest.raises(ValueError, match=re.escape(f"rate={value!r}: must be a number in {bracket} (meaning)")):
            number_in(value, "rate", 0, 1, "meaning", low_open=low_open, high_open=high_open)


def test_no_upper_end_reads_as_a_bound_not_an_inf_bracket():
    assert number_in(1e4, "optim.lr", 0, math.inf, "rate", low_open=True) == 1e4
    with pytest.raises(ValueError, match=re.escape("optim.lr=0: must be a number > 0 (rate)")):
        number_in(0, "optim.lr", 0, math.inf, "rate", low_open=True)
    with pytest.raises(ValueError, match=re.escape("optim.grad_clip=-1: must be a number >= 0 (off)")):
        number_in(-1, "optim.grad_clip", 0, math.inf, "off")
    with pytest.raises(ValueError, match=re.escape("optim.grad_clip=inf: must be a number >= 0")):
        number_in(math.inf, "optim.grad_clip", 0, math.inf, "off")  # finite only: an infinite clip is no clip, say 0
