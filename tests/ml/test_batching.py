"""Dynamic micro-batching: each caller its own answer, its own error, within the wait bound."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

from service.ml.batching import MicroBatcher
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import resolve_preset
from tests.conftest import gardens_point_day_night


class Recorder:
    """A batched function that records its batch sizes and takes ``cost_s`` per call."""

    def __init__(self, cost_s: float = 0.0) -> None:
        self.cost_s = cost_s
        self.sizes: list[int] = []
        self.lock = threading.Lock()

    def __call__(self, items: list[int]) -> list[int]:
        with self.lock:
            self.sizes.append(len(items))
        time.sleep(self.cost_s)
        for item in items:
            if item < 0:
                raise ValueError(f"negative input {item}")
        return [item * item for item in items]


def test_concurrent_callers_each_get_their_own_result() -> None:
    run = Recorder(cost_s=0.002)
    batcher = MicroBatcher(run, window_s=0.01, max_batch=8)
    with ThreadPoolExecutor(32) as pool:
        results = list(pool.map(batcher.submit, range(500)))
    assert results == [i * i for i in range(500)]
    assert sum(run.sizes) == 500
    assert max(run.sizes) > 1, "concurrent callers never shared a batch"
    assert max(run.sizes) <= 8
    assert batcher.stats.items == 500 and batcher.stats.largest == max(run.sizes)


def test_a_failing_input_fails_only_its_own_caller() -> None:
    batcher = MicroBatcher(Recorder(cost_s=0.001), window_s=0.02, max_batch=16)
    inputs = [3, -1, 5, 7, -2, 11] * 5

    def call(item: int) -> int | str:
        try:
            return batcher.submit(item)
        except ValueError as exc:
            return str(exc)

    with ThreadPoolExecutor(len(inputs)) as pool:
        results = list(pool.map(call, inputs))
    want = [f"negative input {i}" if i < 0 else i * i for i in inputs]
    assert results == want
    assert batcher.stats.largest > 1


def test_no_caller_waits_longer_than_the_window_plus_its_inference() -> None:
    window_s, cost_s = 0.05, 0.03
    batcher = MicroBatcher(Recorder(cost_s=cost_s), window_s=window_s, max_batch=4)
    waits: list[float] = []
    lock = threading.Lock()

    def call(item: int) -> None:
        time.sleep(0.013 * (item % 7))  # staggered arrivals: some lead, some join
        start = time.perf_counter()
        assert batcher.submit(item) == item * item
        with lock:
            waits.append(time.perf_counter() - start)

    threads = [threading.Thread(target=call, args=(i,)) for i in range(40)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(waits) == 40
    slack = 0.1  # thread scheduling on a shared machine
    assert max(waits) <= window_s + cost_s + slack, max(waits)


def test_a_full_batch_runs_without_waiting_for_the_window() -> None:
    batcher = MicroBatcher(Recorder(), window_s=5.0, max_batch=4)
    start = time.perf_counter()
    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(batcher.submit, [1, 2, 3, 4])) == [1, 4, 9, 16]
    assert time.perf_counter() - start < 2.0


def test_zero_window_calls_alone_and_bad_settings_are_refused() -> None:
    run = Recorder()
    assert MicroBatcher(run, window_s=0.0, max_batch=8).submit(3) == 9
    assert run.sizes == [1]
    with pytest.raises(ValueError):
        MicroBatcher(run, window_s=-1.0, max_batch=8)
    with pytest.raises(ValueError):
        MicroBatcher(run, window_s=0.01, max_batch=0)


def test_batched_pipeline_gives_each_concurrent_frame_its_own_features() -> None:
    """Real CNNs, distinct real frames from many threads: no mix-ups."""
    from service.ml.images import decode_image

    frames = [decode_image(gardens_point_day_night(i, "query")) for i in range(6)]
    alone = FeaturePipeline(resolve_preset("fast"), precision="fp32")
    batched = FeaturePipeline(
        resolve_preset("fast"), precision="fp32", batch_window_ms=50.0, max_batch=6
    )
    want = [alone.extract(rgb) for rgb in frames]
    with ThreadPoolExecutor(6) as pool:
        got = list(pool.map(batched.extract, frames * 2))
    assert batched.batcher.stats.largest > 1
    for i, features in enumerate(got):
        reference = want[i % 6]
        assert np.allclose(features.global_vector, reference.global_vector, atol=1e-4)
        assert float(features.local_vector @ reference.local_vector) >= 0.999
        assert features.local.count == pytest.approx(reference.local.count, abs=2)


def test_batching_settings_let_a_batch_fill(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from service.concurrency import default_workers
    from service.config import Settings

    on = Settings(data_dir=tmp_path, batch_window_ms=5, max_batch=8, torch_threads=1)
    assert on.inference_workers == 8 * default_workers(1)
    assert on.pipeline_options() == ("auto", 5.0, 8, "auto")
    assert Settings(data_dir=tmp_path).inference_workers is None  # off: unchanged default
    chosen = Settings(data_dir=tmp_path, batch_window_ms=5, inference_workers=3)
    assert chosen.inference_workers == 3


def test_branches_side_by_side_give_the_same_features() -> None:
    """The global backbone in its own thread, beside the local extractor (for a frame alone;
    concurrent frames run their branches one after the other): every frame gets exactly the
    features of the two branches run one after the other."""
    from service.ml.images import decode_image

    frames = [decode_image(gardens_point_day_night(i, "query")) for i in range(4)]
    one_after = FeaturePipeline(resolve_preset("fast"), precision="fp32", parallel_branches="off")
    side_by_side = FeaturePipeline(resolve_preset("fast"), precision="fp32", parallel_branches="on")
    assert side_by_side.parallel_branches and not one_after.parallel_branches
    threads: list[str] = []
    describe = side_by_side._describe_timed

    def recording(rgbs: list[np.ndarray]) -> tuple[np.ndarray, float]:
        threads.append(threading.current_thread().name)
        return describe(rgbs)

    side_by_side._describe_timed = recording  # type: ignore[method-assign]
    intra_op = torch.get_num_threads()
    torch.set_num_threads(1)  # as the service runs (a new thread's own team would take 2)
    try:
        want = [one_after.extract(rgb) for rgb in frames]
        got = [side_by_side.extract(rgb) for rgb in frames]  # one at a time: side by side
        assert all(name.startswith("loopnet-global-branch") for name in threads)
        with ThreadPoolExecutor(4) as pool:  # concurrent frames: one after the other, mostly
            got += list(pool.map(side_by_side.extract, frames))
        for i, features in enumerate(got):
            reference = want[i % 4]
            assert np.array_equal(features.global_vector, reference.global_vector)
            assert np.array_equal(features.local.keypoints, reference.local.keypoints)
            assert np.array_equal(features.local.descriptors, reference.local.descriptors)
            assert set(features.timings_ms) == {"local_features", "global_features"}
    finally:
        torch.set_num_threads(intra_op)


def test_parallel_branches_auto_needs_a_core_per_branch(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    import torch

    from service.ml import pipeline

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert pipeline.branches_in_parallel("auto")
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert not pipeline.branches_in_parallel("auto")  # 4 threads on 2 cores: oversubscribed
    assert pipeline.branches_in_parallel("on") and not pipeline.branches_in_parallel("off")
