"""A harness report's contents (:func:`report_of`): the run's settings and dataset, the rows,
the target's verdict, the machine, the sizes the images were worked at."""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from service.evaluation.datasets import Dataset
from service.evaluation.method_rows import EXTRACTOR_LABELS, UNCALIBRATED
from service.evaluation.protocol import MethodResult
from service.ml.presets import ModelPreset

if TYPE_CHECKING:
    from service.evaluation.eval_config import EvalConfig
    from service.evaluation.retraining_pass import RetrainingRow
    from service.evaluation.service_pass import PassResult

TARGET_MARGIN = 0.10


def target_verdict(methods: Sequence[MethodResult]) -> dict[str, Any]:
    # the calibrated row; today's uncalibrated one where no calibration could be fitted
    loopnet = next((m for m in methods if m.kind == "loopnet"), None) or next(
        m for m in methods if m.kind == UNCALIBRATED
    )
    rivals = [  # single frames against single frames: sequence rows compete among themselves
        m
        for m in methods
        if (m.kind == "baseline" or m.name.startswith("global-only") or "-local-only" in m.name)
        and "+seq" not in m.name
    ]
    if not rivals:
        return {"verdict": "no baseline or single-branch ablation ran", "met": None}
    best = max(rivals, key=lambda m: m.recall[1])
    margin = loopnet.recall[1] - best.recall[1]
    met = margin >= TARGET_MARGIN
    verdict = (
        f"{loopnet.label}: Recall@1 {loopnet.recall[1]:.3f}; best of the baselines and "
        f"single-branch ablations: {best.label} {best.recall[1]:.3f}; margin {margin:+.3f} "
        f"(target ≥ +{TARGET_MARGIN:.2f}): **{'met' if met else 'NOT met'}**."
    )
    return {
        "loopnet": loopnet.name,
        "best_rival": best.name,
        "margin_recall@1": margin,
        "met": met,
        "verdict": verdict,
    }


def machine_summary() -> dict[str, Any]:
    import kornia

    cpus = os.cpu_count()
    summary_text = (
        f"{platform.machine()} CPU, {cpus} cores visible, torch {torch.__version__} with "
        f"{torch.get_num_threads()} threads, kornia {kornia.__version__}, no GPU"
        if not torch.cuda.is_available()
        else f"{platform.machine()}, CUDA available (not used)"
    )
    return {
        "summary": summary_text,
        "platform": platform.platform(),
        "cpu_count": cpus,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": sys.version.split()[0],
    }


def working_sizes(
    sizes: Sequence[tuple[int, int]],
    preset: ModelPreset,
    baselines: Sequence[str],
) -> dict[str, Any]:
    distinct: dict[str, int] = {}
    for w, h in sizes:
        distinct[f"{w}x{h}"] = distinct.get(f"{w}x{h}", 0) + 1
    side = preset.local.long_side
    resized = []
    for size in sorted(distinct):
        w, h = (int(v) for v in size.split("x"))
        scale = side / max(w, h)
        direction = "upsampled" if scale > 1 else "downsampled" if scale < 1 else "kept"
        resized.append(f"{size} {direction} to {round(w * scale)}x{round(h * scale)}")
    parts = [
        f"local extractors at long side {side} ({'; '.join(resized)})",
        f"backbone at {preset.backbone.input_size}x{preset.backbone.input_size}",
    ]
    if "bow-orb" in baselines:
        parts.append(f"ORB at long side {side} (grey)")
    if "seqslam-sad" in baselines:
        parts.append("SeqSLAM thumbnails 64x32 (grey, 8-px patch-normalised)")
    return {
        "decoded": ", ".join(f"{k} ({v})" for k, v in sorted(distinct.items())),
        "local_long_side": side,
        "note": "; ".join(parts) + ".",
    }


def report_of(
    config: EvalConfig,
    dataset: Dataset,
    submap_note: str,
    first_pass: PassResult,
    methods: list[MethodResult],
    stages: dict[str, dict[str, dict[str, float]]],
    skipped: dict[str, str],
    retraining: list[RetrainingRow],
    unreadable: dict[Path, str],
    partial: str | None,
) -> dict[str, Any]:
    """The report of the rows done so far (``partial`` says what is still missing)."""
    answerable = sum(1 for q in dataset.queries if q.positives)
    tolerance_text = (
        f"±{dataset.tolerance} frames" if dataset.tolerance is not None else dataset.ground_truth
    )
    report: dict[str, Any] = {
        "command": config.command or "run_evaluation(...)",
        "partial": partial,
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        "dataset": {
            "name": dataset.name,
            "root": str(dataset.root),
            "layout": dataset.layout,
            "references": len(dataset.references),
            "queries": len(dataset.queries),
            "answerable": answerable,
            "ground_truth": dataset.ground_truth,
            "tolerance": dataset.tolerance,
            "tolerance_text": tolerance_text,
            "excluded": dataset.excluded,
            "unreadable_images": {str(path): why for path, why in unreadable.items()},
        },
        "protocol": {
            "submaps": submap_note,
            "submap_size": config.submap_size,
            "predicted_submap": "submap of the best matching frame (classifier untrained)",
            "recall_ks": [1, 5, 10],
        },
        "models": (
            f"local extractors {', '.join(EXTRACTOR_LABELS.get(e, e) for e in config.extractors if e not in skipped)} "
            f"(long side {first_pass.preset.local.long_side}, at most "
            f"{first_pass.preset.local.max_keypoints} keypoints, NMS {first_pass.preset.local.nms_window}); "
            f"global backbone {first_pass.preset.backbone.name} ImageNet "
            f"({first_pass.preset.backbone.pooling} pooling); LoopNet heads untrained "
            "(block-identity fusion)"
        ),
        "skipped": skipped,
        "working_sizes": working_sizes(first_pass.image_sizes, first_pass.preset, config.baselines),
        "machine": machine_summary(),
        "methods": [m.row() for m in methods],
        "stages": stages,
        "timing_note": (
            "Per-query time of LoopNet rows: decode + CNNs + heads + FAISS search, as the API "
            "spends it (HTTP excluded). Ablations: decode + the branch's CNNs + re-embedding and "
            "exact search. Baselines: decode + describe + scoring. "
            + (
                "CNN timings come from the run that filled the feature cache."
                if any(m.details.get("features_from_cache") for m in methods)
                else "All timings measured in this run."
            )
        ),
        "target": target_verdict(methods),
        "retraining": [row.row() for row in retraining],
    }
    return report
