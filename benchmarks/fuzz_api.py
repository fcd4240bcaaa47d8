"""Fuzz the whole HTTP API at scale and print the responses counted by status.

Runs the schema-driven fuzz test (``tests/reliability/test_api_fuzz.py``: schemathesis over
the OpenAPI spec, in process, with tiny real images and hostile field values, on SQLite and on
PostgreSQL) with many examples per operation (a third of them on PostgreSQL):

    python benchmarks/fuzz_api.py --examples 450    # about 10,000 requests

The test fails on any 5xx or on a rejected request that wrote something; this script prints
the status counts, the requests per operation and the wall time. Needs ``../shared`` (weights
and data) like the test suite (override with ``LOOPNET_SHARED_DIR``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEST = "tests/reliability/test_api_fuzz.py"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=450, help="examples per operation")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "fuzz.json"
        env = {
            **os.environ,
            "LOOPNET_FUZZ_EXAMPLES": str(args.examples),
            "LOOPNET_FUZZ_REPORT": str(report),
        }
        start = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-m", "pytest", TEST, "-q", "-p", "no:cacheprovider", "-rs"],
            cwd=ROOT,
            env=env,
        )
        elapsed = time.perf_counter() - start
        counts = json.loads(report.read_text()) if report.is_file() else None
    if counts is None:
        print("the fuzz run wrote no report", file=sys.stderr)
        return result.returncode or 1

    statuses = {int(k): v for k, v in counts["statuses"].items()}
    total = sum(statuses.values())
    print(f"\nmachine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    print(f"examples per operation: {args.examples}; wall time {elapsed:.0f} s")
    print(f"requests: {total}; 5xx: {sum(v for k, v in statuses.items() if k >= 500)}")
    print("by status: " + ", ".join(f"{k}: {v}" for k, v in sorted(statuses.items())))
    for database, counted in sorted(counts.get("by_database", {}).items()):
        by_status = {int(k): v for k, v in counted.items()}
        print(
            f"  {database}: {sum(by_status.values())} requests; "
            + ", ".join(f"{k}: {v}" for k, v in sorted(by_status.items()))
        )
    for operation, n in sorted(counts["operations"].items()):
        print(f"  {n:6d}  {operation}")
    return result.returncode


if __name__ == "__main__":
    raise SystemExit(main())
