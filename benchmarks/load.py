"""Load test: N simulated robots ingesting and querying a real LoopNet server on loopback.

Starts ``loopnet serve`` on a free loopback port with a fresh data directory (or targets
``--url``), creates an atlas with one submap per robot, then runs N robot threads. Each robot
alternates ingesting a real frame and querying with another (``--query-ratio``), for at most
``--requests`` requests or ``--duration`` seconds. A 503 is retried after its ``Retry-After``
(as a robot would); a 503 without one, a 5xx, an unexpected 4xx or a transport error
(refused, reset, time-out) is an error. Prints throughput, p50/p95 latency per operation and
the status counts:

    python benchmarks/load.py --robots 16 --requests 20 --duration 300

Loopback only: ``--url`` must point at 127.0.0.1 or localhost.
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO
from urllib.parse import urlsplit

import httpx

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_IMAGES = ROOT.parent / "shared" / "data" / "gardenspoint_cohog200"
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    """A real ``loopnet serve`` process on a loopback port, to start, kill and restart."""

    def __init__(self, data_dir: Path, env: dict[str, str] | None = None) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {
            **os.environ,
            **(env or {}),
            "LOOPNET_DATA_DIR": str(data_dir),
            "LOOPNET_HOST": "127.0.0.1",
            "LOOPNET_PORT": str(self.port),
        }
        self.process: subprocess.Popen[bytes] | None = None
        self.log_path = data_dir.parent / f"{data_dir.name}-server.log"
        self._log: IO[bytes] | None = None

    def start(self, timeout: float = 300.0) -> None:
        """Start the process and wait until ``/v1/ready`` answers 200."""
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._log = self.log_path.open("ab")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve"],
            cwd=ROOT,
            env=self.env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + timeout
        while True:
            try:
                if httpx.get(f"{self.url}/v1/ready", timeout=5).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with {self.process.returncode}: {self.log()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"server not ready in {timeout:.0f} s: {self.log()}")
            time.sleep(0.2)

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs, as when the machine or the OOM killer ends it."""
        self._end(signal.SIGKILL)

    def stop(self) -> None:
        """SIGTERM: a graceful shutdown (indexes are written)."""
        self._end(signal.SIGTERM)

    def _end(self, sig: signal.Signals) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(timeout=120)
        self.process = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-3000:] if self.log_path.is_file() else ""

    def __enter__(self) -> LiveServer:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


@dataclass
class LoadConfig:
    robots: int = 16
    requests: int = 20  # per robot
    duration_s: float = 300.0
    query_ratio: float = 0.5  # share of a robot's requests that are queries
    images: Path = DEFAULT_IMAGES
    atlas: str = "load"
    timeout_s: float = 120.0  # a request slower than this is a time-out: an error
    retry_503: bool = True


@dataclass
class LoadReport:
    config: LoadConfig
    wall_s: float = 0.0
    latencies_ms: dict[str, list[float]] = field(default_factory=dict)
    statuses: Counter[str] = field(default_factory=Counter)
    errors: list[str] = field(default_factory=list)
    retry_after_s: list[int] = field(default_factory=list)
    client_cpu_s: float = 0.0  # the load generator's own CPU (it shares the machine)
    server_cpu_s: float | None = None  # the started server's, when this run started it

    def count(self, operation: str) -> int:
        return len(self.latencies_ms.get(operation, []))

    def throughput(self, operation: str) -> float:
        return self.count(operation) / self.wall_s if self.wall_s else 0.0

    def percentile(self, operation: str, q: float) -> float | None:
        samples = sorted(self.latencies_ms.get(operation, []))
        if not samples:
            return None
        if len(samples) == 1:
            return samples[0]
        return statistics.quantiles(samples, n=100, method="inclusive")[round(q) - 1]

    def status_count(self, status: int) -> int:
        return sum(n for key, n in self.statuses.items() if key.endswith(f" {status}"))

    def summary(self) -> str:
        lines = [
            f"{self.config.robots} robots x <= {self.config.requests} requests "
            f"(query ratio {self.config.query_ratio}), wall {self.wall_s:.1f} s",
        ]
        for op in ("ingest", "query"):
            p50, p95 = self.percentile(op, 50), self.percentile(op, 95)
            if p50 is None or p95 is None:
                lines.append(f"  {op:6s}: none succeeded")
                continue
            lines.append(
                f"  {op:6s}: {self.count(op):5d} ok, {self.throughput(op):6.2f}/s, "
                f"p50 {p50:8.1f} ms, p95 {p95:8.1f} ms"
            )
        lines.append(
            "  statuses: " + ", ".join(f"{k}: {v}" for k, v in sorted(self.statuses.items()))
        )
        if self.retry_after_s:
            lines.append(
                f"  503 Retry-After: min {min(self.retry_after_s)} s, max {max(self.retry_after_s)} s"
            )
        lines.append(f"  errors: {len(self.errors)}")
        lines.extend(f"    {e}" for e in self.errors[:10])
        answered = sum(self.count(op) for op in ("ingest", "query"))
        if answered:
            cpu = f"  CPU per answered request: load generator {1000 * self.client_cpu_s / answered:.1f} ms"
            if self.server_cpu_s is not None:
                cores = os.cpu_count() or 1
                cpu += (
                    f", server {1000 * self.server_cpu_s / answered:.1f} ms (the server alone "
                    f"on {cores} idle cores: {answered * cores / self.server_cpu_s:.1f}/s at most)"
                )
            lines.append(cpu)
        return "\n".join(lines)


class _Images:
    """Real frames handed out in turn, so concurrent robots send different images."""

    def __init__(self, folder: Path) -> None:
        paths = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".png", ".jpg"))
        if not paths:
            raise FileNotFoundError(f"no .png/.jpg images under {folder}")
        self._data = [p.read_bytes() for p in paths]
        self._next = 0
        self._lock = threading.Lock()

    def take(self) -> bytes:
        with self._lock:
            data = self._data[self._next % len(self._data)]
            self._next += 1
            return data


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds the process ``pid`` has used so far, all its threads (Linux
    /proc): what requests cost the machine, which other jobs do not inflate as they do wall
    time."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _check_loopback(url: str) -> None:
    host = urlsplit(url).hostname
    if host not in LOOPBACK:
        raise ValueError(f"the load test only targets loopback, not {host!r}")


def prepare_atlas(url: str, config: LoadConfig) -> None:
    """The atlas and one submap per robot (existing ones are kept)."""
    with httpx.Client(base_url=url, timeout=60) as client:
        created = client.post("/v1/atlases", json={"name": config.atlas})
        if created.status_code not in (201, 409):
            raise RuntimeError(f"creating the atlas failed: {created.status_code} {created.text}")
        for robot in range(config.robots):
            submap = client.post(
                f"/v1/atlases/{config.atlas}/submaps", json={"name": f"robot-{robot}"}
            )
            if submap.status_code not in (201, 409):
                raise RuntimeError(f"creating a submap failed: {submap.text}")


def run_load(url: str, config: LoadConfig, server_pid: int | None = None) -> LoadReport:
    """Run the robots against a ready server at ``url`` and collect what they saw (and the CPU
    that the server ``server_pid``, when given, and the load generator spent meanwhile)."""
    _check_loopback(url)
    prepare_atlas(url, config)
    images = _Images(config.images)
    report = LoadReport(config)
    lock = threading.Lock()
    deadline = time.monotonic() + config.duration_s
    every = max(1, round(1 / config.query_ratio)) if config.query_ratio > 0 else 0

    def robot(index: int) -> None:
        name = f"robot-{index}"
        with httpx.Client(base_url=url, timeout=config.timeout_s) as client:
            for i in range(config.requests):
                op = "query" if every and i % every == every - 1 else "ingest"
                image = images.take()
                while time.monotonic() < deadline:
                    outcome = _request(client, op, config.atlas, name, image)
                    with lock:
                        _record(report, op, outcome)
                    status, _ms, retry_after, _detail = outcome
                    if status == 503 and retry_after is not None and config.retry_503:
                        time.sleep(min(retry_after, max(0.0, deadline - time.monotonic())))
                        continue
                    break
                if time.monotonic() >= deadline:
                    return

    start, client_cpu = time.perf_counter(), time.process_time()
    server_cpu = cpu_seconds(server_pid) if server_pid is not None else None
    threads = [threading.Thread(target=robot, args=(i,)) for i in range(config.robots)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    report.wall_s = time.perf_counter() - start
    report.client_cpu_s = time.process_time() - client_cpu
    if server_pid is not None and server_cpu is not None:
        report.server_cpu_s = cpu_seconds(server_pid) - server_cpu
    return report


Outcome = tuple[int | None, float, int | None, str]  # status, ms, Retry-After, detail


def _request(client: httpx.Client, op: str, atlas: str, robot: str, image: bytes) -> Outcome:
    files = {"image": ("frame.png", image, "image/png")}
    start = time.perf_counter()
    try:
        if op == "ingest":
            response = client.post(
                f"/v1/atlases/{atlas}/frames",
                data={"submap": robot, "robot_id": robot},
                files=files,
            )
        else:
            response = client.post(f"/v1/atlases/{atlas}/query", data={"k": "5"}, files=files)
    except httpx.HTTPError as exc:
        return None, (time.perf_counter() - start) * 1000.0, None, f"{type(exc).__name__}: {exc}"
    ms = (time.perf_counter() - start) * 1000.0
    retry = response.headers.get("Retry-After")
    detail = "" if response.status_code < 400 else response.text[:200]
    return response.status_code, ms, int(retry) if retry and retry.isdigit() else None, detail


def _record(report: LoadReport, op: str, outcome: Outcome) -> None:
    status, ms, retry_after, detail = outcome
    report.statuses[f"{op} {status if status is not None else 'transport-error'}"] += 1
    expected = 201 if op == "ingest" else 200
    if status == expected:
        report.latencies_ms.setdefault(op, []).append(ms)
    elif status == 503 and retry_after is not None:
        report.retry_after_s.append(retry_after)
    else:
        report.errors.append(f"{op}: {status} {detail}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=16)
    parser.add_argument("--requests", type=int, default=20, help="per robot")
    parser.add_argument("--duration", type=float, default=300.0, help="seconds, at most")
    parser.add_argument("--query-ratio", type=float, default=0.5)
    parser.add_argument("--images", type=Path, default=DEFAULT_IMAGES)
    parser.add_argument("--url", help="a running server on loopback; default: start one")
    parser.add_argument("--long-side", type=int, help="LOOPNET_LONG_SIDE of the started server")
    parser.add_argument("--workers", type=int, help="LOOPNET_INFERENCE_WORKERS")
    parser.add_argument("--queue", type=int, help="LOOPNET_INFERENCE_QUEUE")
    parser.add_argument("--torch-threads", type=int, help="LOOPNET_TORCH_THREADS")
    args = parser.parse_args()
    config = LoadConfig(
        robots=args.robots,
        requests=args.requests,
        duration_s=args.duration,
        query_ratio=args.query_ratio,
        images=args.images,
    )
    server_env = {
        f"LOOPNET_{name}": str(value)
        for name, value in (
            ("LONG_SIDE", args.long_side),
            ("INFERENCE_WORKERS", args.workers),
            ("INFERENCE_QUEUE", args.queue),
            ("TORCH_THREADS", args.torch_threads),
        )
        if value is not None
    }
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores; server settings: {server_env}")
    if args.url:
        report = run_load(args.url, config)
    else:
        with (
            tempfile.TemporaryDirectory() as tmp,
            LiveServer(Path(tmp) / "data", server_env) as server,
        ):
            assert server.process is not None
            report = run_load(server.url, config, server_pid=server.process.pid)
    print(report.summary())
    return 1 if report.errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
