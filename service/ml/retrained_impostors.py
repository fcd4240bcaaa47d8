"""The impostor model of a retrained model version: what its calibrated score means.

Trained heads change what a cosine means, so a retrained version refits the impostor model of
the calibration it keeps, the way the calibration fitted it (:meth:`Calibration.fit`): pairs
of frames held out of a probe whitening with frames it saw, as a query meets stored frames,
both embedded by the new heads. In-sample pairs of the atlas's own frames look more orthogonal
than any query's: a wrong match scored 12.3 after map-only retraining on cohog200, 2.95 before
(benchmarks/RESULTS.md, "Retraining that does not forget").

Heads that were themselves fitted on the atlas's frames (an adaptation's learned whitening
decorrelates them) would make the probe's held-out frames in-sample again; such a version
passes ``refit``: heads fitted the same way without the probe's held-out frames, nor the
training pairs that hold one of them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.ml.calibration import Calibration, CalibrationInputs
from service.ml.calibration_config import ImpostorProbe
from service.ml.heads import LoopNetHeads
from service.ml.impostors import ImpostorModel, pair_cosines
from service.ml.pipeline import embed_vectors

# heads refitted for a probe, given the frame ids of the probe's rows
ProbeRefit = Callable[[ImpostorProbe, np.ndarray], LoopNetHeads]


def retrained_impostor_model(
    heads: LoopNetHeads,
    calibration: Calibration,
    inputs: CalibrationInputs,
    refit: ProbeRefit | None = None,
) -> ImpostorModel:
    """The impostor model of ``heads`` over ``calibration``'s branches, fitted on the atlas's
    stored features ``inputs`` through the calibration's impostor probe; ``refit``: the heads
    to probe with, fitted without the probe's held-out frames (None: ``heads``)."""
    probe = calibration.impostor_probe(inputs)
    probe_heads = (
        heads if refit is None or probe.in_sample else refit(probe, np.asarray(inputs.order))
    )
    embeddings = embed_vectors(probe_heads, probe.local_branch, probe.global_branch)
    return ImpostorModel.fit(pair_cosines(embeddings, probe.first, probe.second))
