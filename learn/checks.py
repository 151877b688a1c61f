"""Configuration values checked against their allowed ranges: an integer or a number in [low, high] (either end
open on request), else a ValueError naming the key, the range and what the value means. Every count, rate and weight
of learn.train, learn.evaluate, learn.predict, learn.diagnose and the model's options (learn.model, learn.gn) is read
through these two."""
from __future__ import annotations

import math


def integer_in(value, name: str, low: int, high: int, meaning: str) -> int:
    """value as an int when it is an integer in [low, high]; otherwise a ValueError naming `name` and the range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or \
            int(value) != value or not low <= value <= high:
        raise ValueError(f"{name}={value!r}: must be an integer in [{low}, {high}] ({meaning})")
    return int(value)


def number_in(value, name: str, low: float, high: float, meaning: str, low_open: bool = False,
              high_open: bool = False) -> float:
    """value as a float when it is a finite number in [low, high] (an end excluded with low_open / high_open);
    otherwise a ValueError naming `name` and the range (no upper bracket when high is inf)."""
    number = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not number or not (low < value if low_open else low <= value) or \
            not (value < high if high_open else value <= high):
        if math.isinf(high):
            allowed = f"a number {'>' if low_open else '>='} {low:g}"
        else:
            allowed = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
        raise ValueError(f"{name}={value!r}: must be {allowed} ({meaning})")
    return float(value)
