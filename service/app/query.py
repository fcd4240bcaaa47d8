"""Queries and observations: one path per request.

Everything a request names (k, the atlas and its feature signature, the filter and its submap)
is checked once, in one session, before any CNN runs; after extraction one session resolves the
filter, searches and reads the candidates and their stored keypoints for verification.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from service.app.decision import (
    answer_evidence,
    has_verified_rival,
    probable_candidate,
    rival_reserve,
    verified_count,
)
from service.app.filters import QueryFilter, Selection, resolve
from service.app.ingest import FrameIngest
from service.app.observe import Observations, with_extraction_timings
from service.app.results import (
    Candidate,
    QueryResult,
    SubmapGuess,
    VerificationSummary,
    place_margin,
)
from service.app.robot_evidence import RobotContext, RobotEvidence, single_frame_verdict
from service.app.sequence_place import at_sequence_place, place_first, sequence_place
from service.app.sequences import SERVICE_SEQUENCE, SequenceScorer
from service.app.state import AtlasStates, LoadedAtlas
from service.app.stay import RobotFrames, frame_stay, stay_rule
from service.app.verify import CandidateVerification
from service.config import Settings
from service.errors import InvalidInput
from service.metrics import observe_stages
from service.ml.decision import decide_loop
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.geometry import Intrinsics
from service.ml.impostors import loop_score_threshold
from service.ml.sequences import PlaceStatus
from service.ml.thumbnails import make_thumbnail
from service.ml.verification import Verification, View, decide
from service.storage import repository as repo
from service.storage.feature_store import load_local_features
from service.storage.models import Atlas, Frame

# Frames searched per query beyond k, so the margin finds the best other place even when the
# top k all lie in the match's submap.
MARGIN_POOL = 32
SEQUENCE_MAX = 50  # longest sequence a request may ask for


@dataclass(frozen=True)
class Found:
    """What the search session read: candidates in similarity order and their frames."""

    candidates: list[Candidate]
    frames: dict[int, Frame]
    names: dict[int, str]
    stored: dict[int, LocalFeatures]  # keypoints of the candidates to verify
    reserve: Candidate | None  # verified too when no checked candidate is another place
    # the candidate at the place the robot's sequence names, when no checked candidate shows it
    # (verified too, and put first: :func:`place_first`); None: the sequence names none
    place: Candidate | None
    evidence: RobotEvidence | None  # the robot's sequence and previous observations
    proposals: list[int]  # the search's best frames: what this frame proposes to sequences
    stay_frames: int  # the robot's current stay, left out of the search


class AtlasQueries(Observations):
    """Query an atlas with an image or extracted features; observe (query, then insert: see
    :class:`~service.app.observe.Observations`)."""

    def __init__(
        self,
        settings: Settings,
        sessions: sessionmaker[Session],
        states: AtlasStates,
        ingest: FrameIngest,
        verification: CandidateVerification,
    ) -> None:
        self.settings = settings
        self.sessions = sessions
        self.states = states
        self.ingest = ingest
        self.verification = verification
        self.sequences = SequenceScorer(settings)

    def check_k(self, k: int) -> None:
        if not 1 <= k <= self.settings.max_k:
            raise InvalidInput(f"k must be between 1 and {self.settings.max_k}, got {k}")

    def robot_context(
        self, query_filter: QueryFilter, timestamp: float | None, sequence_length: int | None
    ) -> RobotContext | None:
        """The asking robot (the filter's) and its sequence length; None without a robot."""
        length = self.settings.sequence_length if sequence_length is None else sequence_length
        if not 0 <= length <= SEQUENCE_MAX:
            raise InvalidInput(
                f"sequence_length must be between 0 and {SEQUENCE_MAX}, got {length}"
            )
        if query_filter.robot_id is None:
            return None
        return RobotContext(query_filter.robot_id, timestamp, length)

    def _check_targets(
        self, session: Session, atlas_name: str, query_filter: QueryFilter, submap: str | None
    ) -> Atlas:
        """The atlas (signature checked), the filter's submap and the target submap exist."""
        atlas = self.ingest.checked_atlas(session, atlas_name)
        for name in {query_filter.submap, submap} - {None}:
            repo.get_submap(session, atlas=atlas, name=name)  # type: ignore[arg-type]
        return atlas

    def query(
        self,
        *,
        atlas_name: str,
        image_bytes: bytes,
        k: int,
        query_filter: QueryFilter,
        intrinsics: Intrinsics | None = None,
        sequence_length: int | None = None,
    ) -> QueryResult:
        """The frames of the atlas most similar to an image, verified, and the loop-closure
        decision. The filter's robot is the robot asking (its recent frames never match, and
        they form the query's sequence)."""
        total_start = time.perf_counter()
        self.check_k(k)
        robot = self.robot_context(query_filter, query_filter.timestamp, sequence_length)
        with self.sessions() as session:
            self._check_targets(session, atlas_name, query_filter, None)
        features, decode_ms, rgb = self.ingest.extract(image_bytes, thumbnail=False)
        result = self._search(atlas_name, features, k, query_filter, intrinsics, robot)
        if result.loop_closure:  # the console shows a recorded loop closure's query image
            features.thumbnail = make_thumbnail(rgb)
        return with_extraction_timings(result, features, decode_ms, total_start)

    def query_features(
        self,
        *,
        atlas_name: str,
        features: FrameFeatures,
        k: int,
        query_filter: QueryFilter,
        intrinsics: Intrinsics | None = None,
        sequence_length: int | None = None,
        timestamp: float | None = None,
    ) -> QueryResult:
        """Search with already extracted features and verify the best candidates; timings
        cover the heads, the search and the verification."""
        self.check_k(k)
        robot = self.robot_context(query_filter, timestamp, sequence_length)
        return self._search(atlas_name, features, k, query_filter, intrinsics, robot)

    def _search(
        self,
        atlas_name: str,
        features: FrameFeatures,
        k: int,
        query_filter: QueryFilter,
        intrinsics: Intrinsics | None,
        robot: RobotContext | None = None,
    ) -> QueryResult:
        with self.sessions() as session:
            atlas = self.ingest.checked_atlas(session, atlas_name)
            state = self.states.loaded(atlas.id)
            timings: dict[str, float] = {}
            start = time.perf_counter()
            model = state.model
            embedding, prediction = model.embed_and_predict(features)
            timings["heads"] = (time.perf_counter() - start) * 1000.0
            found = self._find(session, atlas, state, embedding, k, query_filter, timings, robot)
        scores = model.score(np.array([c.similarity for c in found.candidates], np.float64))
        if scores is not None:
            for candidate, score in zip(found.candidates, scores, strict=True):
                candidate.score = round(float(score), 4)
        config = self.verification.config
        min_inliers = self.min_inliers(state, config.matcher)
        candidates = found.candidates
        verifications: dict[int, Verification] = {}
        if self.verification.enabled and candidates:
            start = time.perf_counter()
            view = View(features.local, features.image_size, intrinsics)
            checked = candidates[: verified_count(config.top, state.index.size)]
            verifications = self.verification.check(
                view, checked, found.frames, found.stored, min_inliers
            )
            candidates = self.verification.reranked(candidates)
            # the rival part needs another place verified beside the best: when the checked
            # candidates all show one place, the most similar frame elsewhere is verified too
            reserve = found.reserve
            if (
                reserve is not None
                and candidates[0].inliers is not None
                and not has_verified_rival(candidates, self.settings.rival_gap_frames)
            ):
                verifications.update(
                    self.verification.check(
                        view, [reserve], found.frames, found.stored, min_inliers
                    )
                )
                candidates = self.verification.reranked(candidates)
            # a robot's sequence that names a place: the answer is about it (its frame verified
            # when no checked candidate shows it), the best single frame a rival beside it
            if found.place is not None and candidates[0].inliers is not None:
                verifications.update(
                    self.verification.check(
                        view, [found.place], found.frames, found.stored, min_inliers
                    )
                )
                candidates = [*candidates, found.place]
            placed = at_sequence_place(candidates, found.evidence)
            if placed is not None:
                candidates = place_first(candidates, placed)
            timings["verification"] = (time.perf_counter() - start) * 1000.0
        if prediction is None:
            guess = SubmapGuess(
                available=False,
                reason=(
                    f"model version {state.model_version} of atlas '{atlas_name}' has no trained "
                    "classification head; run a retrain job to get submap predictions"
                ),
            )
        else:
            guess = SubmapGuess(True, found.names.get(prediction.submap_id), prediction.probability)
        observe_stages(timings)
        threshold = self.settings.loop_closure_threshold
        match = candidates[0] if candidates else None
        enabled = self.verification.enabled
        # calibrated versions decide on the score, others on the cosine
        score_threshold = (
            loop_score_threshold(self.settings.loop_score_min, state.index.size)
            if scores is not None
            else None
        )
        sequence = found.evidence.sequence if found.evidence is not None else None
        agrees = (
            found.evidence.same_place(match.frame_id, sequence.frame_id)
            if found.evidence is not None and sequence is not None and match is not None
            else None
        )
        decision = decide_loop(
            answer_evidence(
                candidates,
                state.index.size,
                sequence,
                self.verification.config.scale_tolerance,
                self.settings.rival_gap_frames,
                agrees,
            ),
            threshold=self.settings.loop_probability_min,
            verify=enabled,
            min_inliers=min_inliers if enabled else None,
        )
        if enabled:
            loop_closure = decision.passed
        else:  # no geometry: the similarity (or score) threshold alone, as before
            evidence = None
            if match is not None:
                evidence = match.similarity if score_threshold is None else match.score
            loop_closure = decide(
                evidence,
                None,
                threshold=threshold if score_threshold is None else score_threshold,
                verify=False,
            )
        verdict = (
            found.evidence.verdict(match.frame_id if match else None, loop_closure)
            if found.evidence is not None
            else single_frame_verdict(match.frame_id if match else None, loop_closure)
        )
        if enabled:  # without geometry the probability is too thin to hold a place open
            verdict = probable_candidate(verdict, decision)
        return QueryResult(
            atlas=atlas_name,
            model_version=state.model_version,
            match=match,
            candidates=candidates[:k],
            loop_closure=loop_closure,
            threshold=threshold,
            score_threshold=score_threshold,
            predicted_submap=guess,
            keypoints=features.local.count,
            timings_ms={name: round(ms, 3) for name, ms in timings.items()},
            margin=place_margin(candidates),
            verification=VerificationSummary(
                enabled=enabled,
                matcher=config.matcher if enabled else None,
                verified_candidates=len(verifications),
                min_inliers=min_inliers if enabled else None,
            ),
            status=verdict.status.value,
            new_place=verdict.status == PlaceStatus.NEW_PLACE,
            consistent=verdict.consistent,
            loop_frame_id=verdict.loop_frame_id,
            pending_loop_frame_id=verdict.pending_loop_frame_id,
            confirmed=verdict.confirmed,
            sequence=sequence,
            proposals=found.proposals,
            decision=decision,
            stay_frames=found.stay_frames,
        )

    def min_inliers(self, state: LoadedAtlas, matcher: str) -> int:
        """The setting when given, else the atlas calibration's (fitted for this matcher), else
        the matcher's default."""
        fitted = state.min_inliers
        if self.settings.verify_min_inliers is None and fitted is not None and fitted[0] == matcher:
            return fitted[1]
        return self.verification.config.min_inliers

    def _find(
        self,
        session: Session,
        atlas: Atlas,
        state: LoadedAtlas,
        embedding: np.ndarray,
        k: int,
        query_filter: QueryFilter,
        timings: dict[str, float],
        robot: RobotContext | None,
    ) -> Found:
        """Resolve the filter, search the index, read the hits' frames and the stored
        keypoints of those to verify, and the robot's sequence evidence, all in the request's
        one search session."""
        selection = resolve(session, atlas, query_filter)
        own = (
            RobotFrames(session, atlas.id, query_filter.robot_id)
            if query_filter.robot_id is not None
            else None
        )
        stay = self._stay(own, state, embedding, query_filter)
        if len(stay):
            selection = Selection(selection.include, np.union1d(selection.exclude, stay))
        top = self.verification.config.top
        pool = max(k, top, MARGIN_POOL)
        if robot is not None:  # its frame's proposals are kept by an observation
            pool = max(pool, SERVICE_SEQUENCE.seeds)
        start = time.perf_counter()
        hits = state.index.search(
            embedding, pool, include=selection.include, exclude=selection.exclude
        )
        timings["search"] = (time.perf_counter() - start) * 1000.0
        evidence = None
        if robot is not None:
            start = time.perf_counter()
            evidence = self.sequences.answer(session, state, robot, embedding, hits, selection, own)
            if evidence.hit_order is not None:  # a robot's frame: contrasted with its past
                hits = [hits[i] for i in evidence.hit_order]
            timings["sequence"] = (time.perf_counter() - start) * 1000.0
        names = repo.submap_names(session, atlas_id=atlas.id)
        frames = repo.frames_by_id(session, frame_ids=[h.frame_id for h in hits])
        candidates = [
            Candidate(h.frame_id, names[f.submap_id], f.robot_id, h.similarity)
            for h in hits
            if (f := frames.get(h.frame_id)) is not None
        ]
        stored: dict[int, LocalFeatures] = {}
        reserve = place = None
        if self.verification.enabled and candidates:
            checked = candidates[: verified_count(top, state.index.size)]
            reserve = rival_reserve(candidates, len(checked), self.settings.rival_gap_frames)
            place = sequence_place(session, evidence, checked, candidates, frames, names)
            to_load = [*checked, *(c for c in (reserve, place) if c is not None)]
            stored = load_local_features(session, [c.frame_id for c in to_load])
        proposals = [h.frame_id for h in hits[: SERVICE_SEQUENCE.seeds]]
        return Found(
            candidates, frames, names, stored, reserve, place, evidence, proposals, len(stay)
        )

    def _stay(
        self,
        own: RobotFrames | None,
        state: LoadedAtlas,
        embedding: np.ndarray,
        query_filter: QueryFilter,
    ) -> np.ndarray:
        """The asking robot's current stay (:mod:`service.app.stay`): empty without a robot whose
        own frames may match, with the setting off, or on an uncalibrated version."""
        rule = stay_rule(state, self.settings)
        if own is None or query_filter.robots == "others" or rule is None:
            return np.zeros(0, np.int64)
        with self.sequences.maps.hold(own.session, state) as view:
            return frame_stay(own, view, rule, embedding)
