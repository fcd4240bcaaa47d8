"""The verification minimum a calibration job fits on an atlas's hard impostors, and the
operating point it gives on the dataset's queries, beside the matcher's fixed default.

Stores a dataset's references in a temporary atlas through the service (real CNNs), runs the
calibration job as the worker would (verification on), then asks every query through the
service and counts, at the calibrated minimum and at the default: best matches accepted as
verified, right among them (precision) and right ones accepted out of all queries (recall).
No choice is made on the queries: the minimum comes from the references alone.

    python benchmarks/verification_operating_point.py ../shared/data/gardenspoint_cohog200 \\
        --tolerance 2 --long-side 256 --matcher mnn
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from service.app.ingest import FrameFields
from service.config import Settings
from service.evaluation.datasets import load_dataset
from service.jobs.retraining import JobRunner
from service.ml.verification import default_min_inliers
from service.runtime import Runtime
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--tolerance", type=int, default=2)
    parser.add_argument("--long-side", type=int, default=256)
    parser.add_argument("--matcher", default="mnn")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    dataset = load_dataset(args.dataset, tolerance=args.tolerance)
    with tempfile.TemporaryDirectory(prefix="loopnet-verify-") as data_dir:
        settings = Settings(
            data_dir=Path(data_dir),
            long_side=args.long_side,
            matcher=args.matcher,
            calibration_milestones="",
            exclude_recent_frames=0,
        )
        runtime = Runtime(settings)
        runtime.start(background=False)
        service = runtime.service
        service.create_atlas("atlas")
        service.create_submap("atlas", "map")
        reference_of = {}
        for i, reference in enumerate(dataset.references):
            frame = service.ingest_frame(
                atlas_name="atlas",
                fields=FrameFields("map", "map"),
                image_bytes=reference.path.read_bytes(),
            )
            reference_of[frame.id] = i
        with transaction(service.sessions) as session:
            atlas_id = repo.get_atlas(session, name="atlas").id
            job_id = jobs.create_job(session, atlas_id=atlas_id, kind="calibrate", params={}).id
        JobRunner(settings, service.sessions).run(job_id)
        with service.sessions() as session:
            job = jobs.get_job(session, job_id=job_id)
            fitted = job.metrics["verification"]
        service.catch_up()
        rows = []
        for query in dataset.queries:
            answer = service.query(atlas_name="atlas", image_bytes=query.path.read_bytes(), k=5)
            match = answer.match
            if match is None or match.inliers is None:
                continue
            rows.append((match.inliers, reference_of[match.frame_id] in query.positives))
        runtime.stop()

    def point(minimum: int) -> dict[str, float | int]:
        accepted = [right for inliers, right in rows if inliers >= minimum]
        return {
            "min_inliers": minimum,
            "accepted": len(accepted),
            "precision": round(sum(accepted) / len(accepted), 3) if accepted else float("nan"),
            "recall": round(sum(accepted) / len(dataset.queries), 3),
        }

    result = {
        "dataset": dataset.name,
        "matcher": args.matcher,
        "long_side": args.long_side,
        "fitted": fitted,
        "calibrated": point(fitted["min_inliers"]),
        "default": point(default_min_inliers(args.matcher)),
    }
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
