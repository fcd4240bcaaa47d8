"""Reading the served rows of a ``loopnet eval`` report: which rows, and which queries each
closed a loop for, the way the offline screening scripts of issue 25 read them
(``decision_headroom.py``, ``off_map_guard.py``, ``off_route_dataset.py``,
``next_frame_confirmation.py``). Nothing here is a service path.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.ml.sequences.distinctiveness import CONFIRM_Z


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


def newest_z(details: dict[str, Any]) -> np.ndarray:
    """Per query: the ``aligned_z`` of its sequence's newest frame (-inf without a sequence)."""
    return np.array([z[-1] if z else -np.inf for z in details["per_query_sequence_z"]], float)


def weak_passes(details: dict[str, Any]) -> np.ndarray:
    """Per query: its sequence passed while the newest frame's own evidence is below
    :data:`CONFIRM_Z`, the passes whose loops the service leaves pending from stop 46 on
    (unless consistent single frames answer them at once)."""
    passed = np.array(details["per_query_sequence"], float)[:, 3] == 1
    return passed & (newest_z(details) < CONFIRM_Z)
