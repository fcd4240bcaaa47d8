"""Peak memory of a real ``loopnet serve`` under small uploads that decode huge (issue 24).

Starts ``loopnet serve`` from ``--repo`` (default: this checkout; point it at another
worktree for a before/after), fills an atlas with one real frame, then for each attack resets
the server's peak resident memory (``/proc/PID/clear_refs``), sends the attack and reads the
peak (``VmHWM``) back:

- ``png``, ``jpeg``, ``webp``: ``--concurrency`` simultaneous frame uploads of a one-colour
  6300 x 6300 image (under the 40 MP default; 70-600 KB on the wire);
- ``snapshot``: a restore of a ``.tar.gz`` whose ``frames.jsonl`` and ``features.npz`` are
  ``--snapshot-mib`` MiB of zeros each (within the old 1 GiB / 2 GiB limits), the rest a real
  export of the atlas: about 2 MB on the wire, refused 422 (checksums) after it is read.

Prints one line per attack (statuses, upload size, peak rise over the RSS before it in MB) and
the JSON of the whole run.

    python benchmarks/bomb_memory.py --preset fast --concurrency 4
    python benchmarks/bomb_memory.py --repo ../main --preset fast --concurrency 4   # before
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import socket
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("LOOPNET_SHARED_DIR", ROOT.parent / "shared")) / "data"
MB = 1024 * 1024
SIDE = 6300


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def peak_and_current(pid: int) -> tuple[int, int]:
    """(VmHWM, VmRSS) of ``pid`` in bytes."""
    fields = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
    )
    return (int(fields["VmHWM"].split()[0]) * 1024, int(fields["VmRSS"].split()[0]) * 1024)


@contextmanager
def served(repo: Path, preset: str, data_dir: Path) -> Iterator[tuple[httpx.Client, int]]:
    port = free_port()
    env = {
        **os.environ,
        "PYTHONPATH": str(repo),
        "LOOPNET_MODEL_PRESET": preset,
        "LOOPNET_DATA_DIR": str(data_dir),
        "LOOPNET_PORT": str(port),
        "LOOPNET_TORCH_THREADS": "1",
    }
    with (data_dir.parent / "server.log").open("w") as log:
        server = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve"],
            cwd=repo,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=600)
        try:
            deadline = time.monotonic() + 300
            while True:
                try:
                    if client.get("/v1/ready").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if server.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the server did not start: see {log.name}")
                time.sleep(0.5)
            yield client, server.pid
        finally:
            client.close()
            server.terminate()
            server.wait(60)


def image_bomb(fmt: str) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (SIDE, SIDE), (90, 120, 200)).save(buffer, format=fmt)
    return buffer.getvalue()


def snapshot_bomb(export: bytes, zeros_mib: int) -> bytes:
    """The real export with frames.jsonl and features.npz replaced by zeros, gzip-compressed."""

    class Zeros(io.RawIOBase):
        def __init__(self, size: int) -> None:
            self.left = size

        def read(self, n: int = -1) -> bytes:
            n = self.left if n < 0 else min(n, self.left)
            self.left -= n
            return bytes(n)

    out = io.BytesIO()
    with (
        tarfile.open(fileobj=io.BytesIO(export)) as source,
        tarfile.open(fileobj=out, mode="w:gz", compresslevel=1) as target,
    ):
        for member in source.getmembers():
            if member.name in ("frames.jsonl", "features.npz"):
                info = tarfile.TarInfo(member.name)
                info.size = zeros_mib * MB
                target.addfile(info, Zeros(info.size))  # type: ignore[arg-type]
            else:
                target.addfile(member, source.extractfile(member))
    return out.getvalue()


def attack(
    client: httpx.Client, pid: int, send: list[tuple[str, dict[str, Any]]], workers: int
) -> tuple[list[int], float]:
    """Statuses of the requests ``send`` sent at once, and the server's peak rise in MB."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    _, before = peak_and_current(pid)
    with ThreadPoolExecutor(workers) as pool:
        answers = list(pool.map(lambda call: client.post(call[0], **call[1]), send))
    peak, _ = peak_and_current(pid)
    return [a.status_code for a in answers], round((peak - before) / MB, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, default=ROOT)
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--concurrency", type=int, default=4)
    parser.add_argument("--snapshot-mib", type=int, default=900)
    parser.add_argument("--kinds", nargs="+", default=["png", "jpeg", "webp", "snapshot"])
    args = parser.parse_args()
    result: dict = {
        "repo": str(args.repo.resolve()),
        "commit": subprocess.run(
            ["git", "-C", str(args.repo), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
        ).stdout.strip(),
        "preset": args.preset,
        "concurrency": args.concurrency,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "attacks": {},
    }
    frame = (DATA / "gardenspoint_first10" / "ref" / "0.jpg").read_bytes()
    with (
        tempfile.TemporaryDirectory() as tmp,
        served(args.repo, args.preset, Path(tmp) / "data") as (client, pid),
    ):
        assert client.post("/v1/atlases", json={"name": "campus"}).status_code == 201
        assert client.post("/v1/atlases/campus/submaps", json={"name": "s0"}).status_code == 201
        form = {"submap": "s0", "robot_id": "r1"}
        warm = client.post(
            "/v1/atlases/campus/frames", files={"image": ("f.jpg", frame)}, data=form
        )
        assert warm.status_code == 201, warm.text
        result["rss_after_warm_up_mb"] = round(peak_and_current(pid)[1] / MB, 1)
        for kind in args.kinds:
            if kind == "snapshot":
                export = client.get("/v1/atlases/campus/snapshot").content
                body = snapshot_bomb(export, args.snapshot_mib)
                calls: list[tuple[str, dict[str, Any]]] = [
                    ("/v1/snapshots?name=bomb", {"files": {"archive": ("s.tar.gz", body)}})
                ]
            else:
                body = image_bomb(kind.upper())
                upload = {"image": (f"bomb.{kind}", body)}
                calls = [("/v1/atlases/campus/frames", {"files": upload, "data": form})]
                calls *= args.concurrency
            statuses, rise = attack(client, pid, calls, len(calls))
            result["attacks"][kind] = {
                "upload_kb": round(len(body) / 1024),
                "requests": len(calls),
                "statuses": statuses,
                "peak_rise_mb": rise,
            }
            print(f"{kind}: {len(calls)} x {len(body) // 1024} KB -> {statuses}, peak +{rise} MB")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
