"""Branch whitening: centre, project on the leading principal axes, scale each axis.

Fitted without labels on an atlas's stored vectors of one branch (D or R). Each kept axis i
with eigenvalue ``l_i`` is divided by ``sqrt(l_i + s * mean(l))``: strong axes (``l_i`` well
above the mean) come out with unit variance, weak ones are not blown up (their variance stays
about ``l_i / (s * mean(l))``). ``s`` is the shrinkage; ``s = 0`` is plain PCA-whitening,
which on a few hundred frames amplifies the noisy tail of the spectrum.

The number of kept axes is capped by the data as well as by the stored size: at most
``dims_fraction * n`` for ``n`` fitting vectors, because sample eigenvalues beyond that are
mostly noise. With ``whiten=False`` the axes are kept unscaled (PCA reduction only: the
"whitening off" ablation). Output rows are L2-normalised.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from service.ml.aggregation import l2_normalize

EXACT_LIMIT = 2048  # above this (on the smaller side) the randomised SVD is used
POWER_ITERATIONS = 2  # of the randomised SVD from a random sketch
WARM_POWER_ITERATIONS = 0  # from a nearby fit's axes, already close (see Whitening.fit)
BLOCK_VALUES = 1 << 22  # values of a block of rows projected at once (16 MB)


@dataclass(frozen=True)
class WhiteningConfig:
    """How one branch is reduced and whitened.

    Attributes:
        max_dims: the stored size (axes kept at most).
        dims_fraction: axes kept at most per fitting vector.
        shrinkage: ``s`` above (a multiple of the mean eigenvalue added to every eigenvalue).
        whiten: scale the axes (True) or only project on them (False).
    """

    max_dims: int = 256
    dims_fraction: float = 0.5
    shrinkage: float = 1.0
    whiten: bool = True

    def __post_init__(self) -> None:
        if self.max_dims < 1:
            raise ValueError(f"max_dims must be at least 1, got {self.max_dims}")
        if not 0.0 < self.dims_fraction <= 1.0:
            raise ValueError(f"dims_fraction must lie in (0, 1], got {self.dims_fraction}")
        if self.shrinkage < 0.0:
            raise ValueError(f"shrinkage must be non-negative, got {self.shrinkage}")

    def kept_dims(self, n: int, dim: int) -> int:
        """Axes kept for ``n`` fitting vectors of ``dim`` coordinates (at least one)."""
        return max(1, min(self.max_dims, int(self.dims_fraction * n), dim, n - 1))


@dataclass
class Whitening:
    """A fitted branch transform: ``y = normalize(((x - mean) @ axes) * scale)``.

    Attributes:
        mean: ``dim`` centre of the fitting vectors.
        axes: ``dim x kept`` orthonormal principal axes, strongest first.
        eigenvalues: ``kept`` variances along the axes.
        scale: ``kept`` multipliers (``1 / sqrt(l + s * mean(l))``, or ones without whitening).
    """

    mean: np.ndarray
    axes: np.ndarray
    eigenvalues: np.ndarray
    scale: np.ndarray

    @property
    def input_dim(self) -> int:
        return int(self.axes.shape[0])

    @property
    def dim(self) -> int:
        return int(self.axes.shape[1])

    @classmethod
    def fit(
        cls,
        vectors: np.ndarray,
        config: WhiteningConfig,
        *,
        seed: int = 0,
        near: Whitening | None = None,
    ) -> Whitening:
        """Fit on ``n x dim`` vectors (``n >= 2``).

        Small problems are solved exactly (eigen-decomposition on the smaller side); large
        ones by a randomised SVD of the kept axes only, which is what keeps an 8,192-d VLAD
        of tens of thousands of frames within seconds. ``near``: a whitening fitted on most of
        the same vectors (a calibration's probe, on four fifths of its frames); the randomised
        SVD starts from its axes, already close, with fewer passes over the data.
        """
        x = np.asarray(vectors, np.float32)
        n, dim = x.shape
        if n < 2:
            raise ValueError(f"whitening needs at least 2 vectors, got {n}")
        if near is not None and near.input_dim != dim:
            raise ValueError(f"a {near.input_dim}-d whitening cannot start a {dim}-d fit")
        # float64 sums without float64 copies (a 10,000-frame VLAD matrix would be 1.3 GB)
        # and without a centred copy of the vectors: blocks of rows are centred as needed
        mean = x.mean(0, dtype=np.float64).astype(np.float32)
        total_variance = sum(
            float(np.einsum("ij,ij->", centred, centred, dtype=np.float64))
            for centred in (x[rows] - mean for rows in _row_blocks(x))
        ) / (n - 1)
        if total_variance <= 0.0:
            raise ValueError("whitening needs vectors that are not all equal")
        kept = config.kept_dims(n, dim)
        if min(n, dim) <= EXACT_LIMIT:
            values, axes_all = _exact_axes((x - mean).astype(np.float64))
            rank = int((values > values[0] * 1e-9).sum())
        else:
            start = near.axes if near is not None else None
            values, axes_all = _randomised_axes(x, mean, kept, seed, start)
            rank = min(n - 1, dim)
        eigenvalues_all = values / (n - 1)
        kept = min(kept, rank, len(values))
        eigenvalues = eigenvalues_all[:kept]
        mean_eigenvalue = total_variance / rank
        if config.whiten:
            scale = 1.0 / np.sqrt(eigenvalues + config.shrinkage * mean_eigenvalue)
        else:
            scale = np.ones(kept)
        return cls(
            mean=mean,
            axes=np.ascontiguousarray(axes_all[:, :kept], np.float32),
            eigenvalues=eigenvalues.astype(np.float32),
            scale=scale.astype(np.float32),
        )

    def project(self, vectors: np.ndarray) -> np.ndarray:
        """``n x dim`` -> ``n x kept`` reduced, scaled, unscaled-norm coordinates (in blocks
        of rows: centring a 10,000-frame VLAD matrix at once would copy 650 MB)."""
        x = np.asarray(vectors, np.float32)
        projected = np.empty((len(x), self.dim), np.float32)
        for rows in _row_blocks(x):
            projected[rows] = ((x[rows] - self.mean) @ self.axes) * self.scale
        return projected

    def transform(self, vectors: np.ndarray) -> np.ndarray:
        """``n x dim`` -> ``n x kept`` L2-normalised whitened vectors."""
        return l2_normalize(self.project(vectors))

    def state(self) -> dict[str, np.ndarray]:
        return {
            "mean": self.mean,
            "axes": self.axes,
            "eigenvalues": self.eigenvalues,
            "scale": self.scale,
        }

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> Whitening:
        return cls(
            mean=np.asarray(state["mean"], np.float32),
            axes=np.asarray(state["axes"], np.float32),
            eigenvalues=np.asarray(state["eigenvalues"], np.float32),
            scale=np.asarray(state["scale"], np.float32),
        )


def _row_blocks(matrix: np.ndarray) -> Iterator[slice]:
    """Consecutive slices of ``matrix``'s rows, ``BLOCK_VALUES`` values or so each: a block's
    temporaries are small enough to be recycled by the allocator instead of mapped afresh
    (fresh pages of a 650 MB temporary cost seconds of system time on a virtual machine)."""
    step = max(1, BLOCK_VALUES // max(matrix.shape[1], 1))
    return (slice(start, start + step) for start in range(0, len(matrix), step))


def _exact_axes(centred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared singular values (descending) and right singular vectors of ``centred``."""
    n, dim = centred.shape
    if n < dim:  # eigenvectors of the n x n Gram matrix, mapped back
        values, left = np.linalg.eigh(centred @ centred.T)
        order = np.argsort(values)[::-1]
        values, left = np.clip(values[order], 0.0, None), left[:, order]
        positive = values > values[0] * 1e-9
        axes = centred.T @ left[:, positive] / np.sqrt(values[positive])
        return values[positive], axes
    values, axes = np.linalg.eigh(centred.T @ centred)
    order = np.argsort(values)[::-1]
    return np.clip(values[order], 0.0, None), axes[:, order]


def _randomised_axes(
    vectors: np.ndarray,
    mean: np.ndarray,
    kept: int,
    seed: int,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``kept`` leading squared singular values and right singular vectors (Halko et al.)
    of ``vectors - mean``, the sketch's first columns ``start``'s (``dim x m`` orthonormal
    axes near the answer) where given.

    The centred matrix is never formed: each product with it is one with ``vectors`` less a
    rank-one term, which saves a copy of the matrix (650 MB for 10,000 VLAD vectors).
    """
    generator = torch.Generator().manual_seed(seed)
    matrix = torch.from_numpy(np.require(vectors, requirements=("C", "W")))  # torch: writable
    centre = torch.from_numpy(np.ascontiguousarray(mean))[None]  # 1 x dim

    def times(right: torch.Tensor) -> torch.Tensor:  # (vectors - mean) @ right
        return (matrix @ right).sub_(centre @ right)

    def transposed_times(left: torch.Tensor) -> torch.Tensor:  # (vectors - mean).T @ left
        return (matrix.T @ left).addmm_(centre.T, left.sum(0, keepdim=True), alpha=-1.0)

    sketch = min(kept + 16, *matrix.shape)
    omega = torch.randn(matrix.shape[1], sketch, generator=generator)
    iterations = POWER_ITERATIONS
    if start is not None:
        warm = min(start.shape[1], sketch)
        omega[:, :warm] = torch.from_numpy(np.ascontiguousarray(start[:, :warm], np.float32))
        iterations = WARM_POWER_ITERATIONS
    basis, _ = torch.linalg.qr(times(omega))
    for _ in range(iterations):  # power iterations sharpen a slowly decaying spectrum
        basis, _ = torch.linalg.qr(transposed_times(basis))
        basis, _ = torch.linalg.qr(times(basis))
    _, singular, vh = torch.linalg.svd(transposed_times(basis).T, full_matrices=False)
    values = (singular.double() ** 2).numpy()[:kept]
    return values, vh[:kept].T.numpy()
