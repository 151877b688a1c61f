"""Per-term PCA and normalisers as torch modules whose statistics are buffers, saved with the model."""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

MIN_STD = 1e-6
SCALE_FLOOR = 1e-3  # column scale >= this fraction of the term's RMS magnitude
SIGMA_FLOOR = 0.05  # whitening never amplifies a standardised component by more than 1 / SIGMA_FLOOR
CHUNK_ROWS = 1 << 18  # rows per float64 pass of the fits: their memory stays ~150 MB however many rows they see


def chunks(x: np.ndarray, rows: int = CHUNK_ROWS):
    """[n, D] -> float64 row blocks of at most `rows` rows (a fit of tens of millions of rows never holds a float64
    copy of them all)."""
    for start in range(0, len(x), rows):
        yield np.asarray(x[start:start + rows], dtype=np.float64)


def column_moments(x: np.ndarray, rows: int = CHUNK_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """[n, D] -> per-column mean and (population) std, in two float64 passes over row blocks."""
    n = max(len(x), 1)
    mean = sum((c.sum(axis=0) for c in chunks(x, rows)), np.zeros(x.shape[1])) / n
    var = sum((((c - mean) ** 2).sum(axis=0) for c in chunks(x, rows)), np.zeros(x.shape[1])) / n
    return mean, np.sqrt(var)


class Normalizer(nn.Module):
    """x -> (x - mean) / std per column; `floor` keeps near-constant columns from being blown up."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    @classmethod
    def fit(cls, x: np.ndarray, floor: float = 0.0, groups: list[slice] | None = None,
            rows: int = CHUNK_ROWS) -> "Normalizer":
        """x [n, dim]; a column whose std is below `floor` times the mean std of its group of columns (groups:
        column slices of one unit, e.g. geometry and stress; default all columns) gets that value instead."""
        mean, std = column_moments(x, rows)
        for g in groups or [slice(None)]:
            std[g] = np.maximum(std[g], max(floor * std[g].mean(), MIN_STD))
        n = cls(x.shape[1])
        n.mean.copy_(torch.as_tensor(mean))
        n.std.copy_(torch.as_tensor(std))
        return n

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.std + self.mean


class TermPCA(nn.Module):
    """One feature term: standardise each column, project on the principal axes that retain `retention` of the
    variance, whiten. Standardising first keeps rare but decisive columns (the fixed-joint flag) from being cut.

    Buffers: mean, scale [D]; components [D, K]; sigma, lo, hi [K] (training range of the coefficients);
    explained (the variance fraction retained).
    """

    def __init__(self, dim: int, k: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("scale", torch.ones(dim))
        self.register_buffer("components", torch.zeros(dim, k))
        self.register_buffer("sigma", torch.ones(k))
        self.register_buffer("lo", torch.full((k,), -torch.inf))
        self.register_buffer("hi", torch.full((k,), torch.inf))
        self.register_buffer("explained", torch.tensor(1.0))

    @property
    def dim(self) -> int:
        return self.components.shape[0]

    @property
    def k(self) -> int:
        return self.components.shape[1]

    @classmethod
    def fit(cls, x: np.ndarray, retention: float = 0.98, rows: int = CHUNK_ROWS) -> "TermPCA":
        """x [n, D] training rows (training split only); float64 passes over blocks of `rows` rows."""
        n = max(len(x), 1)
        mean, std = column_moments(x, rows)
        # near-constant columns (a rigid joint's shape in its own frame) are not blown up to unit variance:
        # their scale is floored at SCALE_FLOOR times the term's RMS magnitude (sqrt of the mean of x^2)
        rms = np.sqrt(np.mean(std ** 2 + mean ** 2))
        scale = np.maximum(std, max(SCALE_FLOOR * rms, MIN_STD))
        standardised = lambda c: (c - mean) / scale  # noqa: E731
        cov = sum((xs.T @ xs for xs in map(standardised, chunks(x, rows))), np.zeros((x.shape[1],) * 2)) / n
        eigval, eigvec = np.linalg.eigh(cov)
        order = np.argsort(eigval)[::-1]
        eigval, eigvec = np.clip(eigval[order], 0.0, None), eigvec[:, order]
        total = eigval.sum()
        if total <= 0:
            k = 1
        else:
            k = int(np.searchsorted(np.cumsum(eigval) / total, min(retention, 1.0) - 1e-12) + 1)
            k = min(k, x.shape[1])
        p = cls(x.shape[1], k)
        sigma = np.sqrt(np.maximum(eigval[:k], SIGMA_FLOOR ** 2))
        lo, hi = np.full(k, np.inf), np.full(k, -np.inf)  # the training range of the coefficients
        for c in chunks(x, rows):
            z = standardised(c) @ eigvec[:, :k] / sigma
            lo, hi = np.minimum(lo, z.min(axis=0)), np.maximum(hi, z.max(axis=0))
        for name, value in (("mean", mean), ("scale", scale), ("components", eigvec[:, :k]), ("sigma", sigma),
                            ("lo", lo), ("hi", hi),
                            ("explained", eigval[:k].sum() / total if total > 0 else 1.0)):
            getattr(p, name).copy_(torch.as_tensor(value))
        return p

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [..., D] -> [..., K]
        return ((x - self.mean) / self.scale) @ self.components / self.sigma

    def inverse(self, z: torch.Tensor) -> torch.Tensor:  # [..., K] -> [..., D]
        return (z * self.sigma) @ self.components.T * self.scale + self.mean

    def outside(self, z: torch.Tensor, margin: float) -> torch.Tensor:
        """[..., K] bool: coefficients beyond the training range widened by `margin` times its width."""
        width = self.hi - self.lo
        return (z < self.lo - margin * width) | (z > self.hi + margin * width)
