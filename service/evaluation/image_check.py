"""Find the images of a dataset that the service would refuse, before any pass reads them.

``loopnet eval`` leaves such an image out (and lists it in the report) instead of dying half
way with a traceback. Every image is decoded once with the service's own decoder, so "usable"
means exactly what an upload would meet; the verdicts are remembered in the cache folder by
file size and modification time, so later runs re-check only changed files.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from tqdm import tqdm

from service.errors import InvalidInput
from service.ml.images import decode_image

VERDICTS_FILE = "image-check.json"


def _stamp(path: Path) -> list[int]:
    stat = path.stat()
    return [stat.st_size, stat.st_mtime_ns]


def _verdict(path: Path) -> str:
    """ "" when the service decodes the image, else why not."""
    try:
        decode_image(path.read_bytes())
    except (InvalidInput, OSError) as exc:
        return str(exc) or type(exc).__name__
    return ""


def unreadable_images(paths: Iterable[Path], cache_dir: Path | None) -> dict[Path, str]:
    """The images among ``paths`` the service would refuse, each with the reason."""
    paths = list(dict.fromkeys(paths))
    record = cache_dir / VERDICTS_FILE if cache_dir else None
    known: dict[str, list] = {}
    if record is not None and record.is_file():
        known = json.loads(record.read_text())
    verdicts: dict[Path, str] = {}
    unchecked = []
    for path in paths:
        entry = known.get(str(path.resolve()))
        if entry is not None and path.is_file() and entry[:2] == _stamp(path):
            verdicts[path] = entry[2]
        else:
            unchecked.append(path)
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
        found = pool.map(_verdict, unchecked)
        for path, verdict in zip(
            unchecked,
            tqdm(found, total=len(unchecked), desc="check images", leave=False),
            strict=True,
        ):
            verdicts[path] = verdict
            if path.is_file():
                known[str(path.resolve())] = [*_stamp(path), verdict]
    if record is not None and unchecked:
        record.parent.mkdir(parents=True, exist_ok=True)
        record.write_text(json.dumps(known))
    return {path: why for path, why in verdicts.items() if why}
