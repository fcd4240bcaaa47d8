"""Write a run's results: ``report.json`` (everything), ``report.md`` (the tables) and PNG plots
(precision-recall curves of all methods on one chart; a strip of example queries with their
best matches, framed green when right and red when wrong)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.evaluation.datasets import Dataset
from service.evaluation.protocol import RECALL_KS, MethodResult

PR_PLOT = "pr_curves.png"
EXAMPLES_PLOT = "examples.png"


def _fmt(value: float | None, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.{digits}f}"


def methods_table(methods: Sequence[MethodResult], tolerance: str) -> str:
    header = (
        f"| method | {' | '.join(f'R@{k}' for k in RECALL_KS)} | submap acc | frame acc "
        "| AUC-PR | R@100%P | threshold@100%P | ms/query median | ms/query p95 |"
    )
    lines = [header, "|" + " --- |" * (len(RECALL_KS) + 8)]
    for m in methods:
        lines.append(
            f"| {m.label} | "
            + " | ".join(_fmt(m.recall[k]) for k in RECALL_KS)
            + f" | {_fmt(m.submap_accuracy)} | {_fmt(m.frame_accuracy)} | {_fmt(m.auc_pr)} "
            f"| {_fmt(m.recall_at_full_precision)} | {_fmt(m.threshold_at_full_precision)} "
            f"| {_fmt(m.query_ms.get('median'), 1)} | {_fmt(m.query_ms.get('p95'), 1)} |"
        )
    lines.append("")
    lines.append(f"Tolerance: {tolerance}. Frame accuracy is Recall@1.")
    alone = [
        f"{m.label} {_fmt(m.details['recall_at_100_precision_probability_alone'])}"
        for m in methods
        if "recall_at_100_precision_probability_alone" in m.details
    ]
    if alone:
        lines.append(
            "Served rows sweep loop_probability over the answers the service could close "
            "(decision.closable: a verified match, no less rare than the atlas's impostors); "
            "over the probability alone, every answer swept, R@100%P is: " + "; ".join(alone) + "."
        )
    lines.extend(served_jobs_lines(methods))
    return "\n".join(lines)


def served_jobs_lines(methods: Sequence[MethodResult]) -> list[str]:
    """One line per served row whose observations queued jobs (automatic adaptation): each
    job, the query after which it ran, and what became of its version."""
    lines = []
    for m in methods:
        ran = m.details.get("jobs") or []
        if ran:
            jobs = "; ".join(
                f"{j['kind']} after query {j['frame']}: {j['status']}"
                + (f", {j['message']}" if j["message"] else "")
                for j in ran
            )
            lines.append(f"{m.label}: jobs its observations queued, each run at once: {jobs}.")
    return lines


def retraining_table(rows: Sequence[dict[str, Any]]) -> str:
    """Before -> after retraining, per protocol and K, on the same test queries."""
    lines = [
        "| protocol | K | train frames | test queries | R@1 | R@5 | submap acc (nearest frame) "
        "| submap acc (classifier) | AUC-PR | R@100%P | top-1 cosine right / wrong (median) "
        "| train s | epochs (best) | gate: held-out acc, mAP | served R@1 |",
        "|" + " --- |" * 15,
    ]

    def arrow(key: str, row: dict[str, Any]) -> str:
        before, after = row["before"][key], row["after"][key]
        shown = f"**{_fmt(after)}**" if after > before else _fmt(after)  # gains only in bold
        return f"{_fmt(before)} → {shown}"

    def shots(row: dict[str, Any]) -> str:
        used = row.get("shots_used", row["shots"])
        return str(row["shots"]) if used == row["shots"] else f"{used} (asked {row['shots']})"

    def spread(row: dict[str, Any]) -> str:
        cosine = (row.get("top1_spread") or {}).get("cosine") or {}
        right, wrong = cosine.get("right"), cosine.get("wrong")
        return " / ".join(_fmt(side["median"]) if side else "-" for side in (right, wrong))

    def epochs(row: dict[str, Any]) -> str:
        text = f"{row['epochs_run']} ({row['best_epoch']})"
        return text + ": starting heads" if row["best_epoch"] == 0 else text

    def gate(row: dict[str, Any]) -> str:
        found = row.get("gate") or {}
        if found.get("change") is None:
            return "-"
        verdict = "passes" if found["not_worse"] else "refuses"
        accuracy = f"{_fmt(found['active'])} → {_fmt(found['new'])}"
        if "map_active" in found:
            accuracy += f", mAP {_fmt(found['map_active'])} → {_fmt(found['map_new'])}"
        return f"{accuracy} ({found['frames']}): {verdict}"

    def served(row: dict[str, Any]) -> str:
        if "served_recall@1" not in row:
            return "-"
        return f"{_fmt(row['served_recall@1'])} ({row['served']})"

    for row in rows:
        lines.append(
            f"| {row['protocol']} | {shots(row)} | {row['train_frames']} "
            f"| {row['test_queries']} | {arrow('recall@1', row)} | {arrow('recall@5', row)} "
            f"| {arrow('submap_accuracy', row)} | {_fmt(row['classifier_submap_accuracy'])} "
            f"| {arrow('auc_pr', row)} | {arrow('recall_at_100_precision', row)} "
            f"| {spread(row)} | {_fmt(row['train_seconds'], 1)} | {epochs(row)} "
            f"| {gate(row)} | {served(row)} |"
        )
    lines += [
        "",
        "Before = the row the heads start from (the calibrated service row when the map could "
        "be calibrated, as a job starts from the latest calibration; else the uncalibrated "
        "one) on the same test queries; only gains are in bold; K is "
        "the map shots per submap actually used (a submap keeps one frame for validation); "
        "best epoch 0 means the job would ship its starting heads. `map`: K reference frames per "
        "submap train the heads (what a retraining job does). `revisit` (the paper's few-shot "
        "protocol): K reference frames and K query-condition frames per submap train the heads; "
        "those query frames are not test queries. Rankings are over reference frames only. "
        "Submap accuracy (classifier): the classification head's submap holds a right "
        "reference. Training uses the retraining job's default parameters. Gate: the job's "
        "not-worse check, the starting and the new heads' nearest-frame accuracy and mean average "
        "precision on held-out stretches of the map (frames); served R@1: the new version's "
        "when the gate passes it, else the starting row's.",
    ]
    return "\n".join(lines)


def observed_pairs_table(rows: Sequence[dict[str, Any]]) -> str:
    """The pairs protocol (``pairs_pass``): per K, what observe recorded, the adapt job's
    verdict, and the test queries as served before -> after (the served version in brackets)."""
    lines = [
        "| pairs from | K | observed (answers) | pairs recorded (right) | adapt job | test queries "
        "| R@1 before → after (served) | R@100%P before → after (served) "
        "| wrong-match score excess median before → after (served) "
        "| right-match score excess median before → after (served) "
        "| impostor pairs scoring ≥ 2 / ≥ 3 before → after |",
        "|" + " --- |" * 11,
    ]

    def arrow(key: str, row: dict[str, Any]) -> str:
        after = _fmt(row[f"{key}_after"]) if f"{key}_after" in row else "-"
        return f"{_fmt(row[f'{key}_before'])} → {after} ({_fmt(row[f'{key}_served'])})"

    for row in rows:
        statuses = ", ".join(f"{n} {status}" for status, n in sorted(row["statuses"].items()))
        job = row["job"]
        lines.append(
            f"| {row['protocol'].removeprefix('pairs-')} | {row['shots']} "
            f"| {row['observed']} ({statuses}) "
            f"| {row['pairs']} ({row['pairs_right']}{_by_source(row)}) "
            f"| {job['status']}: {job['message']} "
            f"| {row['test_queries']} | {arrow('recall@1', row)} "
            f"| {arrow('recall_at_100_precision', row)} | {arrow('wrong_score_median', row)} "
            f"| {arrow('right_score_median', row)} | {_honesty(row)} |"
        )
    lines += [
        "",
        "K query-condition frames per revisited submap are observed as served by a second "
        "robot asking about the map's frames; every verified closure observe recorded is a pair "
        "(right: its frame is a right reference by the ground truth); a real adapt job with its "
        "default parameters learns from them and its gate decides. Test queries = the other "
        "queries, over the map's frames. After = the job's version (measured even when the gate "
        "kept it back); served = the version the gate left active. Wrong- and right-match score "
        "excess: the decision's score part of wrong (right) best answers (calibrated score - "
        "log10 of the atlas's frames, clipped to [-4, 8]), median. Pairs from `labelled`: the frames are "
        "stored instead and each labelled as a pair with its partner reference (the revisit "
        "protocol as served). Pairs from `stream`: K is a percent; the first K % of the "
        "queries, in order, are observed as one robot's drive (its sequence on), every closure "
        "observe kept (verified, or a loop of its sequence) is a pair, and the test queries are "
        "the rest of the drive, places the job saw no pair of. Impostor pairs: every test "
        "query with every map frame of another place (at least the impostor model's gap, a "
        "twentieth of the map's frames and at least 5, from each right reference); the share "
        "scoring at least 2 "
        "(3) should be about 1 % (0.1 %) if the version's score means what it says "
        "(`service/evaluation/score_honesty.py`).",
    ]
    return "\n".join(lines)


def _honesty(row: dict[str, Any]) -> str:
    """ "1.2 % / 0.1 % → 0.8 % / 0.0 % (of 19,000)": the test queries' impostor pairs scoring
    at least 2 and 3, before and after; "-" without an impostor model."""

    def shares(side: str) -> str:
        at_2, at_3 = row.get(f"impostors_at_2_{side}"), row.get(f"impostors_at_3_{side}")
        if at_2 is None or at_3 is None:
            return "-"
        return f"{100 * at_2:.1f} % / {100 * at_3:.2f} %"

    pairs = row.get("impostors_impostor_pairs_before")
    count = f" (of {int(pairs):,})" if pairs is not None else ""
    return f"{shares('before')} → {shares('after')}{count}"


def _by_source(row: dict[str, Any]) -> str:
    """ "; 40 sequence" where some of a row's pairs were not from verified closures."""
    sources = row.get("pair_sources", {})
    others = [f"{n} {source}" for source, n in sorted(sources.items()) if source != "observe"]
    return "; " + ", ".join(others) if others else ""


def stages_table(stages: dict[str, dict[str, dict[str, float]]]) -> str:
    lines = ["| pass | stage | median ms | p95 ms | frames |", "| --- | --- | --- | --- | --- |"]
    for pass_name, by_stage in stages.items():
        for stage, s in by_stage.items():
            lines.append(
                f"| {pass_name} | {stage} | {_fmt(s['median'], 2)} | {_fmt(s['p95'], 2)} "
                f"| {s['n']} |"
            )
    return "\n".join(lines)


def write_markdown(report: dict[str, Any], methods: Sequence[MethodResult], path: Path) -> None:
    d = report["dataset"]
    target = report["target"]
    lines = [
        f"# LoopNet evaluation: {d['name']}",
        "",
        f"Command: `{report['command']}`",
        "",
        *(
            [f"**Partial report**: the run {report['partial']}.", ""]
            if report.get("partial")
            else []
        ),
        f"- Layout: {d['layout']} ({d['root']}); {d['references']} reference frames, "
        f"{d['queries']} queries ({d['answerable']} with a right reference).",
        f"- Ground truth: {d['ground_truth']}.",
        f"- Submaps: {report['protocol']['submaps']}; predicted submap = the best match's "
        "submap (untrained heads; the retrained rows also give the classifier's).",
        *(f"- Left out: {line}" for line in d["excluded"]),
        f"- Image sizes (decoded): {report['working_sizes']['decoded']}.",
        f"- Working sizes: {report['working_sizes']['note']}",
        f"- Models: {report['models']}",
        f"- Machine: {report['machine']['summary']}.",
        "",
        "## Methods",
        "",
        methods_table(methods, d["tolerance_text"]),
        "",
        "## Target: fused LoopNet ahead of the best baseline or single-branch ablation",
        "",
        f"{target['verdict']}",
        "",
        *(
            ["## Retraining (few-shot, heads only)", "", retraining_table(report["retraining"]), ""]
            if report.get("retraining")
            else []
        ),
        *(
            [
                "## Adaptation from revisit pairs, as served",
                "",
                observed_pairs_table(report["observed_pairs"]),
                "",
            ]
            if report.get("observed_pairs")
            else []
        ),
        "## Time per stage",
        "",
        stages_table(report["stages"]),
        "",
        report["timing_note"],
        "",
        f"![precision-recall]({PR_PLOT})",
        "",
        f"![examples]({EXAMPLES_PLOT})",
        "",
    ]
    path.write_text("\n".join(lines))


def plot_pr_curves(methods: Sequence[MethodResult], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    colours = plt.get_cmap("tab20")
    for i, m in enumerate(methods):
        recall, precision = m.pr_curve["recall"], m.pr_curve["precision"]
        style = "-" if m.kind != "baseline" else "--"
        width = 2.4 if m.kind == "loopnet" else 1.2
        ax.plot(
            [0.0, *recall],
            [precision[0] if precision else 1.0, *precision],
            style,
            linewidth=width,
            color=colours(i % 20),
            label=f"{m.label} (AUC {m.auc_pr:.2f})",
        )
    ax.set_xlabel("recall (share of answerable queries accepted and right)")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def example_queries(count: int, total: int) -> list[int]:
    """``count`` query indices spread evenly over the run (deterministic)."""
    if total == 0 or count <= 0:
        return []
    return sorted({int(i) for i in np.linspace(0, total - 1, min(count, total))})


def plot_examples(
    dataset: Dataset, method: MethodResult, path: Path, *, count: int = 6, top: int = 3
) -> list[dict[str, Any]]:
    """A strip per example query: the query, then its ``top`` best references (green right,
    red wrong). Returns what it drew, for report.json."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    chosen = example_queries(count, len(dataset.queries))
    if not chosen:
        return []
    fig, axes = plt.subplots(
        len(chosen), top + 1, figsize=(2.6 * (top + 1), 1.7 * len(chosen)), dpi=100, squeeze=False
    )
    drawn = []
    for row, q in enumerate(chosen):
        query = dataset.queries[q]
        panels = [(query.path, "query", "black")]
        matches = []
        for rank in range(min(top, method.ranking.indices.shape[1])):
            ref = int(method.ranking.indices[q, rank])
            if ref < 0:
                continue
            right = ref in query.positives
            score = float(method.ranking.scores[q, rank])
            matches.append({"reference": ref, "similarity": score, "right": right})
            panels.append(
                (
                    dataset.references[ref].path,
                    f"#{rank + 1} {score:.2f}",
                    "green" if right else "red",
                )
            )
        drawn.append({"query": q, "path": str(query.path), "matches": matches})
        for col, ax in enumerate(axes[row]):
            ax.set_xticks([])
            ax.set_yticks([])
            if col >= len(panels):
                ax.axis("off")
                continue
            image_path, caption, colour = panels[col]
            with Image.open(image_path) as image:
                ax.imshow(np.asarray(image.convert("RGB")))
            ax.set_title(caption, fontsize=8, color=colour)
            for spine in ax.spines.values():
                spine.set_edgecolor(colour)
                spine.set_linewidth(3 if col else 1)
    fig.suptitle(f"{dataset.name}: {method.label}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return drawn


def write_json(report: dict[str, Any], path: Path) -> None:
    def default(value: Any) -> Any:
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, Path):
            return str(value)
        raise TypeError(f"not JSON serialisable: {type(value).__name__}")

    path.write_text(json.dumps(report, indent=2, default=default, allow_nan=True))
