"""An atlas's calibration: how stored features become a fused embedding and a calibrated score.

A :class:`Calibration` bundles what is learned, without labels, from an atlas's own stored
features: the local aggregator (a VLAD vocabulary, or the plain mean), one whitening per
branch (:mod:`service.ml.whitening`), the fusion weight ``alpha``, and the impostor model that
turns a cosine into a score with a fixed meaning (:mod:`service.ml.impostors`).

Fusion keeps the paper's form, ``F = alpha * D_w + (1 - alpha) * R_w`` with the two whitened
branches side by side, then L2-normalised: exactly what untrained :class:`LoopNetHeads` compute
on the branch vectors (see :meth:`Calibration.heads_config`), so retrained heads start from
the calibrated branches.

*On the same footing.* Two unit branches of different sizes do not spread their cosines alike
(a whitened 512-d VLAD's impostor cosines spread about 0.6x as wide as a 256-d R's), so a raw
``alpha`` would weigh the wider branch more than it says. The fit measures each branch's
impostor spread and fuses at the weight (:attr:`Calibration.fusion_alpha`) that gives each
branch's *standardised* cosine the share ``alpha^2 : (1 - alpha)^2``: ``alpha`` keeps the
paper's meaning whatever the branch sizes. The default is 0.5 (no branch preferred): chosen
over the paper's 0.7 and 0.6 on the first half of each development set's queries (RESULTS-history.md).
Everything is computed from stored features: re-embedding an atlas never runs a CNN.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import BinaryIO

import numpy as np

from service.ml.aggregation import l2_normalize
from service.ml.aggregators import (
    Aggregator,
    aggregator_from_state,
    fit_aggregator,
)
from service.ml.calibration_config import (
    CalibrationConfig,
    CalibrationInputs,
    FittedCalibration,
    ImpostorProbe,
)
from service.ml.calibration_math import (
    StageClock,
    aggregate_frames,
    cosine_weights,
    descriptor_sample,
    held_out_stretches,
    impostor_spread,
    rotated_onto,
    rows_of,
    spread_of,
    standardised_alpha,
)
from service.ml.features import LocalFeatures
from service.ml.fusion import weighted_branches
from service.ml.heads import HeadsConfig
from service.ml.impostors import (
    MIN_PAIRS,
    ImpostorModel,
    impostor_pairs,
    pair_cosines,
)
from service.ml.whitening import Whitening

FORMAT_VERSION = 1


class Calibration:
    """Aggregator + branch whitenings + alpha + impostor model of one model version."""

    def __init__(
        self,
        config: CalibrationConfig,
        aggregator: Aggregator,
        local_whitening: Whitening,
        global_whitening: Whitening,
        impostors: ImpostorModel | None,
        spread: tuple[float, float] | None = None,
    ) -> None:
        self.config = config
        self.aggregator = aggregator
        self.local_whitening = local_whitening
        self.global_whitening = global_whitening
        self.impostors = impostors
        self.spread = spread

    @property
    def alpha(self) -> float:
        """The branches' weight as the paper means it (on standardised cosines)."""
        return self.config.alpha

    @property
    def fusion_alpha(self) -> float:
        """The weight the fused vector is built with (see the module doc)."""
        return standardised_alpha(self.config.alpha, self.spread)

    def heads_config(self) -> HeadsConfig:
        """Heads over the calibrated branches; untrained, they compute :meth:`fuse`."""
        return HeadsConfig(
            local_dim=self.local_whitening.dim,
            global_dim=self.global_whitening.dim,
            alpha=self.fusion_alpha,
        )

    @property
    def dim(self) -> int:
        return self.local_whitening.dim + self.global_whitening.dim

    # ----- embedding ----------------------------------------------------------------------

    def aggregate(
        self, descriptors: Sequence[np.ndarray], scores: Sequence[np.ndarray]
    ) -> np.ndarray:
        """``n x aggregator.dim`` raw local vectors of ``n`` frames."""
        return aggregate_frames(self.aggregator, descriptors, scores)

    def branch_vectors(
        self,
        descriptors: Sequence[np.ndarray],
        scores: Sequence[np.ndarray],
        global_vectors: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The calibrated branches ``(D_w, R_w)`` of ``n`` frames, each row unit (or zero)."""
        raw = self.aggregate(descriptors, scores)
        return self.branches_of_raw(raw, np.asarray(raw.any(1), bool), global_vectors)

    def branches_of_raw(
        self, local_raw: np.ndarray, has_local: np.ndarray, global_vectors: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The branches ``(D_w, R_w)`` of aggregated local vectors and backbone vectors."""
        local = self.local_whitening.transform(local_raw)
        local[~has_local] = 0.0  # no keypoints: no local evidence, as before
        return local, self.global_whitening.transform(global_vectors)

    def fuse(
        self, local_branch: np.ndarray, global_branch: np.ndarray, alpha: float | None = None
    ) -> np.ndarray:
        """``[a * D_w, (1 - a) * R_w]``, L2-normalised, ``a`` the fusion weight of ``alpha``
        (default: the calibration's) on these branches' spreads."""
        a = self.fusion_alpha if alpha is None else standardised_alpha(alpha, self.spread)
        return l2_normalize(weighted_branches(local_branch, global_branch, a))

    def embed_many(
        self,
        descriptors: Sequence[np.ndarray],
        scores: Sequence[np.ndarray],
        global_vectors: np.ndarray,
    ) -> np.ndarray:
        """``n x dim`` fused unit embeddings of ``n`` frames from their stored features."""
        return self.fuse(*self.branch_vectors(descriptors, scores, global_vectors))

    def embed(self, local: LocalFeatures, global_vector: np.ndarray) -> np.ndarray:
        """The fused unit embedding of one frame (ingest and query)."""
        row: np.ndarray = self.embed_many([local.descriptors], [local.scores], global_vector[None])[
            0
        ]
        return row

    def score(self, cosines: np.ndarray | float) -> np.ndarray:
        """The calibrated score of fused cosines (see :mod:`service.ml.impostors`)."""
        if self.impostors is None:
            raise RuntimeError("this calibration was fitted without an impostor model")
        return self.impostors.score(cosines)

    # ----- persistence --------------------------------------------------------------------

    def save(self, path: Path) -> None:
        """One ``.npz`` (arrays + the config as JSON), written atomically."""
        arrays: dict[str, np.ndarray] = {
            "meta": np.array(
                json.dumps(
                    {
                        "format": FORMAT_VERSION,
                        "config": self.config.to_dict(),
                        "aggregator": self.aggregator.name,
                        "impostors": self.impostors is not None,
                        "spread": list(self.spread) if self.spread is not None else None,
                    }
                )
            )
        }
        parts: dict[str, dict[str, np.ndarray]] = {
            "aggregator": self.aggregator.state(),
            "local": self.local_whitening.state(),
            "global": self.global_whitening.state(),
        }
        if self.impostors is not None:
            parts["impostors"] = self.impostors.state()
        for prefix, state in parts.items():
            arrays.update({f"{prefix}.{key}": value for key, value in state.items()})
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **arrays)  # type: ignore[arg-type]
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path | BinaryIO) -> Calibration:
        """A saved calibration, from its file or a stream of its bytes (never unpickled)."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") != FORMAT_VERSION:
                raise ValueError(f"unsupported calibration format {meta.get('format')}")

            def part(prefix: str) -> dict[str, np.ndarray]:
                return {
                    key.split(".", 1)[1]: data[key]
                    for key in data.files
                    if key.startswith(prefix + ".")
                }

            return cls(
                CalibrationConfig.from_dict(meta["config"]),
                aggregator_from_state(meta["aggregator"], part("aggregator")),
                Whitening.from_state(part("local")),
                Whitening.from_state(part("global")),
                ImpostorModel.from_state(part("impostors")) if meta["impostors"] else None,
                spread_of(meta.get("spread")),
            )

    # ----- fitting ------------------------------------------------------------------------

    @classmethod
    def fit(cls, inputs: CalibrationInputs, config: CalibrationConfig) -> FittedCalibration:
        """Fit every part on an atlas's stored features (no labels); see the module doc."""
        if len(inputs) < 3:
            raise ValueError(f"a calibration needs at least 3 frames, got {len(inputs)}")
        clock = StageClock()
        rng = np.random.default_rng(config.seed)
        sample = descriptor_sample(inputs.descriptors, config.descriptor_sample, rng)
        words = config.words_for(sample.shape[1])
        if config.aggregator == "vlad" and len(sample) < words:
            raise ValueError(
                f"the atlas holds {len(sample)} descriptors, too few for {words} words"
            )
        aggregator = fit_aggregator(config.aggregator, sample, words=words, seed=config.seed)
        clock.lap("vocabulary")

        local_raw = aggregate_frames(aggregator, inputs.descriptors, inputs.scores)
        clock.lap("aggregate")

        has_local = np.asarray(local_raw.any(1), bool)  # frames without keypoints: zero
        fit_rows = rng.permutation(len(inputs))[: config.fit_frames]
        # The impostor probe (below) refits both branches without frames held out in stretches;
        # it is fitted first, from a random sketch, and the full fit starts from its axes (four
        # fifths of the same frames): the full fit's randomised SVD then needs no power
        # iteration, 2 passes over the data instead of 6, and lands at least as near its exact
        # axes (benchmarks/RESULTS.md, "Calibration cost"). Not the other way round: a probe
        # started from the full fit would inherit the frames it holds out (its impostor spread
        # fell 1.6% on Nordland).
        held, probe = _fit_probe(config, aggregator, local_raw, has_local, inputs, fit_rows)
        calibration = _fit_branches(
            config, aggregator, local_raw, has_local, inputs.global_vectors, fit_rows, near=probe
        )
        clock.lap("whitening")

        local_branch, global_branch = calibration.branches_of_raw(
            local_raw, has_local, inputs.global_vectors
        )
        clock.lap("transform")

        found = _impostor_probe(
            probe, (local_branch, global_branch), local_raw, has_local, inputs, held
        )
        first, second = found.first, found.second
        local_cos = pair_cosines(found.local_branch, first, second)
        global_cos = pair_cosines(found.global_branch, first, second)
        both_local = has_local[first] & has_local[second]
        calibration.spread = (impostor_spread(local_cos[both_local]), impostor_spread(global_cos))
        weights = cosine_weights(calibration.fusion_alpha)
        calibration.impostors = ImpostorModel.fit(weights[0] * local_cos + weights[1] * global_cos)
        clock.lap("impostors")
        return FittedCalibration(calibration, local_branch, global_branch, clock.wall, clock.cpu)

    def impostor_probe(self, inputs: CalibrationInputs) -> ImpostorProbe:
        """The probe :meth:`fit` fits its impostor model on, refitted on ``inputs`` by the same
        code (this calibration's vocabulary and settings), for a model version that keeps this
        calibration but changes what a cosine means (retrained heads).

        Heads read coordinates, and the probe's axes are not this calibration's (nor as many):
        each probe branch is rotated onto this calibration's axes by the orthogonal map that best
        carries the seen frames' probe branches to their calibrated ones (Procrustes), so heads
        over this calibration's branches read the probe's, and cosines within a branch are kept.
        """
        local_raw = self.aggregate(inputs.descriptors, inputs.scores)
        has_local = np.asarray(local_raw.any(1), bool)
        seen = self.branches_of_raw(local_raw, has_local, inputs.global_vectors)
        rng = np.random.default_rng(self.config.seed)
        rows = rng.permutation(len(inputs))[: self.config.fit_frames]
        held, probe = _fit_probe(self.config, self.aggregator, local_raw, has_local, inputs, rows)
        found = _impostor_probe(probe, seen, local_raw, has_local, inputs, held)
        if found.in_sample:
            return found
        return replace(
            found,
            local_branch=rotated_onto(found.local_branch, seen[0], ~held & has_local),
            global_branch=rotated_onto(found.global_branch, seen[1], ~held),
        )

    def with_alpha(self, alpha: float) -> Calibration:
        """The same branches at another fusion weight (the impostor model is not refitted)."""
        return Calibration(
            replace(self.config, alpha=alpha),
            self.aggregator,
            self.local_whitening,
            self.global_whitening,
            None,
            self.spread,
        )


def _fit_probe(
    config: CalibrationConfig,
    aggregator: Aggregator,
    local_raw: np.ndarray,
    has_local: np.ndarray,
    inputs: CalibrationInputs,
    rows: np.ndarray,
) -> tuple[np.ndarray, Calibration]:
    """The frames held out in stretches (a mask) and both whitenings fitted on ``rows``
    without them: the impostor probe."""
    held = held_out_stretches(inputs.robots, np.asarray(inputs.order), config.impostor_holdout)
    rest = rows[~held[rows]]
    probe = _fit_branches(config, aggregator, local_raw, has_local, inputs.global_vectors, rest)
    return held, probe


def _impostor_probe(
    probe: Calibration,
    seen: tuple[np.ndarray, np.ndarray],
    local_raw: np.ndarray,
    has_local: np.ndarray,
    inputs: CalibrationInputs,
    held: np.ndarray,
) -> ImpostorProbe:
    """Impostor pairs between frames ``held`` out of ``probe``'s whitenings and frames it saw,
    with every frame's probe branches: in-sample pairs look more orthogonal than any query's.
    Frames are held out in whole stretches of their robot's sequence, so that no place of a
    held-out frame was seen either (a query of a new place, which the score is about). Too few
    such pairs (a tiny atlas): in-sample pairs of the ``seen`` (calibrated) branches."""
    config, order = probe.config, np.asarray(inputs.order)
    first, second = impostor_pairs(
        inputs.robots,
        order,
        pairs=config.impostor_pairs,
        seed=config.seed,
        first_from=held,
        same_place=inputs.same_place,
    )
    if len(first) >= MIN_PAIRS:
        local, global_ = probe.branches_of_raw(local_raw, has_local, inputs.global_vectors)
        return ImpostorProbe(local, global_, first, second, in_sample=False, held=held)
    first, second = impostor_pairs(
        inputs.robots,
        order,
        pairs=config.impostor_pairs,
        seed=config.seed,
        same_place=inputs.same_place,
    )
    return ImpostorProbe(*seen, first, second, in_sample=True)


def _fit_branches(
    config: CalibrationConfig,
    aggregator: Aggregator,
    local_raw: np.ndarray,
    has_local: np.ndarray,
    global_vectors: np.ndarray,
    rows: np.ndarray,
    near: Calibration | None = None,
) -> Calibration:
    """Both whitenings fitted on ``rows`` (distinct; local: those with keypoints, where
    ``has_local``); no impostor model. ``near``: a calibration fitted on mostly the same
    rows, whose axes start the fits."""
    local_rows = rows[has_local[rows]]
    if len(local_rows) < 2:
        raise ValueError("fewer than 2 frames with keypoints: the local branch cannot be fitted")
    if len(rows) < 2:
        raise ValueError("fewer than 2 frames: the global branch cannot be fitted")
    return Calibration(
        config,
        aggregator,
        Whitening.fit(
            rows_of(local_raw, local_rows),
            config.local,
            seed=config.seed,
            near=near.local_whitening if near is not None else None,
        ),
        Whitening.fit(
            rows_of(global_vectors, rows),
            config.global_,
            seed=config.seed,
            near=near.global_whitening if near is not None else None,
        ),
        None,
    )


__all__ = [
    "Calibration",
    "CalibrationConfig",
    "CalibrationInputs",
    "FittedCalibration",
    "aggregate_frames",
    "held_out_stretches",
    "standardised_alpha",
]
