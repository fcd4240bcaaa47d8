"""Reading the served rows of a ``loopnet eval`` report: which rows, and which queries each
closed a loop for, the way the offline screening scripts of issue 25 read them
(``decision_headroom.py``, ``off_map_guard.py``, ``off_route_dataset.py``,
``next_frame_confirmation.py``). Nothing here is a service path.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def served_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """The report's served rows (``loopnet-<extractor>-served`` and its ``+seqL``)."""
    rows = [m for m in report["methods"] if "-served" in m["name"]]
    if not rows:
        raise SystemExit("no served row in the report (run loopnet eval without --no-served)")
    return rows


def robot_row(report: dict[str, Any]) -> dict[str, Any]:
    """The served row with sequences (a robot observing: ``-served+seq``)."""
    for method in report["methods"]:
        if "-served+seq" in method["name"] and method["details"].get("per_query_sequence_z"):
            return method  # type: ignore[no-any-return]
    raise SystemExit("no served sequence row with per_query_sequence_z in the report")


def loop_frames(details: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Per query: whether it was answered ``loop`` and the reference of its loop (the
    sequence's place when the sequence passed, else the served match; -1 for no loop)."""
    sequences = np.array(details["per_query_sequence"], float)
    loop = np.array([s == "loop" for s in details["per_query_status"]])
    frames = np.full(len(loop), -1, np.int64)
    for i in np.flatnonzero(loop):
        if sequences[i, 3] == 1:
            frames[i] = int(sequences[i, 0])
        elif details["per_query_candidates"][i]:
            frames[i] = int(details["per_query_candidates"][i][0][0])
    return loop, frames


def sequence_loops(details: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The queries answered ``loop`` by a passed sequence (indices, in order), and every
    query's rightness as the report scored it."""
    sequences = np.array(details["per_query_sequence"], float)
    loop, _ = loop_frames(details)
    return np.flatnonzero(loop & (sequences[:, 3] == 1)), np.array(details["per_query_right"], bool)
