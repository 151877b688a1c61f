"""A count in the factory's configuration checked against its allowed range: an integer (a bool, a float such as
2.5 or a word is refused, never rounded) >= low, or in [low, high], else the caller's error class naming the field,
the value, the range and what the value means. fea_factory.sample (grid counts), fea_factory.generate (episode
counts, seeds, jobs, ranks, shards) and fea_factory.material (the Marlow order) read their counts through it."""
from __future__ import annotations

import numpy as np


def integer_in(value, name: str, error: type[Exception], low: int, high: int | None = None,
               meaning: str = "") -> int:
    """value as an int when it is an integer >= low (and <= high if given); otherwise `error` naming `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low or \
            (high is not None and value > high):
        allowed = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise error(f"{name} = {value!r}: must be an integer {allowed}" + (f" ({meaning})" if meaning else ""))
    return int(value)
