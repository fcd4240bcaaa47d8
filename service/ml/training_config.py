"""A retraining's parameters: what the API validates at submit and the worker trains with."""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from service.ml.heads import HeadsConfig

TrainablePart = Literal["fusion", "similarity", "classifier"]
TRAINABLE_PARTS: tuple[TrainablePart, ...] = ("fusion", "similarity", "classifier")
MAX_SEED = 2**64 - 1


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class TrainingConfig:
    """Parameters of one retraining run, with their bounds: the API's job parameters are this
    schema, so a value either side accepts, both do."""

    shots: int = Field(default=5, ge=1, le=100, description="Training frames (shots) per submap.")
    epochs: int = Field(
        default=100, ge=1, le=2000, description="Most epochs; early stopping may end sooner."
    )
    learning_rate: float = Field(default=3e-3, gt=0, le=1)
    weight_decay: float = Field(default=1e-4, ge=0, le=1)
    classification_weight: float = Field(
        default=1.0, ge=0, le=100, description="Cross-entropy weight."
    )
    contrastive_weight: float = Field(
        default=1.0, ge=0, le=100, description="Contrastive loss weight."
    )
    margin: float = Field(
        default=1.0, gt=0, le=2, description="Contrastive margin m (unit-sphere distance)."
    )
    embed_dim: int | None = Field(
        default=None,
        ge=2,
        le=4096,
        description="Size of the trained fused embedding; unset: the active heads' fused "
        "input size, so training starts from the active embedding itself.",
    )
    train: tuple[TrainablePart, ...] = Field(
        default_factory=lambda: TRAINABLE_PARTS,
        min_length=1,
        description="Which layers are trained; the others keep their initialisation.",
    )
    noise_std: float = Field(
        default=0.01, ge=0, le=1, description="Gaussian noise on stored vectors."
    )
    feature_dropout: float = Field(
        default=0.1, ge=0, lt=1, description="Feature dropout on stored vectors."
    )
    patience: int = Field(
        default=15, ge=1, le=1000, description="Epochs without validation gain before stopping."
    )
    seed: int = Field(default=0, ge=0)
    # Frame-level term: two augmented views of each shot must find each other among all the
    # shots (instance discrimination), so pulling a submap together cannot merge its frames.
    # Off by default: it did not stop map-only retraining from lowering Recall@1 on every K
    # (see benchmarks/RESULTS.md); the job's held-out not-worse check is the safeguard.
    frame_weight: float = Field(
        default=0.0, ge=0, le=100, description="Weight of the frame-level (instance) term."
    )
    frame_temperature: float = Field(
        default=0.1, gt=0, le=10, description="Temperature of the frame-level term."
    )
    keep_weight: float = Field(
        default=0.0,
        ge=0,
        le=100,
        description="Weight of the term that keeps the trained cosines of the shots' "
        "non-positive pairs near the starting heads' (against forgetting); 0: off.",
    )
    positive_window: int = Field(
        default=2,
        ge=0,
        le=1000,
        description="Contrastive positives: frames of one submap at most this many frames "
        "apart in their robot's sequence; 0: the first design (every pair of a submap "
        "positive, every pair of different submaps negative).",
    )

    def __post_init__(self) -> None:
        if self.classification_weight == 0 and self.contrastive_weight == 0:
            raise ValueError("at least one loss weight must be positive")
        if self.seed > MAX_SEED:  # not a schema bound: JSON Schema would round it to a float
            raise ValueError(f"seed must be in 0..{MAX_SEED} (64 bits, what torch accepts)")

    def check_fits(self, base: HeadsConfig) -> None:
        """Refuse an ``embed_dim`` the atlas's features cannot fill: the fusion starts from a
        PCA of the fused input, which has only ``local_dim + global_dim`` directions."""
        fused_input = base.local_dim + base.global_dim
        if self.embed_dim is not None and self.embed_dim > fused_input:
            raise ValueError(
                f"embed_dim {self.embed_dim} exceeds the atlas's fused input size {fused_input} "
                f"({base.local_dim} local + {base.global_dim} global)"
            )
