"""The state of one ``loopnet eval`` run: the data it evaluates and what its steps fill in
(rows, stage timings, what was skipped and why, the extractor passes)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.evaluation import report as reporting
from service.evaluation.calibrated_pass import CalibratedBranches
from service.evaluation.datasets import Dataset
from service.evaluation.eval_config import EvalConfig
from service.evaluation.protocol import MethodResult
from service.evaluation.report_context import report_of
from service.evaluation.retraining_pass import RetrainingRow
from service.evaluation.service_pass import PassResult
from service.evaluation.verification_pass import KeypointCache


@dataclass
class LoadedData:
    """The dataset a run evaluates, after its slice, stride and unreadable images."""

    dataset: Dataset
    submap_of: list[int]
    submap_note: str
    unreadable: dict[Path, str]
    output: Path
    cache_dir: Path


@dataclass
class EvalRun:
    """What the steps of a run fill in: rows, stage timings, what was skipped and why, the
    extractor passes and what the later rows start from."""

    config: EvalConfig
    data: LoadedData
    methods: list[MethodResult] = field(default_factory=list)
    global_only: list[MethodResult] = field(default_factory=list)
    stages: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    passes: list[PassResult] = field(default_factory=list)
    first_keypoints: KeypointCache | None = None
    calibrated_vectors: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    calibrated_branches: dict[str, CalibratedBranches] = field(default_factory=dict)
    retraining: list[RetrainingRow] = field(default_factory=list)
    observed_pairs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def first_pass(self) -> PassResult:
        """The first extractor's pass: the "LoopNet" rows and every later step start from it."""
        return self.passes[0]

    def report(self, partial: str | None) -> dict[str, Any]:
        data = self.data
        report = report_of(
            self.config,
            data.dataset,
            data.submap_note,
            self.first_pass,
            self.methods + self.global_only,
            self.stages,
            self.skipped,
            self.retraining,
            data.unreadable,
            partial,
        )
        report["observed_pairs"] = self.observed_pairs
        return report

    def checkpoint(self, next_step: str) -> None:
        """Write the rows done so far (no plots): a run stopped later keeps them."""
        if self.passes:
            report = self.report(f"stopped before {next_step}")
            output = self.data.output
            reporting.write_json(report, output / "report.json")
            reporting.write_markdown(report, self.methods + self.global_only, output / "report.md")
