"""Seeding the weights cache: safe when several processes seed it at once (parallel test
workers, two services starting), and a stale link to moved weights is replaced."""

from __future__ import annotations

import threading
from pathlib import Path

from service.ml.weights import seed_cache


def _weights(folder: Path, count: int) -> list[Path]:
    folder.mkdir()
    files = [folder / f"net-{i}.pth" for i in range(count)]
    for i, file in enumerate(files):
        file.write_bytes(bytes([i]) * 64)
    return files


def test_seeding_at_once_from_many_threads_links_every_file(tmp_path: Path) -> None:
    files = _weights(tmp_path / "weights", 20)
    for round_ in range(10):  # the race (checked, then linked by another) needs a few tries
        cache = tmp_path / f"cache-{round_}"
        start = threading.Barrier(8)
        errors: list[BaseException] = []

        def seed(
            cache: Path = cache, start: threading.Barrier = start, errors: list = errors
        ) -> None:
            start.wait()
            try:
                seed_cache(tmp_path / "weights", cache)
            except BaseException as exc:  # the test's own thread: report, do not lose it
                errors.append(exc)

        threads = [threading.Thread(target=seed) for _ in range(8)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert errors == []
        for file in files:
            assert (cache / file.name).read_bytes() == file.read_bytes()


def test_a_stale_link_is_replaced(tmp_path: Path) -> None:
    (file,) = _weights(tmp_path / "weights", 1)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / file.name).symlink_to(tmp_path / "moved-away" / file.name)  # dangling
    assert seed_cache(tmp_path / "weights", cache) == [cache / file.name]
    assert (cache / file.name).read_bytes() == file.read_bytes()
