"""What one ``loopnet eval`` run is asked to do (:func:`service.evaluation.runner.run_evaluation`
reads it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service.evaluation.retraining_pass import PROTOCOLS
from service.jobs.adaptation_config import DEFAULT_METHOD, AdaptMethod


@dataclass(frozen=True)
class EvalConfig:
    """One evaluation run.

    Attributes:
        dataset: the dataset folder; ``layout`` ``auto`` detects its layout.
        output: the report folder (created).
        tolerance: frame tolerance (traversals, CSV frames); None: 1.
        distance: metres for position ground truth (CSV).
        reference, query: the traversal folders, where auto-detection is not wanted.
        submap_size: consecutive reference frames per submap (datasets without their own).
        preset, long_side, max_keypoints, backbone: the model settings (``resolve_preset``).
        extractors: local extractors, one service pass each; the first is "LoopNet".
        alphas: fusion weights of the ablations.
        baselines: classical baselines to run.
        limit: keep the first ``limit`` reference frames (a quick slice).
        cache_dir: where extracted features are cached (None: ``output/cache``).
        retrain_shots: K values (shots per submap) of the retrained rows; empty: none.
        retrain_protocols: ``map`` and/or ``revisit`` (see ``retraining_pass``).
        retrain_params: retraining job parameters (``TrainingConfig`` fields) other than the
            job's defaults, e.g. ``{"positive_window": 0}`` for an ablation; ``shots`` is K.
        verify: matchers ("mnn", "lightglue") whose geometric verification of the first
            extractor's ranking adds a row each; empty: none.
        verify_top: candidates verified per query.
        ransac_backend: the verification rows' fundamental-matrix RANSAC ("batched",
            "kornia"; the service's ``LOOPNET_RANSAC_BACKEND``).
        query_stride: keep every n-th query only (bounded runs on long datasets).
        sequence: sequence lengths L of the ``+seqL`` rows; empty: none.
        sequence_contrast: the sequence rows' local contrast window (0: whole-map z-scores).
        sequence_seed_frames: newest query frames whose best matches propose candidates (0:
            every frame's, the service's default; 1: the newest frame's own search hits).
        precision: the CNNs' arithmetic (``service.ml.precision``); features cached in one
            precision are reused in another, so give each its own ``cache_dir``.
        served: add a ``loopnet-<extractor>-served`` row per extractor: the queries answered
            as the service serves them (``served_pass``).
        adapt_observe_shots: K values of the pairs protocol (``pairs_pass``: the pairs the
            service's own observe verified, a real adapt job, served before -> after); needs
            ``served``.
        adapt_labelled_shots: the same with the shots labelled as pairs with their partner
            references (the revisit protocol as served).
        adapt_stream_percents: the same with the first P % of the queries driven in order by
            one robot through observe (its sequence on), the rest the test queries.
    """

    dataset: Path
    output: Path
    layout: str = "auto"
    tolerance: int | None = None
    distance: float = 25.0
    reference: str | None = None
    query: str | None = None
    submap_size: int = 5
    preset: str = "default"
    long_side: int | None = None
    max_keypoints: int | None = None
    backbone: str | None = None
    extractors: tuple[str, ...] = ("disk", "xfeat")
    alphas: tuple[float, ...] = (0.0, 0.3, 0.5, 0.7, 1.0)
    baselines: tuple[str, ...] = ("bow-orb", "seqslam-sad")
    limit: int | None = None
    cache_dir: Path | None = None
    examples: int = 6
    k: int = 10
    retrain_shots: tuple[int, ...] = ()
    retrain_protocols: tuple[str, ...] = PROTOCOLS
    retrain_params: dict[str, Any] = field(default_factory=dict)
    adapt_shots: tuple[int, ...] = ()
    adapt_shrinkage: float | None = None
    adapt_method: AdaptMethod = DEFAULT_METHOD
    adapt_observe_shots: tuple[int, ...] = ()
    adapt_labelled_shots: tuple[int, ...] = ()
    adapt_stream_percents: tuple[int, ...] = ()
    command: str = ""
    verify: tuple[str, ...] = ()
    verify_top: int = 5
    ransac_backend: str = "batched"
    query_stride: int = 1
    sequence: tuple[int, ...] = ()
    sequence_contrast: int = 0
    sequence_seed_frames: int = 0
    precision: str = "fp32"
    served: bool = True
