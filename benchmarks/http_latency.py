"""End-to-end latency over HTTP, one client, per preset: what a robot sees.

For each preset it starts ``loopnet serve`` in a fresh data directory (a real uvicorn process),
fills an atlas over HTTP with the Gardens Point frames, then times single queries back to back
(the client's wall time from sending the multipart request to parsing the JSON answer):

- ingest throughput: frames/s posting images one by one (single client), and through the
  service path in-process (``AtlasService.ingest_frame``, no HTTP) for comparison;
- query latency p50 / p95 posting the image, and posting precomputed features
  (``query:features``: the server only fuses and searches);
- the server process's CPU time per query (user + system, from /proc): what a query costs
  the machine, which other jobs sharing the cores do not inflate.

    python benchmarks/http_latency.py --presets fast default
    LOOPNET_BACKBONE=mobilenetv2 python benchmarks/http_latency.py --presets paper

The weights must be in $TORCH_HOME/hub/checkpoints (``loopnet weights seed ../shared/weights``);
the frames are read from ``../shared/data`` beside the repository (``LOOPNET_SHARED_DIR``).
The server runs with ``--threads`` torch threads (LOOPNET_TORCH_THREADS).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
from load import cpu_seconds  # the sibling script (its folder is on the path)

from service.app.ingest import FrameFields
from service.features_payload import encode_features
from service.ml.images import decode_image
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import FeatureSignature, ModelPreset

ROOT = Path(__file__).resolve().parents[1]
# the frames live in ../shared beside the repository, like the test suite's (override with
# LOOPNET_SHARED_DIR)
DATA = Path(os.environ.get("LOOPNET_SHARED_DIR", ROOT.parent / "shared")) / "data"


@contextmanager
def served(
    preset: str, port: int, threads: int, data_dir: Path
) -> Iterator[tuple[httpx.Client, int]]:
    """A ``loopnet serve`` process with ``preset``; the client once it is ready."""
    env = {
        **os.environ,
        "LOOPNET_MODEL_PRESET": preset,
        "LOOPNET_DATA_DIR": str(data_dir),
        "LOOPNET_PORT": str(port),
        "LOOPNET_TORCH_THREADS": str(threads),
        "OMP_NUM_THREADS": str(threads),
    }
    loopnet = Path(sys.executable).with_name("loopnet")
    # the log goes to a file: a pipe nobody reads fills after a few hundred requests' log
    # lines and blocks the server (200 queries hung this benchmark)
    log = (data_dir / "server.log").open("w+b")
    server = subprocess.Popen([str(loopnet), "serve"], env=env, stdout=log, stderr=log)
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}/v1", timeout=120.0)
    try:
        deadline = time.monotonic() + 300
        while True:
            if server.poll() is not None:
                log.seek(0)
                raise RuntimeError(f"the server exited: {log.read().decode()[-2000:]}")
            try:
                ready = client.get("/ready")
                if ready.status_code == 200:
                    break
                if "Weights" in ready.text or time.monotonic() > deadline:
                    raise RuntimeError(f"the server is not ready: {ready.text}")
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        yield client, server.pid
    finally:
        client.close()
        server.terminate()
        server.wait(30)
        log.close()


def percentiles(samples: list[float]) -> str:
    return f"p50 {np.percentile(samples, 50):.1f} ms, p95 {np.percentile(samples, 95):.1f} ms"


def bench_preset(preset: str, args: argparse.Namespace, images: list[Path]) -> None:
    queries = sorted((DATA / "gardenspoint_first10" / "query").glob("*.jpg"))
    with (
        tempfile.TemporaryDirectory() as tmp,
        served(preset, args.port, args.threads, Path(tmp)) as (client, pid),
    ):
        ready = client.get("/ready").json()
        assert client.post("/atlases", json={"name": "bench"}).status_code == 201
        assert client.post("/atlases/bench/submaps", json={"name": "s"}).status_code == 201
        start = time.perf_counter()
        for path in images:
            response = client.post(
                "/atlases/bench/frames",
                data={"submap": "s", "robot_id": "r"},
                files={"image": (path.name, path.read_bytes(), "image/jpeg")},
            )
            response.raise_for_status()
        ingest_s = time.perf_counter() - start

        def query(data: bytes) -> float:
            begin = time.perf_counter()
            response = client.post(
                "/atlases/bench/query", data={"k": "5"}, files={"image": ("q.jpg", data)}
            )
            response.raise_for_status()
            return (time.perf_counter() - begin) * 1000.0

        payloads = [q.read_bytes() for q in queries]
        for data in payloads[:3]:
            query(data)  # warm-up
        cpu_before = cpu_seconds(pid)
        image_ms = [query(payloads[i % len(payloads)]) for i in range(args.queries)]
        image_cpu_ms = (cpu_seconds(pid) - cpu_before) / args.queries * 1000.0

        signature = FeatureSignature.from_json(
            client.get("/atlases/bench").json()["feature_signature"]
        )
        pipeline = FeaturePipeline(_preset_of(signature))
        features = [encode_features(pipeline.extract(decode_image(p)), signature) for p in payloads]

        def query_features(data: bytes) -> float:
            begin = time.perf_counter()
            response = client.post(
                "/atlases/bench/query:features", data={"k": "5"}, files={"features": ("f", data)}
            )
            response.raise_for_status()
            return (time.perf_counter() - begin) * 1000.0

        query_features(features[0])
        cpu_before = cpu_seconds(pid)
        features_ms = [query_features(features[i % len(features)]) for i in range(args.queries)]
        features_cpu_ms = (cpu_seconds(pid) - cpu_before) / args.queries * 1000.0
    size = np.mean([len(f) for f in features]) / 1024
    in_process = bench_in_process(preset, args.threads, images)
    print(
        f"| {preset} ({ready['local_extractor']}, {ready['backbone']}) | "
        f"{len(images) / ingest_s:.1f} | {in_process:.1f} | {percentiles(image_ms)} | "
        f"{image_cpu_ms:.1f} | {percentiles(features_ms)} ({size:.0f} KiB payload) | "
        f"{features_cpu_ms:.1f} |",
        flush=True,
    )


def _preset_of(signature: FeatureSignature) -> ModelPreset:
    """The preset an atlas's features were extracted with, from its feature signature."""
    return ModelPreset("client", signature.local, signature.backbone)


def bench_in_process(preset: str, threads: int, images: list[Path]) -> float:
    """Frames/s through ``AtlasService.ingest_frame`` (decode, CNNs, database, index; no HTTP)."""
    from service.config import Settings
    from service.runtime import Runtime

    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), model_preset=preset, torch_threads=threads)
        runtime = Runtime(settings)
        runtime.start(background=False)
        try:
            service = runtime.service
            service.create_atlas("bench")
            service.create_submap("bench", "s")
            data = [p.read_bytes() for p in images]
            service.ingest_frame(
                atlas_name="bench", fields=FrameFields("s", "r"), image_bytes=data[0]
            )  # warm-up
            start = time.perf_counter()
            for image in data:
                service.ingest_frame(
                    atlas_name="bench", fields=FrameFields("s", "r"), image_bytes=image
                )
            return len(data) / (time.perf_counter() - start)
        finally:
            runtime.stop()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--presets", nargs="+", default=["fast", "default"])
    parser.add_argument("--queries", type=int, default=50)
    parser.add_argument("--frames", type=int, default=20, help="frames ingested over HTTP")
    parser.add_argument("--threads", type=int, default=2, help="the server's torch threads")
    parser.add_argument("--port", type=int, default=8765)
    args = parser.parse_args()
    references = sorted((DATA / "gardenspoint_first10" / "ref").glob("*.jpg"))
    images = [references[i % len(references)] for i in range(args.frames)]
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, server torch threads "
        f"{args.threads}, load average {os.getloadavg()[0]:.1f}; {args.frames} frames ingested "
        f"(Gardens Point night, 640x360 JPEG), {args.queries} queries (day, 960x540), k=5\n"
    )
    print(
        "| preset | ingest frames/s, HTTP | ingest frames/s, in-process | query over HTTP (image) "
        "| server CPU ms per query | query over HTTP (precomputed features) "
        "| server CPU ms per query |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for preset in args.presets:
        bench_preset(preset, args, images)


if __name__ == "__main__":
    main()
