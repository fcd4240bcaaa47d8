"""How honest the active version's calibrated score is on the queries it actually meets.

A score of ``s`` says: one pair of frames of different places in ``10**s`` is this similar. The
impostor model behind it is fitted on the atlas's own frames (a probe of held-out frames
against seen ones); queries of another condition meet the map differently. Over every pair of
a test query and a map frame of another place, the share scoring at least 2 (at least 3)
should be about 1 % (0.1 %): more means the score calls impostors rarer than they are (a loop
decided on it is riskier than it says), less means it is cautious. "Another place" is the
impostor model's own rule: a map frame at least its gap (a twentieth of the map's frames, at
least 5) from every right reference along the map's route; a frame a few places off shows the
same scene, which the model never counted as an impostor, and an adapted version that learned
the scene across conditions rightly finds it close.
Comparing the shares of two versions tells which one's score means what it says, whatever
their medians did.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from service.app.catalog import AtlasService
from service.evaluation.served_pass import as_stored
from service.ml.features import FrameFeatures
from service.ml.impostors import MIN_GAP

LEVELS = (2.0, 3.0)


def impostor_exceedance(
    service: AtlasService,
    atlas_id: int,
    queries: Sequence[FrameFeatures],
    positives: Sequence[frozenset[int]],
    frame_to_reference: dict[int, int],
) -> dict[str, float]:
    """The impostor pairs' count and, per level of :data:`LEVELS`, the share of them scoring at
    least that level under the atlas's active version (empty when it has no impostor model).
    Map frames are the atlas's frames that are references (``frame_to_reference``, in route
    order as the map robot stored them)."""
    state = service.loaded(atlas_id)
    model = state.model
    if not model.scores or not queries:
        return {}
    ids = state.index.ids()
    references = np.array([frame_to_reference.get(int(i), -1) for i in ids], np.int64)
    kept = references >= 0
    map_vectors = state.index.vectors(ids[kept])
    references = references[kept]
    asked = np.stack([model.embed(replace(q, local=as_stored(q.local))) for q in queries])
    cosines = asked @ map_vectors.T
    gap = max(MIN_GAP, len(frame_to_reference) // 20)
    impostor = np.array([other_places(references, right, gap) for right in positives], bool)
    scores = model.score(cosines[impostor].astype(np.float64))
    if scores is None:
        return {}
    found: dict[str, float] = {"impostor_pairs": float(impostor.sum())}
    for level in LEVELS:
        found[f"at_{level:g}"] = float(np.mean(scores >= level)) if len(scores) else float("nan")
    return found


def other_places(references: np.ndarray, right: frozenset[int], gap: int) -> np.ndarray:
    """Per map frame (its reference index): whether it is at least ``gap`` places from every
    right reference, so an impostor by the impostor model's rule."""
    if not right:
        return np.ones(len(references), bool)
    nearest = np.min(np.abs(references[:, None] - np.array(sorted(right))[None, :]), axis=1)
    return np.asarray(nearest >= gap, bool)
