"""``python -m workers [--threads N]``: the worker process's entry point (the same as
``loopnet worker``); the job code itself lives in :mod:`service.jobs`."""

from __future__ import annotations

import argparse
import logging

from service.config import Settings
from service.runtime.worker import run_worker


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m workers", description=__doc__)
    parser.add_argument("--threads", type=int, default=1, help="consumer threads")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    run_worker(Settings(), workers=args.threads)


if __name__ == "__main__":
    main()
