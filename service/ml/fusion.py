"""The paper's fusion, written once: ``F = alpha * D + (1 - alpha) * R``.

Every embedding LoopNet serves is this weighted pair of branches, concatenated: the untrained
heads and calibrated atlases use ``[alpha D, (1 - alpha) R]`` itself (so the fused cosine weighs
the branches' cosines ``alpha^2 : (1 - alpha)^2``), trained heads multiply it by the stacked
projection ``[P_D  P_R]`` (which gives ``alpha P_D D + (1 - alpha) P_R R``).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

Branches = TypeVar("Branches", np.ndarray, torch.Tensor)


def weighted_branches(local: Branches, global_: Branches, alpha: float) -> Branches:
    """``[alpha * local, (1 - alpha) * global_]`` along the last axis (arrays or tensors)."""
    if isinstance(local, torch.Tensor):
        return torch.cat([alpha * local, (1.0 - alpha) * global_], dim=-1)
    return np.concatenate([alpha * local, (1.0 - alpha) * global_], axis=-1)
