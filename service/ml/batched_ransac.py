"""Fundamental-matrix RANSAC for several correspondence sets at once, vectorised in numpy.

Verification fits one fundamental matrix per retrieval candidate. kornia's RANSAC spends most
of a call on fixed per-call work (2048 hypotheses a batch, a Levenberg-Marquardt refinement
of eight models in small torch operations), whether a candidate has 20 matches or 200
(figures: benchmarks/RESULTS.md, "Figures behind choices in the code"). Here the hypotheses of every candidate go through the same few array operations:

- 7-point minimal solver: the two null vectors of each 7 x 9 design matrix by one batched
  7 x 7 elimination (SVD for the degenerate samples), the cubic ``det(l F1 + (1 - l) F2) = 0``
  by interpolation and Cardano's formula (F1 and F2 themselves where it vanishes everywhere,
  as for a frame against itself);
- scoring as kornia's: squared Sampson distance in decoded pixels against ``threshold**2``,
  models ranked by MSAC (``sum(1 - min(e / t**2, 1))``), inliers counted for stopping;
- adaptive rounds: a candidate stops drawing once ``confidence`` says no better model is
  likely left (the standard bound from its best inlier ratio), or at ``max_hypotheses``;
- local optimisation: the eight best minimal models, as kornia keeps, each refitted by the
  weighted normalised 8-point algorithm on its inliers while its MSAC score rises (kornia
  refines by Levenberg-Marquardt instead); the best refit wins.

The result has kornia's convention: no model when the best has no more inliers than its
7-point sample. Inlier counts agree with kornia's within a few on real pairs
(tests/ml/test_verification_real_pairs.py); the settings choose either.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, overload

import numpy as np

SAMPLE = 7
# Below this many correspondences no estimate is attempted (as two_view.MIN_CORRESPONDENCES).
MIN_POINTS = 8
# A pivot this small in the 7-point elimination (Hartley-normalised points are of order 1)
# means a degenerate sample, solved by SVD instead.
SINGULAR_PIVOT = 1e-9
MAX_ROUND = 2048  # hypotheses a set per round at most


@dataclass(frozen=True)
class BatchedRansacConfig:
    """Budget and stopping of :func:`fundamental_ransac_many`.

    Attributes:
        threshold_px: inlier threshold (Sampson distance, pixels).
        confidence: stop a set once a better model is this unlikely to be left undrawn.
        round_size: hypotheses drawn per set in the first round (doubling each round).
        max_hypotheses: hypotheses per set at most (kornia's budget: 5 batches of 2048).
        lo_models: how many of the best minimal models are refined (kornia's eight).
        lo_iterations: 8-point refits of each at most.
        seed: the generator's seed (same input, same answer).
    """

    threshold_px: float = 3.0
    confidence: float = 0.999
    round_size: int = 128
    max_hypotheses: int = 10240
    lo_models: int = 8
    lo_iterations: int = 5
    seed: int = 0


@dataclass
class _Best:
    """A set's pool of best minimal models so far (MSAC score, model), and its sampling."""

    pool: list[tuple[float, np.ndarray]] = field(default_factory=list)
    inliers: int = 0  # of the best one: what stopping counts
    drawn: int = 0


def fundamental_ransac_many(
    sets: Sequence[tuple[np.ndarray, np.ndarray]], config: BatchedRansacConfig
) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """For each ``(a, b)`` of ``K x 2`` pixel correspondences, ``(F, inlier mask)`` with
    ``b^T F a = 0``, or None (fewer than 8 correspondences, or no consensus)."""
    rng = np.random.default_rng(config.seed)
    t2 = config.threshold_px**2
    prepared = [_Prepared(a, b) if len(a) >= MIN_POINTS else None for a, b in sets]
    best = [_Best() for _ in sets]
    active = [i for i, p in enumerate(prepared) if p is not None]
    count, drawn_each = config.round_size, 0
    while active:
        drawn = _seven_point([prepared[i] for i in active], rng, count)  # type: ignore[misc]
        for i, models in zip(active, drawn, strict=True):
            p = prepared[i]
            assert p is not None
            _keep_best(best[i], p, models, t2, config.lo_models)
            best[i].drawn += count
        drawn_each += count
        active = [i for i in active if not _done(best[i], prepared[i], config)]
        # Sets still drawing have a low inlier ratio: larger rounds, fewer of them, up to
        # kornia's batch (memory: hypotheses x 3 models x matches) and within the budget.
        count = min(2 * count, MAX_ROUND, config.max_hypotheses - drawn_each)
    out: list[tuple[np.ndarray, np.ndarray] | None] = []
    for p, b in zip(prepared, best, strict=True):
        if p is None or not b.pool:
            out.append(None)
            continue
        model = _local_optimisation(p, np.stack([m for _, m in b.pool]), t2, config.lo_iterations)
        mask = p.errors(model[None])[0] <= t2
        out.append((model, mask) if mask.sum() > SAMPLE else None)
    return out


class _Prepared:
    """One set's correspondences: homogeneous pixels and Hartley-normalised copies."""

    def __init__(self, a: np.ndarray, b: np.ndarray) -> None:
        self.n = len(a)
        self.a = np.c_[np.asarray(a, np.float64), np.ones(self.n)]
        self.b = np.c_[np.asarray(b, np.float64), np.ones(self.n)]
        self.ta, self.tb = _hartley(self.a), _hartley(self.b)
        self.na, self.nb = self.a @ self.ta.T, self.b @ self.tb.T
        # Transposed and contiguous for the products of scoring (BLAS's fast layout).
        self.design_t = np.ascontiguousarray(_design(self.a, self.b).T)  # b^T F a = F.ravel() @ it
        self.a_t, self.b_t = np.ascontiguousarray(self.a.T), np.ascontiguousarray(self.b.T)

    def to_pixels(self, normalised: np.ndarray) -> np.ndarray:
        """Models fitted on normalised points -> models on pixels (``Tb^T F Ta``)."""
        return np.asarray(self.tb.T @ normalised @ self.ta)

    @overload
    def errors(self, models: np.ndarray) -> np.ndarray: ...

    @overload
    def errors(
        self, models: np.ndarray, with_weights: Literal[True]
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def errors(
        self, models: np.ndarray, with_weights: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Squared Sampson distances, ``models x points``; ``with_weights`` also gives each
        point's ``1 / sqrt(Sampson denominator)`` (the weight of its row in a refit)."""
        m = len(models)
        numerator = (models.reshape(m, 9) @ self.design_t) ** 2  # (b^T F a)^2
        fa = (models[:, :2].reshape(-1, 3) @ self.a_t).reshape(m, 2, self.n)
        ftb = (models[:, :, :2].transpose(0, 2, 1).reshape(-1, 3) @ self.b_t).reshape(m, 2, self.n)
        denominator = (fa**2).sum(1) + (ftb**2).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            e = numerator / denominator
            errors = np.where(np.isfinite(e), e, np.inf)
            if not with_weights:
                return errors
            weights = 1.0 / np.sqrt(denominator)
        return errors, np.where(np.isfinite(weights), weights, 0.0)


def _hartley(points: np.ndarray) -> np.ndarray:
    """The similarity taking ``points`` to zero mean and mean distance sqrt(2)."""
    centre = points[:, :2].mean(0)
    spread = np.linalg.norm(points[:, :2] - centre, axis=1).mean()
    s = math.sqrt(2.0) / spread if spread > 1e-12 else 1.0
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def _design(na: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """Rows of ``b^T F a = 0`` in F's row-major entries, for ``... x 3`` points."""
    return np.asarray(nb[..., :, None] * na[..., None, :]).reshape(*na.shape[:-1], 9)


def _seven_point(sets: list[_Prepared], rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """For each set, the pixel-space models (up to three each) of ``count`` random 7-point
    samples; the samples of all sets are solved together."""
    designs = []
    for p in sets:
        sample = np.argpartition(rng.random((count, p.n)), SAMPLE, axis=1)[:, :SAMPLE]
        designs.append(_design(p.na[sample], p.nb[sample]))  # count x 7 x 9
    design = np.concatenate(designs)
    x, singular = _null_vectors(design)  # (sets * count) x 7 x 2
    total = len(x)
    f1 = np.concatenate([x[:, :, 0], np.ones((total, 1)), np.zeros((total, 1))], 1)
    f2 = np.concatenate([x[:, :, 1], np.zeros((total, 1)), np.ones((total, 1))], 1)
    if singular.any():  # e.g. a sample of points that did not move: the SVD's null space
        _, _, vt = np.linalg.svd(design[singular])
        f1[singular], f2[singular] = vt[:, -1], vt[:, -2]
    f1, f2 = f1.reshape(-1, 3, 3), f2.reshape(-1, 3, 3)
    roots = _cubic_roots(*_det_cubic(f1, f2))  # total x 3, NaN where not real
    models = roots[..., None, None] * f1[:, None] + (1 - roots[..., None, None]) * f2[:, None]
    # Where det vanishes for every l (a null space of rank-2 matrices, as for points that did
    # not move, whose F is any skew-symmetric matrix), F1 and F2 are models themselves.
    no_root = ~np.isfinite(roots).any(1)[:, None, None, None]
    nan = np.full_like(f1[:, None], np.nan)
    models = np.concatenate(
        [models, np.where(no_root, f1[:, None], nan), np.where(no_root, f2[:, None], nan)], 1
    )
    out = []
    for k, p in enumerate(sets):
        mine = models[k * count : (k + 1) * count].reshape(-1, 3, 3)
        out.append(p.to_pixels(mine[np.isfinite(mine).all((1, 2))]))
    return out


def _null_vectors(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each 7 x 9 ``a``: ``x`` (7 x 2) with ``a [x; I2] = 0``, by Gauss-Jordan elimination
    with partial pivoting over the whole batch at once (LAPACK's batched solve pays a call per
    matrix), and which samples were singular (their ``x`` is meaningless)."""
    m = a.copy()
    rows = np.arange(len(m))
    singular = np.zeros(len(m), bool)
    with np.errstate(all="ignore"):
        for k in range(SAMPLE):
            pivot = k + np.abs(m[:, k:, k]).argmax(1)
            m[:, [k]], m[rows, pivot] = m[rows, pivot][:, None], m[:, k].copy()
            singular |= np.abs(m[:, k, k]) < SINGULAR_PIVOT
            m[:, k] /= np.where(singular, 1.0, m[:, k, k])[:, None]
            factors = m[:, :, k].copy()
            factors[:, k] = 0.0
            m -= factors[:, :, None] * m[:, k][:, None, :]
    return -m[:, :, SAMPLE:], singular | ~np.isfinite(m).all((1, 2))


def _det_cubic(
    f1: np.ndarray, f2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (c3, c2, c1, c0) of ``det(l F1 + (1 - l) F2)``, from its values at
    l = 0, 1, -1, 2."""
    d0, d1 = np.linalg.det(f2), np.linalg.det(f1)
    dm1, d2 = np.linalg.det(2 * f2 - f1), np.linalg.det(2 * f1 - f2)
    c0 = d0
    c2 = (d1 + dm1) / 2 - d0
    odd = (d1 - dm1) / 2  # c3 + c1
    c3 = (d2 - 4 * c2 - c0 - 2 * odd) / 6
    return c3, c2, odd - c3, c0


def _cubic_roots(c3: np.ndarray, c2: np.ndarray, c1: np.ndarray, c0: np.ndarray) -> np.ndarray:
    """Real roots of ``c3 x^3 + c2 x^2 + c1 x + c0`` (Cardano), ``... x 3`` with NaN for the
    missing ones."""
    with np.errstate(all="ignore"):
        a, b, c = c2 / c3, c1 / c3, c0 / c3
        p = b - a * a / 3
        q = 2 * a**3 / 27 - a * b / 3 + c
        disc = (q / 2) ** 2 + (p / 3) ** 3
        root = np.sqrt(np.maximum(disc, 0.0))
        one = np.cbrt(-q / 2 + root) + np.cbrt(-q / 2 - root)
        r = 2 * np.sqrt(np.maximum(-p / 3, 0.0))
        cos_arg = np.clip(3 * q / (p * r + (p * r == 0)), -1.0, 1.0)
        phi = np.arccos(cos_arg) / 3
        three = r[..., None] * np.cos(phi[..., None] - 2 * np.pi * np.arange(3) / 3)
        nan = np.full_like(one, np.nan)
        single = np.stack([one, nan, nan], -1)
        roots = np.where((disc > 0)[..., None], single, three) - (a / 3)[..., None]
    return np.where(np.isfinite(roots), roots, np.nan)


def _keep_best(best: _Best, p: _Prepared, models: np.ndarray, t2: float, size: int) -> None:
    """Score ``models`` on ``p`` (MSAC) and keep the ``size`` best so far in ``best``'s pool."""
    if len(models) == 0:
        return
    errors = p.errors(models)
    scores = np.maximum(0.0, 1.0 - errors / t2).sum(1)
    top = np.argsort(-scores)[:size]
    pool = best.pool + [(float(scores[k]), models[k]) for k in top]
    best.pool = sorted(pool, key=lambda found: -found[0])[:size]
    if best.pool[0][0] == scores[top[0]]:
        best.inliers = int((errors[top[0]] <= t2).sum())


def _done(best: _Best, p: _Prepared | None, config: BatchedRansacConfig) -> bool:
    """Enough hypotheses for ``confidence`` given the best inlier ratio, or the budget spent."""
    assert p is not None
    if best.drawn >= config.max_hypotheses:
        return True
    ratio = best.inliers / p.n
    good_sample = ratio**SAMPLE
    if good_sample <= 0.0:
        return False
    if good_sample >= 1.0:
        return True
    needed = math.log(1.0 - config.confidence) / math.log(1.0 - good_sample)
    return best.drawn >= needed


def _local_optimisation(p: _Prepared, models: np.ndarray, t2: float, iterations: int) -> np.ndarray:
    """The best of ``models`` after each is refitted on its inliers while its MSAC score
    rises: the normalised 8-point algorithm with each inlier's row weighted by its Sampson
    denominator (iteratively reweighted least squares of the Sampson error; kornia refines by
    Levenberg-Marquardt). All models are refitted together."""
    errors, weights = p.errors(models, with_weights=True)
    scores = np.maximum(0.0, 1.0 - errors / t2).sum(1)
    design = _design(p.na, p.nb)  # n x 9
    for _ in range(iterations):
        inliers = errors <= t2
        fit = inliers.sum(1) >= MIN_POINTS
        if not fit.any():
            break
        rows = design[None] * (weights * inliers)[..., None]  # models x n x 9
        _, vectors = np.linalg.eigh(np.einsum("mni,mnj->mij", rows, rows))
        u, s, vt = np.linalg.svd(vectors[:, :, 0].reshape(-1, 3, 3))  # smallest: least squares
        s[:, 2] = 0.0  # rank 2
        refits = p.to_pixels(u @ (s[..., None] * vt))
        refit_errors, refit_weights = p.errors(refits, with_weights=True)
        refit_scores = np.maximum(0.0, 1.0 - refit_errors / t2).sum(1)
        better = fit & (refit_scores > scores)
        if not better.any():
            break
        models = np.where(better[:, None, None], refits, models)
        errors = np.where(better[:, None], refit_errors, errors)
        weights = np.where(better[:, None], refit_weights, weights)
        scores = np.where(better, refit_scores, scores)
    return np.asarray(models[int(scores.argmax())])
