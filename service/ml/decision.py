"""The loop-closure decision: one probability of "same place" from the evidence a query has.

A SLAM back end that accepts one false loop bends its map, so the service thresholds one
number whose meaning it can state: ``loop_probability``, a logistic model over the evidence the
service already computes for the best candidate (after verification has re-ranked them):

- ``inliers``: its RANSAC inliers (log scale), the geometric evidence;
- ``inlier_ratio``: inliers / tentative matches;
- ``rival``: its inliers over those of the best verified candidate of another place (log
  ratio): a look-alike elsewhere that verifies as well means the geometry cannot tell them
  apart; on a calibrated version only when one of the two reaches the verification minimum
  (below it on both sides the inliers are noise);
- ``score``: its calibrated score minus ``log10(frames)`` (the best of N impostors is N times
  likelier to look this alike), only on a calibrated model version;
- ``sequence``: the robot's sequence margin over its best rival place, when a robot streams
  (for a match at the sequence's place; negated for a match elsewhere:
  :func:`service.app.decision.sequence_part`).

Each part enters centred, so a part the answer does not have (no calibration yet, no robot)
adds nothing and the others decide. The geometric and score coefficients are set by hand and
checked on halves of gardenspoint_cohog200 (DISK at 256 px, MNN; a logistic refit on the
first half did worse on the second); the sequence weight was chosen on the first half of a
nordland_64x32 slice (XFeat) and reported on the second (``benchmarks/served_halves.py``;
the numbers are in benchmarks/RESULTS.md, issue 25).

Agreement of consecutive answers (the robot's consistency) is applied after the probability,
by the status: a probable loop that its previous observations do not support yet is a
``candidate``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

# A loop is declared from this probability on: no false loop on the development halves
# (benchmarks/served_halves.py); LOOPNET_LOOP_PROBABILITY_MIN overrides it.
DEFAULT_LOOP_PROBABILITY = 0.98
# Below this the answer is a new place; between it and the loop threshold, a candidate.
CANDIDATE_PROBABILITY = 0.5
# Frames of one robot at most this many apart along its route are one stretch of it, the same
# place for the rival part; LOOPNET_RIVAL_GAP_FRAMES overrides it (service.app.decision).
# Larger gaps rank gardenspoint_cohog200's first half better as served (R@100%P 2 -> 0.46,
# 5 -> 0.52, 7 -> 0.55; benchmarks/served_settings.py) but give up the one thing a close rival
# tells: a match four frames off whose true neighbours verify as well. At 5 an adapted
# version closed such a loop (one false loop on each labelled protocol); 2 closed none.
DEFAULT_RIVAL_GAP = 2

# Logistic coefficients of each part (per unit of the part, after its centre is subtracted).
INTERCEPT = 0.0
COEFFICIENTS = {
    "inliers": 3.0,  # per e-fold of (1 + inliers)
    "inlier_ratio": 2.0,
    "rival": 4.0,  # per e-fold of (1 + inliers) / (1 + rival's inliers)
    "score": 1.0,  # per decade of rarity among impostors
    "sequence": 10.0,  # per standard deviation of sequence margin (chosen on the first half)
}
# Where each part is neutral (the logit's zero along that axis).
CENTRES = {
    "inliers": math.log1p(20.0),
    "inlier_ratio": 0.5,
    "rival": math.log(2.0),
    "score": 2.0,
    "sequence": 2.0,
}
CLIP = {"rival": (-2.0, 1.5), "score": (-4.0, 8.0), "sequence": (-4.0, 8.0)}


@dataclass(frozen=True)
class Evidence:
    """What the answer knows about its best candidate; None: that part is unavailable.

    Attributes:
        inliers: RANSAC inliers of the best candidate (None: verification off or not verified).
        inlier_ratio: its inliers / tentative matches.
        rival_inliers: most inliers of a verified candidate of another place, in the best's
            terms when the re-rank weighs zoom (service.app.decision; None: none was verified).
        score_excess: calibrated score minus log10 of the atlas's frames (None: uncalibrated).
        sequence_margin: the robot's sequence margin (None: no robot or no sequence).
        frames: frames in the atlas.
    """

    inliers: int | None = None
    inlier_ratio: float | None = None
    rival_inliers: float | None = None
    score_excess: float | None = None
    sequence_margin: float | None = None
    frames: int = 0

    def parts(self) -> dict[str, float]:
        """The model's inputs that are present, uncentred."""
        values: dict[str, float] = {}
        if self.inliers is not None:
            values["inliers"] = math.log1p(max(self.inliers, 0))
            values["inlier_ratio"] = float(self.inlier_ratio or 0.0)
            if self.rival_inliers is not None:
                values["rival"] = _clip(
                    "rival",
                    math.log1p(max(self.inliers, 0)) - math.log1p(max(self.rival_inliers, 0)),
                )
        if self.score_excess is not None:
            values["score"] = _clip("score", self.score_excess)
        if self.sequence_margin is not None:
            values["sequence"] = _clip("sequence", self.sequence_margin)
        return values


@dataclass(frozen=True)
class Decision:
    """The probability, what it was made of, and why it is low when it is.

    Attributes:
        loop_probability: P(same place) of the best candidate, in [0, 1]; None only with no
            candidate at all (``reason`` says so).
        threshold: the probability a loop needs.
        passed: ``loop_probability >= threshold`` and ``closable``.
        closable: the checks no probability threshold overrides pass (the match is verified,
            and on a calibrated atlas no less rare than the best of its impostors): some
            threshold would make it a loop. A sweep of the threshold, as served, moves only the
            closable answers.
        parts: each present part's value (log inliers, ratio, log inlier ratio over the rival,
            score excess, sequence margin).
        contributions: each present part's term in the logit (positive: for a loop).
        failed: the part that pulled the probability down most (None when it passed).
        reason: why the answer cannot be a loop or cannot decide well, in words; None when the
            evidence is complete and passed.
    """

    loop_probability: float | None
    threshold: float
    passed: bool
    closable: bool = False
    parts: dict[str, float] = field(default_factory=dict)
    contributions: dict[str, float] = field(default_factory=dict)
    failed: str | None = None
    reason: str | None = None


def logit(parts: dict[str, float]) -> float:
    """The model's logit of present (uncentred) parts; absent parts add nothing."""
    return INTERCEPT + sum(COEFFICIENTS[name] * (v - CENTRES[name]) for name, v in parts.items())


def probability(parts: dict[str, float]) -> float:
    z = logit(parts)
    return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0


def decide_loop(
    evidence: Evidence | None,
    *,
    threshold: float = DEFAULT_LOOP_PROBABILITY,
    verify: bool = True,
    min_inliers: int | None = None,
) -> Decision:
    """The decision over ``evidence`` (None: the answer has no candidate).

    With verification on, an unverified best candidate (fewer inliers than ``min_inliers``)
    never passes, whatever the probability: geometry is the one part a look-alike cannot fake.
    On a calibrated atlas a match whose score is below ``log10(frames)`` (no rarer than the
    best of the atlas's impostors) never passes either: on Nordland at 64x32 px, where RANSAC
    fits 70 inliers between look-alike frames, it was the only part that told them apart.
    """
    if evidence is None:
        return Decision(None, threshold, False, reason="the atlas has no frame to match")
    parts = evidence.parts()
    if "rival" in parts and not _either_verified(evidence, min_inliers):
        del parts["rival"]
    terms = {name: round(COEFFICIENTS[name] * (v - CENTRES[name]), 4) for name, v in parts.items()}
    p = probability(parts)
    reasons: list[str] = []
    if not verify:
        reasons.append("verification is off: no geometric evidence")
    elif evidence.inliers is None:
        reasons.append("no candidate was verified")
    elif min_inliers is not None and evidence.inliers < min_inliers:
        reasons.append(f"the match has {evidence.inliers} inliers, below {min_inliers}")
    if evidence.score_excess is None:
        reasons.append(
            f"the atlas ({evidence.frames} frames) is not calibrated yet: no score against "
            "impostors"
        )
    geometry_ok = (
        verify
        and evidence.inliers is not None
        and (min_inliers is None or evidence.inliers >= min_inliers)
    )
    # on a calibrated atlas the match must be at least as rare as the best of its N impostors
    rare = evidence.score_excess is None or evidence.score_excess >= 0.0
    if not rare:
        reasons.append(
            f"the match's score is below log10({evidence.frames}): the best of the atlas's "
            "impostors is as similar"
        )
    closable = geometry_ok and rare
    passed = closable and p >= threshold
    failed = None
    if not passed:
        negative = {name: t for name, t in terms.items() if t < 0}
        if not geometry_ok:
            failed = "inliers"
        elif not rare:
            failed = "score"
        elif negative:
            failed = min(negative, key=lambda name: negative[name])
        if p < threshold:
            reasons.insert(0, f"loop_probability {p:.3f} is below {threshold}")
    return Decision(
        round(p, 6),
        threshold,
        passed,
        closable,
        {name: round(v, 4) for name, v in parts.items()},
        terms,
        failed,
        "; ".join(reasons) if reasons else None,
    )


def _either_verified(evidence: Evidence, min_inliers: int | None) -> bool:
    """Whether the match or its rival reaches the verification minimum, on a calibrated
    version (whose minimum is fitted as the inliers the atlas's hard impostors reach): between
    two frames that both fail it (0 against 9 inliers across seasons at 64x32 px) the inliers
    are noise, and their ratio says nothing about which place is the right one. Before
    calibration the minimum is the matcher's default, not the atlas's noise level, and a small
    atlas's right answers verify below it (the README's ten frames: 28 to 42 inliers)."""
    if min_inliers is None or evidence.score_excess is None:
        return True
    return max(evidence.inliers or 0, evidence.rival_inliers or 0) >= min_inliers


def _clip(name: str, value: float) -> float:
    low, high = CLIP[name]
    return min(max(value, low), high)
