"""How far the served decision could go on a development set, from ``loopnet eval`` reports:
what bounds each served row's R@100%P, and what *loop tracking* would add to a robot's row.

    python benchmarks/decision_headroom.py /work/runs/n0/report.json --tolerance 1 \\
        --margins 2,2.5,3,3.5 --out benchmarks/results/issue25/stop41_headroom_nordland.json

1. **The closable ceiling.** A served sweep moves only the answers the service could close
   (a verified match no less rare than the atlas's impostors, or a passed sequence). Right
   answers outside that set can never count, so ``closable and right / queries`` bounds
   R@100%P whatever the probability's order. Printed for every served row, with the
   inliers of the right answers left out (below the fitted minimum or not).
2. **Loop tracking, offline.** A robot's row (``observe``): after a loop, a sequence whose
   place continues the previous loop's along its trajectory (``step`` frames on) is accepted
   from a lower margin. ``--dropout G`` continues the newest loop up to G frames back (a
   track lost for a frame or two, ``G x step`` frames on). Counted per half of the queries
   (route order) with the loops it adds and how many are false. Choose on the FIRST half,
   read the second as held out. Reports from stop 43 on carry each answer's ``aligned_z``, and
   an answer whose newest frame fails ``NEWEST_Z_MIN`` is not counted; on older reports the
   added loops are an upper bound. Needs frame-aligned ground truth (query i right on
   references i +- ``tolerance``).
3. **What sets the sequence margin.** The wrong sequence answers' margins by how far their
   place lies from the right one (just outside the tolerance, a few frames off, far): the
   largest wrong margin is what ``LOOPNET_SEQUENCE_MARGIN_MIN`` must stay above. Frame-aligned
   ground truth again.
4. **Continued loops in a replay** (``--online OUT/online.json`` from ``loopnet eval-online``):
   every loop whose previous frame closed one too, by its step along the route and whether its
   sequence margin was below the cross-run margin the replay ran with (``--cross-run-margin``,
   default the setting's: only tracking could close it), right or false.
5. **The recent frames' own evidence** (``--recent-z``): for guards "the mean ``aligned_z`` of
   the sequence's last k frames is at least t", the loops closed by a passed sequence that each
   would refuse, right and false (rightness as the report scored the answer, so any layout).
   Offline: a refused loop would also stop the tracking that follows it, which is not counted.
6. **Why right sequence answers were not loops** (reports with ``per_query_sequence_z``): each
   right sequence answer of a robot's row that did not close a loop, by the first condition it
   failed: the newest frame's own evidence (``NEWEST_Z_MIN``), a margin below the tracking
   margin, a margin below the cross-run margin where only tracking could have lowered it (no
   loop in the last ``TRACKING_DROPOUT`` frames, or not its continuation), too few frames, or
   none of these (the decision held it back). Frame-aligned ground truth.
7. **Places running ahead of the robot** (``--run-ahead``): the loops closed by a passed
   sequence whose place lies further past a loop of the previous ``TRACKING_DROPOUT`` queries
   than the fastest speed carries a robot, plus ``RUN_AHEAD_SLACK`` (the service's rule since
   stop 44; run it on reports made before it), right and false as the report scored them.
   References in route order (one trajectory). With ``--recent-z``, part 5 also gives guards
   relative to the sequence's own level: the last k frames' mean ``aligned_z`` as a share of
   the median of the frames before them, and the last k frames all below t.

Nothing here is a service path: it is the record of what a change could buy before building it.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from served_report import loop_frames, sequence_loops, served_rows  # a sibling script

from service.app import sequence_rules
from service.app.sequence_rules import TrackedLoop
from service.config_sections import SequenceSettings
from service.evaluation.served_pass import PARTS
from service.ml.sequences import SequenceSettings as SequenceModel
from service.ml.sequences import Trajectories
from service.ml.sequences.distinctiveness import NEWEST_Z_MIN, TRACKING_DROPOUT, TRACKING_STEP


@dataclass(frozen=True)
class Ceiling:
    row: str
    queries: int
    right: int
    closable_right: int
    closable_wrong: int
    ceiling: float
    # median inliers of the right answers the service could not close
    unclosable_inliers_median: float


@dataclass(frozen=True)
class Tracking:
    margin: float
    half: str
    added: int
    false: int
    false_examples: list[tuple[int, int, float]]  # (query, reference, margin)


def ceiling(row: dict[str, Any]) -> Ceiling:
    """The closable ceiling of one served row."""
    details = row["details"]
    right = np.array(details["per_query_right"], bool)
    closable = np.array(details["per_query_closable"], bool)
    parts = np.array(details["per_query_parts"], float)
    inliers = np.expm1(parts[:, PARTS.index("inliers")])  # the part is log(1 + inliers)
    left_out = inliers[right & ~closable]
    left_out = left_out[~np.isnan(left_out)]
    return Ceiling(
        row=row["name"],
        queries=len(right),
        right=int(right.sum()),
        closable_right=int((right & closable).sum()),
        closable_wrong=int((~right & closable).sum()),
        ceiling=round(float((right & closable).mean()), 3),
        unclosable_inliers_median=round(float(np.median(left_out)), 1)
        if len(left_out)
        else math.nan,
    )


def tracking(
    details: dict[str, Any],
    margin: float,
    tolerance: int,
    steps: tuple[int, int],
    required: int,
    dropout: int = 1,
) -> list[Tracking]:
    """The loops tracking at ``margin`` adds, per half, and the false ones among them. The loop
    continued is the newest within ``dropout`` frames back (1: the previous frame's only), and
    ``steps`` scale with how far back it lies (a frame along the route per frame driven)."""
    sequences = np.array(details["per_query_sequence"], float)
    evidence = details.get("per_query_sequence_z") or []
    loop, frames = loop_frames(details)
    n = len(loop)
    added: list[tuple[int, int, float, bool]] = []
    for i in range(1, n):
        if loop[i] or np.isnan(sequences[i, 0]):
            continue
        if evidence and evidence[i] and evidence[i][-1] < NEWEST_Z_MIN:
            continue  # the newest-frame guard holds it back whatever the margin
        back = [g for g in range(1, min(dropout, i) + 1) if loop[i - g]]
        if not back:
            continue
        g = back[0]
        reference, seq_margin, length = int(sequences[i, 0]), sequences[i, 1], sequences[i, 2]
        step = reference - frames[i - g]
        if g * steps[0] <= step <= g * steps[1] and seq_margin >= margin and length >= required:
            loop[i], frames[i] = True, reference  # tracked: the next frame may continue it
            added.append((i, reference, float(seq_margin), abs(reference - i) > tolerance))
    out = []
    for half, (lo, hi) in {"first": (0, n // 2), "second": (n // 2, n)}.items():
        mine = [a for a in added if lo <= a[0] < hi]
        false = [(q, r, round(m, 2)) for q, r, m, wrong in mine if wrong]
        out.append(Tracking(margin, half, len(mine), len(false), false[:5]))
    return out


@dataclass(frozen=True)
class RecentGuard:
    frames: int  # the sequence's last k frames
    z_min: float  # their mean aligned_z at least this
    refused_right: int
    refused_false: int


def recent_guards(details: dict[str, Any], thresholds: list[float]) -> list[RecentGuard]:
    """What each guard on the mean ``aligned_z`` of the last 1-5 frames would refuse among the
    loops a passed sequence closed."""
    by_sequence, right = sequence_loops(details)
    evidence = details["per_query_sequence_z"]
    out = []
    for k in range(1, 6):
        recent = np.array([np.mean(evidence[i][-k:]) for i in by_sequence])
        for t in thresholds:
            refused = by_sequence[recent < t]
            wrong = int((~right[refused]).sum())
            out.append(RecentGuard(k, t, len(refused) - wrong, wrong))
    return out


def relative_guards(details: dict[str, Any], shares: list[float], levels: list[float]) -> list[str]:
    """Part 5's guards against the sequence's own level: per k, the loops a passed sequence
    closed that "last k frames' mean aligned_z below a share of the median before them" and
    "last k frames all below t" would refuse, as lines (right, false)."""
    closed, right = sequence_loops(details)
    evidence = details["per_query_sequence_z"]
    by_sequence = [i for i in closed if len(evidence[i]) > 3]
    lines = []
    for k in (1, 2, 3):
        z = [np.asarray(evidence[i], float) for i in by_sequence]
        share = np.array([z_[-k:].mean() / max(np.median(z_[:-k]), 1e-3) for z_ in z])
        weakest = np.array([z_[-k:].max() for z_ in z])
        for name, values, cuts in (
            ("share of the level", share, shares),
            ("all below", weakest, levels),
        ):
            for t in cuts:
                refused = np.array(by_sequence, np.int64)[values < t]
                wrong = int((~right[refused]).sum())
                lines.append(f"last {k}, {name} {t}: {len(refused) - wrong} right, {wrong} false")
    return lines


def ran_ahead(details: dict[str, Any]) -> tuple[int, int, list[int]]:
    """Part 7: (right, false, the false ones' queries) among the loops closed by a passed
    sequence whose place runs ahead of a loop of the previous TRACKING_DROPOUT queries, by the
    service's own rule (:func:`service.app.sequence_rules.ran_ahead`)."""
    closed, right = sequence_loops(details)
    loop, frames = loop_frames(details)
    route = Trajectories.single(int(max(frames.max(), 0)) + 1)
    model = SequenceModel()
    refused = []
    for i in (int(q) for q in closed):
        recent = [
            TrackedLoop(int(frames[i - g]), g)
            for g in range(1, min(TRACKING_DROPOUT, i) + 1)
            if loop[i - g]
        ]
        if sequence_rules.ran_ahead(route, int(frames[i]), recent, model) is not None:
            refused.append(i)
    wrong = [i for i in refused if not right[i]]
    return len(refused) - len(wrong), len(wrong), wrong


TRACKING_MARGIN = SequenceSettings.model_fields["sequence_margin_min_tracking"].default


def unclosed_right(
    details: dict[str, Any], tolerance: int, cross_run_margin: float, required: int
) -> dict[str, int]:
    """``condition -> right sequence answers held back by it first`` (part 6)."""
    sequences = np.array(details["per_query_sequence"], float)
    evidence = details["per_query_sequence_z"]
    loop, _ = loop_frames(details)
    right = np.abs(sequences[:, 0] - np.arange(len(loop))) <= tolerance
    counts: dict[str, int] = {}
    for i in np.flatnonzero(right & ~loop):
        margin, length = sequences[i, 1], sequences[i, 2]
        if evidence[i] and evidence[i][-1] < NEWEST_Z_MIN:
            why = f"this frame's own evidence below {NEWEST_Z_MIN:g}"
        elif margin < TRACKING_MARGIN:
            why = f"margin below the tracking margin {TRACKING_MARGIN:g}"
        elif margin < cross_run_margin:
            why = f"margin below {cross_run_margin:g}, not continuing a loop"
        elif length < required:
            why = f"fewer than {required} frames aligned"
        else:
            why = "the sequence passed; the decision held it back"
        counts[why] = counts.get(why, 0) + 1
    return dict(sorted(counts.items(), key=lambda item: -item[1]))


@dataclass(frozen=True)
class WrongMargins:
    offsets: str  # how far the wrong answers' places lie from the query's frame
    answers: int
    top: list[float]  # the largest margins, largest first


# bands of |reference - query| beyond the tolerance: just outside it, a few frames, far
OFFSET_BANDS = ((1, 2), (3, 9), (10, None))


def wrong_margins(details: dict[str, Any], tolerance: int) -> list[WrongMargins]:
    """The margins of the sequence answers whose place is wrong, per band of how far off it
    lies (the band's bounds count frames past the tolerance)."""
    sequences = np.array(details["per_query_sequence"], float)
    held = ~np.isnan(sequences[:, 0])
    off = np.abs(sequences[:, 0] - np.arange(len(sequences))) - tolerance
    out = []
    for lo, hi in OFFSET_BANDS:
        band = held & (off >= lo) & (off <= (np.inf if hi is None else hi))
        top = np.sort(sequences[band, 1])[::-1][:5]
        near = tolerance + lo, "" if hi is None else tolerance + hi
        out.append(
            WrongMargins(f"{near[0]}-{near[1]} frames", int(band.sum()), top.round(2).tolist())
        )
    return out


def continued_loops(replay: dict[str, Any], cross_run_margin: float) -> dict[str, int]:
    """``"step S, margin below M|M or more, right|false" -> loops`` of one served replay row
    of ``eval-online``'s online.json (its ``per_frame`` answers), M the cross-run margin."""
    frames = replay["per_frame"]
    status, reference, right = frames["status"], frames["reference"], frames["right"]
    margins = np.array(frames["parts"], float)[:, PARTS.index("sequence")]
    counts: dict[str, int] = {}
    for i in range(1, len(status)):
        if status[i] != "loop" or status[i - 1] != "loop":
            continue
        below = f"below {cross_run_margin:g}"
        if margins[i] >= cross_run_margin:
            below = f"{cross_run_margin:g} or more"
        key = f"step {reference[i] - reference[i - 1]}, margin {below}, "
        key += "right" if right[i] else "false"
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reports", nargs="*", type=Path)
    parser.add_argument("--online", type=Path, help="an eval-online online.json: part 4 only")
    parser.add_argument("--tolerance", type=int, help="frames either side (reports only)")
    parser.add_argument("--margins", default="2,2.5,3,3.5")
    parser.add_argument(
        "--steps",
        default=f"{TRACKING_STEP},{TRACKING_STEP}",
        help="continuation window along the route (default: the service's step)",
    )
    parser.add_argument(
        "--cross-run-margin",
        type=float,
        default=SequenceSettings.model_fields["sequence_margin_min"].default,
        help="the LOOPNET_SEQUENCE_MARGIN_MIN the replay ran with (--online)",
    )
    parser.add_argument("--required", type=int, default=3, help="aligned frames at least")
    parser.add_argument(
        "--dropout",
        type=int,
        default=1,
        help="continue the newest loop up to this many frames back (1: the previous frame's)",
    )
    parser.add_argument(
        "--recent-z",
        help="part 5: comma-separated thresholds of the last frames' mean aligned_z",
    )
    parser.add_argument("--run-ahead", action="store_true", help="part 7")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.reports and args.tolerance is None:
        parser.error("--tolerance is needed to read loopnet eval reports")
    lo, hi = (int(v) for v in args.steps.split(","))
    record: dict[str, Any] = {}
    if args.online:
        for replay in json.loads(args.online.read_text())["rows"]:
            if replay.get("per_frame"):
                counts = continued_loops(replay, args.cross_run_margin)
                record[f"{args.online}:{replay['method']}"] = counts
                print(f"== {replay['method']}: loops continuing the previous frame's loop")
                for key, count in counts.items():
                    print(f"    {key}: {count}")
    for path in args.reports:
        report = json.loads(path.read_text())
        entry: dict[str, Any] = {"ceilings": [], "tracking": [], "wrong_margins": []}
        print(f"== {path}")
        for row in served_rows(report):
            c = ceiling(row)
            entry["ceilings"].append(asdict(c))
            print(
                f"{c.row}: right {c.right}/{c.queries}, closable right {c.closable_right} "
                f"(ceiling of R@100%P {c.ceiling}), closable wrong {c.closable_wrong}, "
                f"unclosable right answers' inliers median {c.unclosable_inliers_median}"
            )
            details = row["details"]
            sequences = details.get("per_query_sequence") or []
            if not any(not math.isnan(s[0]) for s in sequences):
                continue
            loops = sum(s == "loop" for s in details["per_query_status"])
            print(
                f"  loop tracking (steps {lo}..{hi}, loops up to {args.dropout} frames back) "
                f"on {loops} loops at the defaults:"
            )
            for margin in (float(m) for m in args.margins.split(",")):
                for t in tracking(
                    details, margin, args.tolerance, (lo, hi), args.required, args.dropout
                ):
                    entry["tracking"].append(asdict(t))
                    print(
                        f"    margin >= {margin}, {t.half} half: +{t.added} loops, {t.false} "
                        f"false {t.false_examples}"
                    )
            if args.recent_z and details.get("per_query_sequence_z"):
                thresholds = [float(t) for t in args.recent_z.split(",")]
                print("  guards on the last k frames' mean aligned_z (loops refused):")
                for g in recent_guards(details, thresholds):
                    entry.setdefault("recent_guards", []).append(asdict(g))
                    print(
                        f"    last {g.frames}, mean >= {g.z_min}: {g.refused_right} right, "
                        f"{g.refused_false} false"
                    )
                print("  guards against the sequence's own level (loops refused):")
                for line in relative_guards(details, [0.2, 0.25, 0.3], [1.5, 2.0, 2.5]):
                    entry.setdefault("relative_guards", []).append(line)
                    print(f"    {line}")
            if args.run_ahead:
                kept_right, kept_false, examples = ran_ahead(details)
                entry["run_ahead"] = [kept_right, kept_false, examples]
                print(
                    f"  places running ahead of a recent loop: {kept_right} right, "
                    f"{kept_false} false {examples}"
                )
            if details.get("per_query_sequence_z"):
                held = unclosed_right(details, args.tolerance, args.cross_run_margin, args.required)
                entry["unclosed_right"] = held
                print(f"  right sequence answers not closed ({sum(held.values())}), first held by:")
                for why, count in held.items():
                    print(f"    {why}: {count}")
            print("  wrong sequence answers' margins, by how far off their place lies:")
            for w in wrong_margins(details, args.tolerance):
                entry["wrong_margins"].append(asdict(w))
                print(f"    {w.offsets}: {w.answers} answers, largest margins {w.top}")
        record[str(path)] = entry
    if args.out:
        args.out.write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
