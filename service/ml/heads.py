"""LoopNet's heads on the fused feature: fusion, a similarity head and a classification head.

Fusion follows the paper, F = alpha * D + (1 - alpha) * R, with D (the aggregated local
descriptor) and R (the backbone vector) each brought into one fused space by a linear map.

Before any training the embedding is already meaningful: both maps start as block identities
(D into the first ``local_dim`` coordinates, R into the rest, ``embed_dim`` unset), and the
similarity head is a residual MLP whose last layer starts at zero. So an untrained model computes

    cos(E1, E2) = (alpha^2 cos(D1, D2) + (1 - alpha)^2 cos(R1, R2)) / (alpha^2 + (1 - alpha)^2)

for frames with keypoints: a fixed blend of the two pretrained branches' cosines. Trained
versions use a compact fused space (``embed_dim``, e.g. 256) whose maps start from a PCA of the
atlas's own stored features (see :mod:`service.ml.training`), so training never starts from
noise either, and re-embedding a large atlas stays cheap.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from service.ml.fusion import weighted_branches

DEFAULT_ALPHA = 0.7


@dataclass(frozen=True)
class HeadsConfig:
    """Shapes and the fusion weight of a model version's heads."""

    local_dim: int
    global_dim: int
    alpha: float = DEFAULT_ALPHA
    hidden_dim: int = 256
    # None: the fused space is D and R side by side (block identities, the untrained model).
    embed_dim: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"alpha must lie in [0, 1], got {self.alpha}")
        if self.embed_dim is not None and self.embed_dim < 2:
            raise ValueError(f"embed_dim must be at least 2, got {self.embed_dim}")

    @property
    def fused_dim(self) -> int:
        return self.embed_dim or self.local_dim + self.global_dim


class Fusion(nn.Module):
    """``F = alpha * P_D(D) + (1 - alpha) * P_R(R) + b``: ``B x local, B x global -> B x fused``.

    Initialised as block identities with ``b = 0`` (D and R side by side); a retraining job
    re-initialises ``P_D``, ``P_R`` and ``b`` from a PCA of the atlas before training.
    """

    def __init__(self, config: HeadsConfig) -> None:
        super().__init__()
        self.alpha = config.alpha
        self.project_local = nn.Linear(config.local_dim, config.fused_dim, bias=False)
        self.project_global = nn.Linear(config.global_dim, config.fused_dim, bias=False)
        self.bias = nn.Parameter(torch.zeros(config.fused_dim))
        with torch.no_grad():
            block = torch.eye(config.local_dim + config.global_dim)[: config.fused_dim]
            self.project_local.weight.copy_(block[:, : config.local_dim])
            self.project_global.weight.copy_(block[:, config.local_dim :])
        self._blocks_checked: tuple[int, ...] | None = None
        self._blocks = False

    def forward(self, local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
        if self.is_block_identity():  # D and R side by side: no product with an identity
            return weighted_branches(local, global_, self.alpha) + self.bias
        weighted = weighted_branches(local, global_, self.alpha)
        return F.linear(weighted, self.stacked_weight(), self.bias)

    def stacked_weight(self) -> torch.Tensor:
        """``[P_D  P_R]`` (``fused x local + global``): times ``[alpha D, (1 - alpha) R]`` it
        gives ``alpha P_D D + (1 - alpha) P_R R``."""
        return torch.cat([self.project_local.weight, self.project_global.weight], dim=1)

    def is_block_identity(self) -> bool:
        """Whether the projections are still the block identities of the untrained model, so
        the fusion is a weighted concatenation: multiplying by an identity of the branches'
        size reads tens of MB per frame for nothing.
        Checked again whenever a projection's tensor changes (its in-place version counter:
        training steps and ``load_state_dict`` bump it) and never while autograd records."""
        local_w, global_w = self.project_local.weight, self.project_global.weight
        if torch.is_grad_enabled() and (local_w.requires_grad or global_w.requires_grad):
            return False
        try:
            key = (id(local_w), local_w._version, id(global_w), global_w._version)
        except RuntimeError:  # inference tensors have no version counter: check every time
            key = None
        if key is None or key != self._blocks_checked:
            with torch.no_grad():
                block = torch.eye(local_w.shape[0], local_w.shape[1] + global_w.shape[1])
                self._blocks = local_w.shape[0] == local_w.shape[1] + global_w.shape[1] and bool(
                    torch.equal(local_w, block[:, : local_w.shape[1]])
                    and torch.equal(global_w, block[:, local_w.shape[1] :])
                )
            self._blocks_checked = key
        return self._blocks


class SimilarityHead(nn.Module):
    """Residual MLP, then L2 norm: ``B x fused -> B x fused`` unit embeddings for cosine search."""

    def __init__(self, config: HeadsConfig) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(config.fused_dim, config.hidden_dim),
            nn.ReLU(inplace=True),
            nn.Linear(config.hidden_dim, config.fused_dim),
        )
        last = self.mlp[2]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, fused: torch.Tensor) -> torch.Tensor:
        return F.normalize(fused + self.mlp(fused), dim=-1)


class ClassificationHead(nn.Module):
    """Linear classifier over an atlas's submaps: ``B x fused -> B x n_submaps`` logits."""

    def __init__(self, config: HeadsConfig, num_classes: int) -> None:
        super().__init__()
        self.linear = nn.Linear(config.fused_dim, num_classes)

    def forward(self, fused: torch.Tensor) -> torch.Tensor:
        logits: torch.Tensor = self.linear(F.normalize(fused, dim=-1))
        return logits


@dataclass
class SubmapPrediction:
    submap_id: int
    probability: float


class LoopNetHeads(nn.Module):
    """Fusion + similarity head + (once trained) classification head of one model version.

    ``class_labels[i]`` is the submap id of the classifier's output ``i``; an untrained model
    has no classifier and ``class_labels`` is empty.
    """

    def __init__(self, config: HeadsConfig, class_labels: list[int] | None = None) -> None:
        super().__init__()
        self.config = config
        self.fusion = Fusion(config)
        self.similarity = SimilarityHead(config)
        self.class_labels = list(class_labels or [])
        self.classifier: ClassificationHead | None = (
            ClassificationHead(config, len(self.class_labels)) if self.class_labels else None
        )

    @property
    def has_classifier(self) -> bool:
        return self.classifier is not None

    def embed(self, local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
        """``B x local_dim, B x global_dim -> B x fused_dim`` L2-normalised embeddings."""
        embedded: torch.Tensor = self.similarity(self.fusion(local, global_))
        return embedded

    def classify(self, local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
        """``B x n_submaps`` logits; raises if this model version has no classifier."""
        if self.classifier is None:
            raise RuntimeError("this model version has no trained classification head")
        logits: torch.Tensor = self.classifier(self.fusion(local, global_))
        return logits

    @torch.inference_mode()
    def predict_submap(self, local: torch.Tensor, global_: torch.Tensor) -> SubmapPrediction | None:
        """The most probable submap of one frame, or None without a classifier."""
        if self.classifier is None:
            return None
        probabilities = self.classify(local, global_).softmax(-1)[0]
        best = int(probabilities.argmax())
        return SubmapPrediction(self.class_labels[best], float(probabilities[best]))

    def save(self, path: Path) -> None:
        """Write tensors, config and labels to one file (atomically, via a temporary name)."""
        payload: dict[str, Any] = {
            "config": asdict(self.config),
            "class_labels": self.class_labels,
            "state_dict": self.state_dict(),
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save(payload, tmp)
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> LoopNetHeads:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        heads = cls(HeadsConfig(**payload["config"]), payload["class_labels"])
        heads.load_state_dict(payload["state_dict"])
        return heads.eval()
