"""Sequence scoring and temporal consistency through the real app (SQLite, HTTP), with
synthetic precomputed features whose similarities are known by construction.

The map robot drives places 0..39 once (one frame a second). Every place has its own global
vector (orthogonal); all frames share one local descriptor, so only the global part tells
places apart. An ambiguous query frame at place p is ``0.9 g[p] + g[d]`` with a decoy d that
changes from frame to frame: each frame alone matches its decoy best, only the sequence
(which accumulates along the map's trajectory) finds p.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from service.app.ingest import FrameFields
from service.app.results import DeferredLoop, QueryResult
from service.features_payload import encode_features
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.sequences import TRACKING_DROPOUT
from service.ml.sequences.distinctiveness import CONFIRM_Z, NEWEST_Z_MIN
from service.storage.models import FrameProposals, RevisitPair
from tests.conftest import make_settings, wait_ready

PLACES = 40
DECOYS = [3, 11, 37, 7, 15, 33, 1, 9, 17, 35]  # never two consecutive places, never near 20-31
LOCAL_DIM, GLOBAL_DIM = 128, 2816  # the default preset's DISK + MobileNetV2 (GeM + layout)


def place_vectors() -> np.ndarray:
    basis, _ = np.linalg.qr(np.random.default_rng(7).standard_normal((GLOBAL_DIM, PLACES + 8)))
    return basis.T.astype(np.float32)  # orthonormal rows


G = place_vectors()


def features(global_vector: np.ndarray) -> FrameFeatures:
    n = 16
    descriptors = np.zeros((n, LOCAL_DIM), np.float32)
    descriptors[:, 0] = 1.0
    keypoints = np.stack([np.arange(n) * 10.0 + 5.0, np.full(n, 20.0)], axis=1).astype(np.float32)
    local = LocalFeatures(keypoints, descriptors, np.ones(n, np.float32))
    g = (global_vector / np.linalg.norm(global_vector)).astype(np.float32)
    return FrameFeatures(local, descriptors[0].copy(), g, (640, 480))


def ambiguous(place: int, decoy: int) -> FrameFeatures:
    return features(0.9 * G[place] + G[decoy])


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "data"


def make_client(data_dir: Path, pipeline, **overrides: object) -> TestClient:  # type: ignore[no-untyped-def]
    from service.api.app import create_app

    settings = make_settings(data_dir, verify_top=0, **overrides)
    return TestClient(create_app(settings, pipeline=pipeline))


@pytest.fixture(params=[1, 0], ids=["newest-seeds", "all-seeds"])
def app(data_dir: Path, pipeline, request) -> Iterator[TestClient]:  # type: ignore[no-untyped-def]
    """The atlas, served with candidates from the newest frame's matches or every frame's."""
    with make_client(data_dir, pipeline, sequence_seed_frames=request.param) as client:
        wait_ready(client)
        assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        client.map_ids = [  # type: ignore[attr-defined]
            insert(client, pipeline, features(G[place]), "mapper", float(place))
            for place in range(PLACES)
        ]
        yield client


def insert(client: TestClient, pipeline, frame: FrameFeatures, robot: str, t: float) -> int:  # type: ignore[no-untyped-def]
    payload = encode_features(frame, pipeline.signature)
    response = client.post(
        "/v1/atlases/campus/frames:features",
        data={"submap": "s0", "robot_id": robot, "timestamp": str(t)},
        files={"features": ("f.npz", payload)},
    )
    assert response.status_code == 201, response.text
    return int(response.json()["frame_id"])


def query(client: TestClient, pipeline, frame: FrameFeatures, **fields: str) -> dict:  # type: ignore[no-untyped-def,type-arg]
    payload = encode_features(frame, pipeline.signature)
    response = client.post(
        "/v1/atlases/campus/query:features",
        data=fields,
        files={"features": ("f.npz", payload)},
    )
    assert response.status_code == 200, response.text
    return response.json()  # type: ignore[no-any-return]


def map_frame_ids(client: TestClient) -> list[int]:
    return client.map_ids  # type: ignore[attr-defined,no-any-return]


def drive(client: TestClient, pipeline, places: list[int], start: float = 100.0) -> None:  # type: ignore[no-untyped-def]
    """The rover's earlier frames (stored, as observe stores them)."""
    for i, place in enumerate(places):
        insert(client, pipeline, ambiguous(place, DECOYS[i]), "rover", start + i)


def test_single_frames_are_ambiguous_the_sequence_is_not(app: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    ids = map_frame_ids(app)
    places = [20, 21, 22, 23, 24]
    drive(app, pipeline, places[:-1])
    newest = ambiguous(places[-1], DECOYS[len(places) - 1])
    answer = query(app, pipeline, newest, robot_id="rover", timestamp="104", sequence_length="5")
    assert answer["match"]["frame_id"] == ids[DECOYS[4]]  # alone, the decoy wins
    sequence = answer["sequence"]
    assert sequence["frame_id"] == ids[24]
    assert sequence["aligned"] == [ids[p] for p in places]
    assert sequence["length"] == 5 and sequence["speed"] == 1.0
    # off per request, and nothing about sequences without a robot
    assert query(app, pipeline, newest, robot_id="rover", sequence_length="0")["sequence"] is None
    anonymous = query(app, pipeline, newest)
    assert anonymous["sequence"] is None and anonymous["status"] in {"loop", "new_place"}


def test_a_faster_traversal_within_the_speed_range(app: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    ids = map_frame_ids(app)
    places = [25, 26, 28, 29, 30]  # 1.25 map frames per rover frame, aligned from the newest
    drive(app, pipeline, places[:-1])
    newest = ambiguous(places[-1], DECOYS[4])
    answer = query(app, pipeline, newest, robot_id="rover", timestamp="104", sequence_length="5")
    assert answer["sequence"]["frame_id"] == ids[30]
    assert answer["sequence"]["speed"] == 1.25
    assert answer["sequence"]["aligned"] == [ids[p] for p in places]


def test_a_time_gap_starts_a_new_sequence(app: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    ids = map_frame_ids(app)
    drive(app, pipeline, [20, 21, 22, 23])
    newest = ambiguous(24, DECOYS[4])
    later = query(app, pipeline, newest, robot_id="rover", timestamp="200", sequence_length="5")
    assert later["sequence"]["length"] == 1  # 96 s after the last frame: only this one
    assert later["sequence"]["frame_id"] == ids[DECOYS[4]]
    on_time = query(app, pipeline, newest, robot_id="rover", timestamp="104", sequence_length="5")
    assert on_time["sequence"]["length"] == 5 and on_time["sequence"]["frame_id"] == ids[24]


def test_consistency_candidate_then_loop_and_new_place(app: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    ids = map_frame_ids(app)
    statuses = []
    for i, place in enumerate([10, 11, 12]):
        answer = query(app, pipeline, features(G[place]), robot_id="rover", timestamp=str(100 + i))
        assert answer["loop_closure"] and answer["match"]["frame_id"] == ids[place]
        statuses.append((answer["status"], answer["consistent"], answer["new_place"]))
        insert(app, pipeline, features(G[place]), "rover", 100 + i)
    assert statuses == [("candidate", 1, False), ("candidate", 2, False), ("loop", 3, False)]
    elsewhere = query(app, pipeline, features(G[PLACES + 3]), robot_id="rover", timestamp="103")
    assert not elsewhere["loop_closure"]
    assert (elsewhere["status"], elsewhere["new_place"]) == ("new_place", True)


def test_two_replicas_answer_the_same_sequence_score(
    app: TestClient, data_dir: Path, pipeline
) -> None:  # type: ignore[no-untyped-def]
    fields = {"robot_id": "rover", "timestamp": "104", "sequence_length": "5"}
    query(app, pipeline, features(G[5]), **fields)  # this replica's map now grows frame by frame
    drive(app, pipeline, [20, 21, 22, 23])
    newest = ambiguous(24, DECOYS[4])
    first = query(app, pipeline, newest, **fields)["sequence"]  # map grown frame by frame
    with make_client(data_dir, pipeline) as other:  # a second process: map built from the rows
        wait_ready(other)
        second = query(other, pipeline, newest, **fields)["sequence"]
    assert second == first


def test_sequence_length_is_checked(app: TestClient, pipeline) -> None:  # type: ignore[no-untyped-def]
    payload = encode_features(features(G[0]), pipeline.signature)
    response = app.post(
        "/v1/atlases/campus/query:features",
        data={"robot_id": "rover", "sequence_length": "51"},
        files={"features": ("f.npz", payload)},
    )
    assert response.status_code == 422


def test_two_replicas_on_postgresql_answer_alike(
    tmp_path: Path, postgres_url: str, pipeline
) -> None:  # type: ignore[no-untyped-def]
    """The fleet setting: two API processes' apps on one PostgreSQL database, each with its
    own data directory; one takes every write, both answer."""
    fields = {"robot_id": "rover", "timestamp": "104", "sequence_length": "5"}
    newest = ambiguous(24, DECOYS[4])
    with make_client(tmp_path / "a", pipeline, database_url=postgres_url) as first:
        wait_ready(first)
        assert first.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert first.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        ids = [insert(first, pipeline, features(G[p]), "mapper", float(p)) for p in range(PLACES)]
        query(first, pipeline, features(G[5]), **fields)  # its map grows frame by frame from here
        drive(first, pipeline, [20, 21, 22, 23])
        answer = query(first, pipeline, newest, **fields)["sequence"]
        with make_client(tmp_path / "b", pipeline, database_url=postgres_url) as second:
            wait_ready(second)
            assert query(second, pipeline, newest, **fields)["sequence"] == answer
    assert answer["frame_id"] == ids[24] and answer["length"] == 5


def observe(
    client: TestClient,
    frame: FrameFeatures,
    t: float,
    exclusion: dict[str, object] | None = None,
    **fields: object,
) -> QueryResult:
    """The rover observes a frame (query, then insert) through the service, as ``observe`` over
    HTTP does after extraction; ``exclusion`` overrides the filter's recent-frame rules."""
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    result, _ = service.observe_features(
        atlas_name="campus",
        fields=FrameFields("s0", "rover", timestamp=t),
        features=frame,
        query_filter=service.query_filter(robot_id="rover", timestamp=t, **(exclusion or {})),
        **fields,
    )
    return result  # type: ignore[no-any-return]


def map_then_rover_past_decoys(client: TestClient, pipeline) -> tuple[list[int], list[QueryResult]]:  # type: ignore[no-untyped-def]
    """The mapper's places 0..39, then the rover observing places 20..24 each beside its decoy
    with sequences of 5: the map's frame ids and the rover's answers."""
    wait_ready(client)
    assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
    assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
    ids = [insert(client, pipeline, features(G[p]), "mapper", float(p)) for p in range(PLACES)]
    answers = [
        observe(client, ambiguous(place, DECOYS[i]), 100.0 + i, sequence_length=5)
        for i, place in enumerate([20, 21, 22, 23, 24])
    ]
    return ids, answers


def kept_proposals(client: TestClient) -> dict[int, int]:
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        rows = session.execute(select(FrameProposals.frame_id, FrameProposals.frame_ids))
        return {int(i): len(blob) // 4 for i, blob in rows}


def count_searches(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    from service.index import AtlasIndex

    calls: list[int] = []
    search = AtlasIndex.search

    def counted(self: AtlasIndex, *args: object, **kwargs: object) -> object:
        calls.append(1)
        return search(self, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(AtlasIndex, "search", counted)
    return calls


def test_observed_frames_propose_without_a_search_and_answer_as_searched_ones(
    app: TestClient, data_dir: Path, pipeline, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    """Each observation keeps its own search's matches; a later request of its robot reads them
    instead of searching the index again, and answers exactly as if it had searched."""
    places = [20, 21, 22, 23]
    for i, place in enumerate(places):
        observe(app, ambiguous(place, DECOYS[i]), 100.0 + i, sequence_length=0)
    assert sorted(kept_proposals(app).values()) == [len(map_frame_ids(app))] * 4  # 40 < 50
    newest = ambiguous(24, DECOYS[4])
    fields = {"robot_id": "rover", "timestamp": "104", "sequence_length": "5"}
    searches = count_searches(monkeypatch)
    kept = query(app, pipeline, newest, **fields)
    assert len(searches) == 1  # the newest frame's own search only (consistency reads them too)
    with make_client(data_dir / "searched", pipeline) as other:  # the same frames, no proposals
        wait_ready(other)
        assert other.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert other.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        for place in range(PLACES):
            insert(other, pipeline, features(G[place]), "mapper", float(place))
        drive(other, pipeline, places)
        searches.clear()
        searched = query(other, pipeline, newest, **fields)
        # every earlier frame searched again for the sequence, the last two for consistency
        assert len(searches) == 1 + len(places) + 2
    assert kept["sequence"] == searched["sequence"]
    assert kept["sequence"]["frame_id"] == map_frame_ids(app)[24]


@pytest.mark.parametrize("pairs_from_sequence_loops", [True, False])
def test_a_distinct_sequence_is_a_loop_where_single_frames_are_not(
    data_dir: Path, pipeline, pairs_from_sequence_loops: bool
) -> None:  # type: ignore[no-untyped-def]
    """Every frame alone matches a decoy, so the single-frame answers never pass; the
    sequence's margin over its rival does, and names the frame to close the loop with; that
    loop is kept as a revisit pair (source ``sequence``) unless the setting says no. On
    plain vectors: the places here share no condition for trajectory contrast to remove, so
    contrasting the rover's first few frames would only add noise to the margin."""
    with make_client(
        data_dir,
        pipeline,
        sequence_margin_min=3.0,
        trajectory_contrast_frames=0,
        pairs_from_sequence_loops=pairs_from_sequence_loops,
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        listed = client.get("/v1/atlases/campus/pairs", params={"robot": "rover"})
        assert listed.status_code == 200, listed.text
        pairs = listed.json()
    loops = [a.loop_frame_id for a in answers if a.status == "loop"]
    assert loops  # the newest at least (below)
    if pairs_from_sequence_loops:  # one pair per loop, with the loop's frame; none verified
        assert [(p["source"], p["other_frame_id"], p["inliers"]) for p in reversed(pairs)] == [
            ("sequence", frame, None) for frame in loops
        ]
        assert all(p["robot_id"] == "rover" and p["other_robot_id"] == "mapper" for p in pairs)
    else:
        assert pairs == []
    newest = answers[-1]
    assert newest.match is not None and newest.match.frame_id == ids[DECOYS[4]]
    assert newest.sequence is not None and newest.sequence.frame_id == ids[24]
    assert newest.sequence.margin >= 3.0 and newest.sequence.passed
    assert (newest.status, newest.loop_frame_id, newest.new_place) == ("loop", ids[24], False)
    first = answers[0]  # one frame aligned: fewer than consistency_frames, never passed
    assert first.sequence is not None and not first.sequence.passed
    assert first.loop_frame_id is None


@pytest.mark.parametrize("mapped_by", ["mapper", "rover"])
def test_a_revisit_within_one_run_needs_the_own_run_margin(
    data_dir: Path, pipeline, mapped_by: str
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys above, the places mapped by another robot or by the rover itself
    just before, in the same run: the same sequence answer passes on another robot's
    trajectory (sequence_margin_min) and needs sequence_margin_min_own_run on the rover's
    own, which says so in ``margin_min``."""
    with make_client(
        data_dir,
        pipeline,
        sequence_margin_min=3.0,
        sequence_margin_min_own_run=50.0,
        sequence_margin_min_tracking=None,
        trajectory_contrast_frames=0,
    ) as client:
        wait_ready(client)
        assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        ids = [insert(client, pipeline, features(G[p]), mapped_by, float(p)) for p in range(PLACES)]
        recent = {"exclude_recent_frames": 3, "exclude_recent_seconds": 0.0}
        answers = [
            observe(client, ambiguous(place, DECOYS[i]), PLACES + i, recent, sequence_length=5)
            for i, place in enumerate([20, 21, 22, 23, 24])
        ]
    newest = answers[-1].sequence
    own = mapped_by == "rover"
    assert newest is not None and newest.frame_id == ids[24] and newest.margin >= 3.0
    assert newest.margin_min == (50.0 if own else 3.0)
    assert newest.passed is not own
    assert newest.reason == (f"margin {newest.margin:.2f} is below 50" if own else None)
    assert (answers[-1].status == "loop") is not own


def test_a_robot_that_leaves_the_route_is_not_held_on_it_by_its_last_frames(
    data_dir: Path, pipeline
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys closes its loop at place 24; then the rover turns off the mapped
    route: its next frame shows a place the map does not hold. Its four earlier frames still
    align along the mapper's trajectory, so the sequence names place 25 with a margin above
    the one it needs (the tracking margin: 25 continues the loop at 24); only the newest
    frame's own evidence for 25 is missing, and that alone keeps the answer from a loop
    (service.ml.sequences.distinctiveness.NEWEST_Z_MIN)."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        assert (answers[-1].status, answers[-1].loop_frame_id) == ("loop", ids[24])
        unmapped = features(0.9 * G[PLACES + 1] + G[DECOYS[5]])  # not on the map's route
        off = observe(client, unmapped, 105.0, sequence_length=5)
    sequence = off.sequence
    assert sequence is not None and sequence.frame_id == ids[25]
    assert sequence.margin_min == 2.5  # the tracking margin's default: it continues the loop
    assert sequence.margin >= sequence.margin_min and sequence.length >= 3
    assert not sequence.passed
    assert off.status != "loop" and off.loop_frame_id is None
    # the answer says which evidence failed: the newest frame's own, not its four before
    assert len(sequence.aligned_z) == 5 and sequence.aligned_z[-1] < 1.0
    assert sequence.reason == (
        f"this frame's own evidence (aligned_z {sequence.aligned_z[-1]:.2f}) is below 1"
    )
    assert min(sequence.aligned_z[:-1]) >= 1.0
    assert answers[-1].sequence is not None and answers[-1].sequence.aligned_z[-1] >= 1.0


SCATTERED = [0, 5, 13, 19, 34, 38]  # places far from the rover's route and from each other


WEAK_SECOND = 1.2  # a second faint frame whose own evidence stays below CONFIRM_Z


def off_the_map(place: int, weight: float) -> FrameFeatures:
    """A frame from somewhere the map does not hold that looks a little like many mapped
    places and, by ``weight``, like ``place``: its own evidence for ``place`` is weak."""
    return features(weight * G[place] + G[SCATTERED].sum(axis=0) + 2.0 * G[PLACES + 2])


def test_a_robot_whose_newest_frames_look_off_the_map_is_not_carried_along_it(
    data_dir: Path, pipeline
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys closes its loop at place 24; then the rover leaves the route: its
    next two frames show somewhere unmapped, each only faintly like the place the route would
    reach. The second one alone favours that place enough (aligned_z >= NEWEST_Z_MIN) and the
    sequence's margin passes on the three route frames before it; what says "lost" is the two
    newest frames together (service.ml.sequences.off_map), and the answer says so."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        assert (answers[-1].status, answers[-1].loop_frame_id) == ("loop", ids[24])
        first = observe(client, off_the_map(25, 0.1), 105.0, sequence_length=5)
        second = observe(client, off_the_map(26, 1.0), 106.0, sequence_length=5)
    assert first.status != "loop" and second.status != "loop"
    sequence = second.sequence
    assert sequence is not None and sequence.frame_id == ids[26]
    assert sequence.margin >= sequence.margin_min and sequence.length == 5
    assert sequence.aligned_z[-1] >= 1.0 > sum(sequence.aligned_z[-2:]) / 2 + 0.25
    assert not sequence.passed and second.loop_frame_id is None
    newest = sequence.aligned_z[-2:]
    assert sequence.reason == (
        f"its last 2 frames favour the place by a mean aligned_z of {sum(newest) / 2:.2f}, "
        "below the 0.75 of a robot on the map (it may have left the mapped route)"
    )


def pairs_of(client: TestClient, frame_id: int) -> list[tuple[int, str]]:
    """The revisit pairs kept for ``frame_id``: (the other frame, source)."""
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    with service.sessions() as session:
        rows = session.execute(
            select(RevisitPair.other_frame_id, RevisitPair.source).where(
                RevisitPair.frame_id == frame_id
            )
        )
        return [(int(other), str(source)) for other, source in rows]


def observe_stored(client: TestClient, frame: FrameFeatures, t: float) -> tuple[QueryResult, int]:
    """:func:`observe` with a sequence of 5, and the id of the frame it stored."""
    service = client.app.state.runtime.service  # type: ignore[attr-defined]
    result, stored = service.observe_features(
        atlas_name="campus",
        fields=FrameFields("s0", "rover", timestamp=t),
        features=frame,
        query_filter=service.query_filter(robot_id="rover", timestamp=t),
        sequence_length=5,
    )
    return result, int(stored.id)


@pytest.mark.parametrize("next_place", [26, None], ids=["back-on-the-route", "off-the-map"])
def test_a_loop_whose_newest_frame_is_weak_waits_for_the_next_frame(
    data_dir: Path, pipeline, next_place: int | None
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys closes its loop at place 24; the rover's next frame shows place 25
    only faintly (its own aligned_z between NEWEST_Z_MIN and CONFIRM_Z): the sequence passes on
    the frames behind it, but the answer is a ``candidate`` whose loop is pending, as the first
    frame of a robot leaving the route would be. The frame after it decides: on the route
    (place 26) its loop is answered at once, the same place, and its answer confirms the pending
    one (the revisit pair is kept then); off the map it closes nothing, and the pending loop is
    never answered nor kept as a pair."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        assert (answers[-1].status, answers[-1].loop_frame_id) == ("loop", ids[24])
        weak, weak_id = observe_stored(client, off_the_map(25, 0.8), 105.0)
        after = features(G[next_place]) if next_place is not None else off_the_map(26, 0.1)
        decided, decided_id = observe_stored(client, after, 106.0)
        pairs = pairs_of(client, weak_id), pairs_of(client, decided_id)
    assert_pending(weak, ids[25])
    if next_place is None:
        assert decided.status != "loop" and decided.confirmed == ()
        assert pairs == ([], [])
        return
    assert (decided.status, decided.loop_frame_id) == ("loop", ids[26])
    assert decided.confirmed == (DeferredLoop(weak_id, ids[25]),)
    assert pairs == ([(ids[25], "sequence")], [(ids[26], "sequence")])


@pytest.mark.parametrize("last_place", [27, None], ids=["back-on-the-route", "off-the-map"])
def test_two_weak_frames_wait_together_for_a_strong_one(
    data_dir: Path, pipeline, last_place: int | None
) -> None:  # type: ignore[no-untyped-def]
    """Two weak frames in a row (places 25 and 26, each pending) do not confirm each other, as
    a robot's first two frames off the map must not: the second answer confirms nothing. A
    third frame back on the route (place 27, answered at once) confirms both, oldest first;
    off the map, neither loop is ever answered nor kept."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, _ = map_then_rover_past_decoys(client, pipeline)
        first, first_id = observe_stored(client, off_the_map(25, 0.8), 105.0)
        second, second_id = observe_stored(client, off_the_map(26, WEAK_SECOND), 106.0)
        after = features(G[last_place]) if last_place is not None else off_the_map(27, 0.1)
        decided, decided_id = observe_stored(client, after, 107.0)
        pairs = [pairs_of(client, i) for i in (first_id, second_id, decided_id)]
    assert_pending(first, ids[25])
    assert_pending(second, ids[26])
    assert second.confirmed == ()
    if last_place is None:
        assert decided.status != "loop" and decided.confirmed == ()
        assert pairs == [[], [], []]
        return
    assert (decided.status, decided.loop_frame_id) == ("loop", ids[27])
    assert decided.confirmed == (DeferredLoop(first_id, ids[25]), DeferredLoop(second_id, ids[26]))
    assert pairs == [[(ids[25], "sequence")], [(ids[26], "sequence")], [(ids[27], "sequence")]]


def assert_pending(answer: QueryResult, loop_frame_id: int) -> None:
    """``answer`` passed its sequence on a weak newest frame: a candidate whose loop with
    ``loop_frame_id`` waits, and says why."""
    sequence = answer.sequence
    assert sequence is not None and sequence.passed and sequence.awaits_next
    assert NEWEST_Z_MIN <= sequence.aligned_z[-1] < CONFIRM_Z
    assert (answer.status, answer.loop_frame_id, answer.pending_loop_frame_id) == (
        "candidate",
        None,
        loop_frame_id,
    )
    assert sequence.reason == (
        f"this frame's own evidence (aligned_z {sequence.aligned_z[-1]:.2f}) is below 3: the "
        "loop waits for a later frame with strong evidence of its own to confirm the place"
    )


def test_with_confirmation_off_a_weak_loop_is_answered_at_once(data_dir: Path, pipeline) -> None:  # type: ignore[no-untyped-def]
    """``sequence_confirm_z`` 0 (a deployment that cannot take a frame of latency): the same
    faint frame's passed sequence is a loop in its own answer, and nothing waits."""
    with make_client(
        data_dir,
        pipeline,
        sequence_margin_min=3.0,
        trajectory_contrast_frames=0,
        sequence_confirm_z=0.0,
    ) as client:
        map_then_rover_past_decoys(client, pipeline)
        weak, _ = observe_stored(client, off_the_map(25, 0.8), 105.0)
    assert weak.sequence is not None and weak.sequence.aligned_z[-1] < CONFIRM_Z
    assert weak.status == "loop" and weak.pending_loop_frame_id is None
    assert not weak.sequence.awaits_next and weak.sequence.reason is None


@pytest.mark.parametrize("dropped", [1, 2])
def test_a_track_lost_for_a_frame_or_two_is_picked_up_again(
    data_dir: Path, pipeline, dropped: int
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys closes its loop at place 24; then ``dropped`` frames show
    nothing of the map (none closes a loop) and the rover is back on the route: its sequence
    names the place as far along the route as it has driven since the loop, which continues
    that loop (the tracking margin; no further back than TRACKING_DROPOUT frames, as
    tests/ml/test_sequences.py checks)."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        assert (answers[-1].status, answers[-1].loop_frame_id) == ("loop", ids[24])
        for k in range(dropped):
            lost = observe(client, features(G[PLACES + 1 + k]), 105.0 + k, sequence_length=5)
            assert lost.status != "loop"
        place = 24 + dropped + 1
        back = observe(client, ambiguous(place, DECOYS[6]), 105.0 + dropped, sequence_length=5)
    sequence = back.sequence
    assert sequence is not None and sequence.frame_id == ids[place]
    assert dropped < TRACKING_DROPOUT and sequence.margin_min == 2.5


def test_a_place_running_ahead_of_the_robots_loops_is_not_its_sequences_loop(
    data_dir: Path, pipeline
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys closes its loop at place 24; one second later the rover's frames
    show places 30 to 34: further along the route than any speed of the sequence model (at
    most 1.25 map frames a frame, and one of rounding) carries it from that loop. Its sequence
    names those places but does not pass while the loop is one of the frames it reads back
    (its last TRACKING_DROPOUT, here fewer: its sequence of 5), and says why; the first frame
    whose sequence no longer holds the loop passes."""
    with make_client(
        data_dir, pipeline, sequence_margin_min=3.0, trajectory_contrast_frames=0
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        assert (answers[-1].status, answers[-1].loop_frame_id) == ("loop", ids[24])
        jumped = [
            observe(client, features(G[place]), 105.0 + k, sequence_length=5)
            for k, place in enumerate([30, 31, 32, 33, 34])
        ]
    sequences = [answer.sequence for answer in jumped]
    assert all(s is not None for s in sequences)
    named = [(ids.index(s.frame_id), s.passed) for s in sequences if s is not None]
    assert named[1:] == [(31, False), (32, False), (33, False), (34, True)]
    reason = sequences[2].reason if sequences[2] is not None else None
    # its margin alone would pass: what fails is the pace
    assert reason == (
        "its place lies 8 map frames past the loop closed 3 frames ago, more than the 4.75 "
        "the sequence's speeds allow"
    )
    assert TRACKING_DROPOUT >= 4


@pytest.mark.parametrize("tracking", [1.0, None])
def test_a_loop_the_robot_just_closed_is_continued_from_the_tracking_margin(
    data_dir: Path, pipeline, tracking: float | None
) -> None:  # type: ignore[no-untyped-def]
    """The drive past decoys: its first loop needs sequence_margin_min; every answer right
    after a loop whose place continues it (the next place along the mapper's trajectory)
    needs only sequence_margin_min_tracking, and says so; with tracking unset, none does.
    The loop's frame is read back from what the previous observation stored."""
    with make_client(
        data_dir,
        pipeline,
        sequence_margin_min=3.0,
        sequence_margin_min_tracking=tracking,
        trajectory_contrast_frames=0,
    ) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
        service = client.app.state.runtime.service  # type: ignore[attr-defined]
        with service.sessions() as session:
            stored = dict(
                session.execute(select(FrameProposals.frame_id, FrameProposals.loop_frame_id)).all()
            )
    assert sorted(v for v in stored.values() if v is not None) == sorted(
        a.loop_frame_id for a in answers if a.status == "loop"
    )
    follows = [
        (before.status == "loop", after.sequence.margin_min)
        for before, after in zip(answers, answers[1:], strict=False)
        if after.sequence is not None and after.sequence.frame_id in ids[21:25]
    ]
    assert any(after_loop for after_loop, _ in follows)  # the drive closes a loop early enough
    for after_loop, margin_min in follows:
        assert margin_min == (tracking if after_loop and tracking is not None else 3.0)


@pytest.mark.parametrize("contrast", [10, 0])
def test_trajectory_contrast_finds_the_place_across_a_change_of_condition(
    data_dir: Path, pipeline, contrast: int
) -> None:  # type: ignore[no-untyped-def]
    """The mapper drove places 0..39 in summer (each frame carries a shared summer component);
    the rover drives new places 40..45 and then places 20..29 in winter. Every winter frame is
    far more like the rover's own earlier winter frames than like the summer frame of its place:
    on plain vectors its sequence aligns with its own past; contrasted with the frames just
    before each one, the shared condition cancels and the sequence finds the summer places."""
    summer, winter = 2.0 * G[46], 2.0 * G[47]
    with make_client(data_dir, pipeline, trajectory_contrast_frames=contrast) as client:
        wait_ready(client)
        assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        ids = [
            insert(client, pipeline, features(G[p] + summer), "mapper", float(p))
            for p in range(PLACES)
        ]
        route = [40, 41, 42, 43, 44, 45, *range(20, 30)]
        answers = [
            observe(
                client,
                features(G[place] + winter),
                1000.0 + t,
                {"exclude_recent_frames": 3, "exclude_recent_seconds": 0.0},
                sequence_length=5,
            )
            for t, place in enumerate(route)
        ]
    revisits = answers[6 + 4 :]  # the sequence has five frames of the mapped stretch
    found = [a.sequence.frame_id if a.sequence else None for a in revisits]
    matched = [a.match.frame_id if a.match else None for a in revisits]  # single frame
    expected = [ids[place] for place in route[6 + 4 :]]
    assert answers[-1].sequence is not None
    assert answers[-1].sequence.contrast_frames == contrast  # the rover's last ten frames
    if contrast:
        assert found == expected
        assert matched == expected  # the candidates are ordered by contrast too
    else:
        assert not any(f == e for f, e in zip(found, expected, strict=True))
        assert not any(f == e for f, e in zip(matched, expected, strict=True))


@pytest.mark.parametrize("verify_top", [5, 1])
def test_the_answer_is_about_the_place_the_sequence_names(
    data_dir: Path, pipeline, verify_top: int
) -> None:  # type: ignore[no-untyped-def]
    """With verification on, each frame alone still matches its decoy best, while the rover's
    sequence names place 24 by a wide margin: the answer is about place 24 (verified, even
    when it is not among the ``verify_top`` checked candidates), the decoy stands beside it as
    a rival, and the sequence's margin backs the match. Before, the margin was lent to the
    decoy: the match that a sequence elsewhere contradicts."""
    from service.api.app import create_app

    settings = make_settings(data_dir, verify_top=verify_top, trajectory_contrast_frames=0)
    with TestClient(create_app(settings, pipeline=pipeline)) as client:
        ids, answers = map_then_rover_past_decoys(client, pipeline)
    newest = answers[-1]
    assert newest.sequence is not None and newest.sequence.frame_id == ids[24]
    assert newest.sequence.margin >= 2.0
    assert newest.match is not None and newest.match.frame_id == ids[24]
    assert newest.match.inliers is not None  # verified
    assert ids[DECOYS[4]] in [c.frame_id for c in newest.candidates]
    assert newest.decision is not None
    assert newest.decision.parts["sequence"] == pytest.approx(newest.sequence.margin, abs=1e-3)
