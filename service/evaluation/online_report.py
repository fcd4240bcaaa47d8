"""``online.json`` and ``online.md`` of ``loopnet eval-online``: one table of every row's PR
sweep (the retrieval rows over the cosine or sequence margin, the served rows over
``loop_probability``), the served rows' operating point at the defaults, and the jobs (the
milestone calibrations) run during each served replay."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def write_report(report: dict[str, Any], output: Path) -> None:
    """Write the report's JSON and its Markdown tables into ``output`` (created)."""
    output.mkdir(parents=True, exist_ok=True)
    (output / "online.json").write_text(json.dumps(report, indent=2, default=str))
    lines = [
        f"# Online single-trajectory replay: {report['trajectory']}",
        "",
        f"Command: `{report['command']}`",
        "",
        f"- Ground truth: {report['ground_truth']}",
        f"- Features: {report['features']}",
        "",
        "| method | L | consistency k | swept over | best match right | AUC-PR | R@100%P "
        "| latency median ms | p95 ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in report["rows"]:
        swept = "cosine" if row["settings"]["length"] == 1 else "margin"
        for score, decisions in (row.get("sweeps") or {swept: row["decisions"]}).items():
            for decision in decisions.values():
                lines.append(
                    f"| {row['method']} | {row['settings']['length']} | "
                    f"{decision['consistency_required']} | {score} | "
                    f"{decision['best_match_right']:.3f} | "
                    f"{decision['auc_pr']:.3f} | {decision['recall_at_100_precision']:.3f} | "
                    f"{row['latency_ms']['median']:.2f} | {row['latency_ms']['p95']:.2f} |"
                )
    served = [row for row in report["rows"] if "operating_point" in row]
    if served:
        lines += _operating_points(served)
        lines += _jobs(served)
    (output / "online.md").write_text("\n".join(lines) + "\n")


def _operating_points(rows: list[dict[str, Any]]) -> list[str]:
    lines = _section(
        "At the service's defaults (status `loop`)",
        "method | L | threshold | loops | precision | recall | false loops | per 1,000 frames "
        "| right answers called new_place",
    )
    for row in rows:
        point = row["operating_point"]
        lines.append(
            f"| {row['method']} | {row['settings']['length']} | {point['threshold']:g} | "
            f"{point['loops']} | {point['precision']:.3f} | {point['recall']:.3f} | "
            f"{point['false_loops']} | {point['false_loops_per_1000']:.2f} | "
            f"{point['right_called_new_place']} |"
        )
    return lines


def _jobs(rows: list[dict[str, Any]]) -> list[str]:
    lines = _section(
        "Jobs run during the served replays",
        "method | L | job | milestone | after frame | status | version | frames fitted "
        "| min inliers | seconds | message",
        "A frame whose insert reached a calibration milestone (a calibrate job) or whose "
        "observation brought the atlas's new revisit pairs to the setting's number (an adapt "
        "job: LOOPNET_ADAPT_AFTER_PAIRS, or N in rows `-adaptN`) queued the job; it ran before "
        "the next frame, which the new model version answered.",
    )
    for row in rows:
        for job in row["jobs"]:
            lines.append(
                f"| {row['method']} | {row['settings']['length']} | {job['kind']} | "
                f"{job['milestone']} | {job['frame']} | {job['status']} | "
                f"{job['model_version']} | {job['frames_at_fit']} | {job['min_inliers']} | "
                f"{job['seconds']:.1f} | {job['message']} |"
            )
        if not row["jobs"]:
            lines.append(
                f"| {row['method']} | {row['settings']['length']} | none | | | | | | | | |"
            )
    return lines


def _section(title: str, columns: str, note: str = "") -> list[str]:
    """A Markdown section's heading, optional note and table header (``a | b | c``)."""
    count = len(columns.split("|"))
    return [
        "",
        f"## {title}",
        "",
        *([note, ""] if note else []),
        f"| {columns} |",
        "|" + " --- |" * count,
    ]
