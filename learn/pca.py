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


class Moments:
    """Count, mean and centred scatter matrix of rows seen block by block (Chan et al.'s pairwise merge, float64):
    the moments of every row at once without holding them, so a fit can stream over data built a block at a time
    (a training set turned per batch, learn.dataset.TurnedSet.fit_blocks)."""

    def __init__(self, dim: int):
        self.n = 0
        self.mean = np.zeros(dim)
        self.scatter = np.zeros((dim, dim))  # sum over rows of (x - mean)(x - mean)^T

    @classmethod
    def of(cls, x: np.ndarray, rows: int = CHUNK_ROWS) -> "Moments":
        m = cls(x.shape[1])
        for c in chunks(x, rows):
            m.add(c)
        return m

    def add(self, x) -> "Moments":
        """Merge the rows of x [n, dim] (numpy or torch); returns self."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.mean.shape[0])
        if not len(x):
            return self
        n_b, mean_b = len(x), x.mean(axis=0)
        centred = x - mean_b
        delta, n = mean_b - self.mean, self.n + n_b
        self.scatter += centred.T @ centred + np.outer(delta, delta) * (self.n * n_b / n)
        self.mean += delta * (n_b / n)
        self.n = n
        return self

    @property
    def cov(self) -> np.ndarray:
        """Population covariance [dim, dim]."""
        return self.scatter / max(self.n, 1)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))


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
        return cls.from_moments(Moments.of(x, rows), floor, groups)

    @classmethod
    def from_moments(cls, m: Moments, floor: float = 0.0, groups: list[slice] | None = None) -> "Normalizer":
        """As fit, from the moments of the rows (Moments, accumulated block by block)."""
        mean, std = m.mean, m.std
        for g in groups or [slice(None)]:
            std[g] = np.maximum(std[g], max(floor * std[g].mean(), MIN_STD))
        n = cls(len(mean))
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
        p = cls.from_moments(Moments.of(x, rows), retention)
        for c in chunks(x, rows):
            p.widen_range(c)
        return p

    @classmethod
    def from_moments(cls, m: Moments, retention: float = 0.98) -> "TermPCA":
        """The PCA of the rows whose moments are m; its coefficient range (lo, hi) is empty until widen_range has
        seen the rows (a second pass)."""
        mean, std = m.mean, m.std
        # near-constant columns (a rigid joint's shape in its own frame) are not blown up to unit variance:
        # their scale is floored at SCALE_FLOOR times the term's RMS magnitude (sqrt of the mean of x^2)
        rms = np.sqrt(np.mean(std ** 2 + mean ** 2))
        scale = np.maximum(std, max(SCALE_FLOOR * rms, MIN_STD))
        cov = m.cov / np.outer(scale, scale)  # the covariance of the standardised columns
        eigval, eigvec = np.linalg.eigh(cov)
        order = np.argsort(eigval)[::-1]
        eigval, eigvec = np.clip(eigval[order], 0.0, None), eigvec[:, order]
        total = eigval.sum()
        if total <= 0:
            k = 1
        else:
            k = int(np.searchsorted(np.cumsum(eigval) / total, min(retention, 1.0) - 1e-12) + 1)
            k = min(k, len(mean))
        p = cls(len(mean), k)
        sigma = np.sqrt(np.maximum(eigval[:k], SIGMA_FLOOR ** 2))
        for name, value in (("mean", mean), ("scale", scale), ("components", eigvec[:, :k]), ("sigma", sigma),
                            ("lo", np.full(k, np.inf)), ("hi", np.full(k, -np.inf)),
                            ("explained", eigval[:k].sum() / total if total > 0 else 1.0)):
            getattr(p, name).copy_(torch.as_tensor(value))
        return p

    def widen_range(self, x) -> None:
        """Widen the training range of the coefficients (lo, hi) to cover the rows x [n, D] (numpy or torch), in
        float64."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.dim)
        if not len(x):
            return
        f64 = {k: getattr(self, k).double().numpy() for k in ("mean", "scale", "components", "sigma")}
        z = (x - f64["mean"]) / f64["scale"] @ f64["components"] / f64["sigma"]
        self.lo.copy_(torch.minimum(self.lo, torch.as_tensor(z.min(axis=0), dtype=self.lo.dtype)))
        self.hi.copy_(torch.maximum(self.hi, torch.as_tensor(z.max(axis=0), dtype=self.hi.dtype)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [..., D] -> [..., K]
        return ((x - self.mean) / self.scale) @ self.components / self.sigma

    def inverse(self, z: torch.Tensor) -> torch.Tensor:  # [..., K] -> [..., D]
        return (z * self.sigma) @ self.components.T * self.scale + self.mean

    def outside(self, z: torch.Tensor, margin: float) -> torch.Tensor:
        """[..., K] bool: coefficients beyond the training range widened by `margin` times its width."""
        width = self.hi - self.lo
        return (z < self.lo - margin * width) | (z > self.hi + margin * width)
