"""Dataset readers: each layout on a small folder written here, and the shared real datasets."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.evaluation.datasets import detect_layout, load_dataset
from tests.conftest import DATA_DIR


def write_image(path: Path, seed: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.random.default_rng(seed).integers(0, 255, (12, 16, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)
    return path


def names(paths: list[Path]) -> list[str]:
    return [p.name for p in paths]


# ----- traversals -------------------------------------------------------------------------


def make_traversals(root: Path, n: int = 6) -> None:
    for i in range(n):
        write_image(root / "summer" / f"img{i * 10}.png", i)  # natural order: img0, img10, ...
        write_image(root / "winter" / f"img{i * 10}.png", 100 + i)


def test_two_aligned_folders_are_traversals_with_a_frame_tolerance(tmp_path: Path) -> None:
    make_traversals(tmp_path)
    assert detect_layout(tmp_path) == "traversals"
    dataset = load_dataset(tmp_path, tolerance=1)
    assert names([r.path for r in dataset.references])[:3] == ["img0.png", "img10.png", "img20.png"]
    assert all(r.path.parent.name == "summer" for r in dataset.references)  # first folder = map
    assert [sorted(q.positives) for q in dataset.queries] == [
        [0, 1],
        [0, 1, 2],
        [1, 2, 3],
        [2, 3, 4],
        [3, 4, 5],
        [4, 5],
    ]
    assert dataset.tolerance == 1 and "±1" in dataset.ground_truth


def test_degenerate_rows_of_gt_csv_are_left_out(tmp_path: Path) -> None:
    make_traversals(tmp_path)
    with (tmp_path / "gt.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "summer", "winter", "degenerate"])
        for i in range(6):
            writer.writerow([i, f"summer/img{i * 10}.png", f"winter/img{i * 10}.png", int(i == 2)])
    dataset = load_dataset(tmp_path, tolerance=1)
    assert [r.order for r in dataset.references] == [0, 1, 3, 4, 5]
    # query frame 3 is right on frames 2..4; frame 2 is gone, so on slots 2 (frame 3), 3 (frame 4)
    assert [sorted(q.positives) for q in dataset.queries][2] == [2, 3]
    assert dataset.excluded and "degenerate" in dataset.excluded[0]


def test_explicit_folders_and_mismatched_counts(tmp_path: Path) -> None:
    make_traversals(tmp_path)
    dataset = load_dataset(tmp_path, layout="traversals", reference="winter", query="summer")
    assert dataset.references[0].path.parent.name == "winter"
    write_image(tmp_path / "winter" / "extra.png")
    with pytest.raises(ValueError, match="same number"):
        load_dataset(tmp_path, layout="traversals")


# ----- VPR-Bench --------------------------------------------------------------------------


def test_vpr_bench_ground_truth_indexes_images_in_natural_order(tmp_path: Path) -> None:
    for i in range(4):
        write_image(tmp_path / "ref" / f"{i}.jpg", i)
    for i in range(3):
        write_image(tmp_path / "query" / f"{i}.jpg", 10 + i)
    rows = np.empty((3, 2), dtype=object)
    rows[0], rows[1], rows[2] = [0, [0, 1]], [1, [2]], [2, np.array([3])]
    np.save(tmp_path / "ground_truth_new.npy", rows)
    assert detect_layout(tmp_path) == "vpr-bench"
    dataset = load_dataset(tmp_path)
    assert [sorted(q.positives) for q in dataset.queries] == [[0, 1], [2], [3]]
    assert names([r.path for r in dataset.references]) == ["0.jpg", "1.jpg", "2.jpg", "3.jpg"]


# ----- LoopDB -----------------------------------------------------------------------------


def test_loopdb_submaps_come_from_the_pose_stream(tmp_path: Path) -> None:
    shots = {
        "IMG_1": "IMG_1",
        "IMG_2": "IMG_1",
        "IMG_3": "IMG_1",
        "IMG_4": "IMG_4",
        "IMG_5": "IMG_4",
    }
    (tmp_path / "datastream_1").mkdir()
    (tmp_path / "datastream_2").mkdir()
    lines = ["timestamp_start,timestamp_stop,sampling_time,left_file_path_0,right_file_path_0,"]
    for i, shot in enumerate(shots):
        write_image(tmp_path / "datastream_1" / "samples" / "left" / f"{shot}.jpg", i)
        lines.append(f"{shot},{shot},1,datastream_1\\samples\\left\\{shot},0, ")
    lines.append(",,,,, ")  # LoopDB's descriptor has empty rows
    (tmp_path / "datastream_1" / "data_descriptor.csv").write_text("\n".join(lines) + "\n")
    poses = ["timestamp_start,timestamp_stop,sampling_time,timestamp_root,q_1,q_2,q_3,q_w,tx,ty,tz"]
    for shot, root in shots.items():
        poses.append(f"{shot},{shot},1,{root},0,0,0,1,1.5,0,0")
    poses[3] = "IMG_3,IMG_3,1,IMG_1,,,,,,,"  # a shot whose pose is missing
    (tmp_path / "datastream_2" / "data_descriptor.csv").write_text("\n".join(poses) + "\n")

    assert detect_layout(tmp_path) == "loopdb"
    dataset = load_dataset(tmp_path)
    assert names([r.path for r in dataset.references]) == ["IMG_1.jpg", "IMG_2.jpg", "IMG_4.jpg"]
    assert [r.submap for r in dataset.references] == ["IMG_1", "IMG_1", "IMG_4"]
    assert dataset.has_native_submaps
    assert dataset.references[0].position == (1.5, 0.0, 0.0)
    assert names([q.path for q in dataset.queries]) == ["IMG_3.jpg", "IMG_5.jpg"]
    assert [sorted(q.positives) for q in dataset.queries] == [[0, 1], [2]]


# ----- generic CSV ------------------------------------------------------------------------


def test_csv_ground_truth_rules(tmp_path: Path) -> None:
    rows = [
        ["role", "image", "place", "submap", "frame", "x", "y", "positives"],
        ["reference", "map/a.png", "hall", "s1", "0", "0", "0", ""],
        ["reference", "map/b.png", "hall", "s1", "1", "10", "0", ""],
        ["reference", "map/c.png", "lab", "s2", "2", "100", "0", ""],
        ["query", "q/listed.png", "", "", "", "", "", "map/c.png;map/a.png"],
        ["query", "q/near.png", "", "", "", "8", "0", ""],
        ["query", "q/frame.png", "", "", "2", "", "", ""],
        ["query", "q/place.png", "hall", "", "", "", "", ""],
    ]
    for i, row in enumerate(rows[1:]):
        write_image(tmp_path / row[1], i)
    with (tmp_path / "dataset.csv").open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    assert detect_layout(tmp_path) == "csv"
    dataset = load_dataset(tmp_path, tolerance=1, distance=5.0)
    assert [sorted(q.positives) for q in dataset.queries] == [[0, 2], [1], [1, 2], [0, 1]]
    assert [r.submap for r in dataset.references] == ["s1", "s1", "s2"]
    assert "within 5 m" in dataset.ground_truth and "same place" in dataset.ground_truth


def test_csv_without_the_required_columns_is_refused(tmp_path: Path) -> None:
    (tmp_path / "dataset.csv").write_text("file,label\na.png,x\n")
    with pytest.raises(ValueError, match="role and image"):
        load_dataset(tmp_path)


# ----- place-labelled folders -------------------------------------------------------------


def test_place_folders_split_first_image_as_reference(tmp_path: Path) -> None:
    for place, count in (("corridor", 3), ("kitchen", 2), ("stairs", 1)):
        for i in range(count):
            write_image(tmp_path / place / f"{i}.png", i)
    assert detect_layout(tmp_path) == "places"
    dataset = load_dataset(tmp_path)
    assert [r.place for r in dataset.references] == ["corridor", "kitchen", "stairs"]
    assert [(q.place, sorted(q.positives)) for q in dataset.queries] == [
        ("corridor", [0]),
        ("corridor", [0]),
        ("kitchen", [1]),
    ]


def test_place_folders_with_a_given_split(tmp_path: Path) -> None:
    write_image(tmp_path / "ref" / "a" / "1.png")
    write_image(tmp_path / "ref" / "a" / "2.png")
    write_image(tmp_path / "ref" / "b" / "1.png")
    write_image(tmp_path / "query" / "b" / "9.png")
    assert detect_layout(tmp_path) == "places"
    dataset = load_dataset(tmp_path)
    assert [sorted(q.positives) for q in dataset.queries] == [[2]]


def test_an_empty_folder_names_the_layouts(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no known dataset layout"):
        load_dataset(tmp_path)


# ----- the shared real datasets -----------------------------------------------------------


def test_nordland_leaves_out_its_degenerate_frames() -> None:
    root = DATA_DIR / "nordland_64x32"
    with (root / "gt.csv").open() as handle:
        flagged = sum(row["degenerate"] == "1" for row in csv.DictReader(handle))
    dataset = load_dataset(root, tolerance=1)
    assert dataset.layout == "traversals"
    assert len(dataset.references) == len(dataset.queries) == 3576 - flagged
    assert dataset.references[0].path.parent.name == "summer"
    assert all(q.positives for q in dataset.queries)


@pytest.mark.parametrize(
    ("folder", "tolerance", "pairs"),
    [("gardenspoint_cohog200", 2, 200), ("gardenspoint_first10", 1, 10)],
)
def test_gardens_point_folders_are_frame_aligned(folder: str, tolerance: int, pairs: int) -> None:
    dataset = load_dataset(DATA_DIR / folder, tolerance=tolerance)
    assert dataset.layout == "traversals"
    assert dataset.references[0].path.parent.name == "ref"
    assert len(dataset.queries) == pairs
    assert sorted(dataset.queries[5].positives) == list(range(5 - tolerance, 6 + tolerance))


def test_a_slice_keeps_the_queries_answerable_in_it() -> None:
    dataset = load_dataset(DATA_DIR / "gardenspoint_cohog200", tolerance=2).head(20)
    assert len(dataset.references) == 20
    assert len(dataset.queries) == 22  # queries 20 and 21 still see references 18 and 19
    assert all(max(q.positives) < 20 for q in dataset.queries)
