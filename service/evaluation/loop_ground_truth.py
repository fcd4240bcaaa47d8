"""Single-trajectory ground truth: which earlier frames each frame closes a loop with.

Two sources:

- a loop-closure matrix file in the FAB-MAP layout (City Centre, New College): an ``N x N``
  0/1 matrix over the trajectory's images in natural name order, entry ``(i, j)`` = 1 when
  images i and j show the same place (only one triangle need be filled). Read from MATLAB
  ``.mat`` (the variable named, else the only 2-D one: FAB-MAP's files call it ``truth``),
  ``.npy``, or text (``.csv``/``.txt``, comma- or space-separated);
- two frame-aligned traversals driven one after the other (the development case from
  ``nordland_64x32``: the robot drives the summer route, then the winter one; winter frame i
  closes a loop with summer frames i ± tolerance, and nothing else does).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.evaluation.datasets import Dataset, list_images


@dataclass(frozen=True)
class Trajectory:
    """One robot's frames in the order it took them.

    Attributes:
        images: the frames, in order.
        loops: for each frame, the earlier frames it closes a loop with.
        starts: frames that start a new run (after a pause: no sequence spans one).
        ground_truth: how ``loops`` were decided, in words.
        root: the dataset folder the frames come from (it keys the feature cache, so a
            two-traversal trajectory reads the file ``loopnet eval`` wrote for the dataset);
            None: the first image's folder.
    """

    name: str
    images: list[Path]
    loops: list[frozenset[int]]
    starts: np.ndarray
    ground_truth: str
    root: Path | None = None

    def answerable(self, exclude_recent: int) -> int:
        """Frames with a loop partner older than the robot's ``exclude_recent`` last frames
        (the recall's denominator: only those can be answered right)."""
        return sum(
            1 for t, loops in enumerate(self.loops) if any(j < t - exclude_recent for j in loops)
        )


def read_loop_closure_matrix(path: Path, variable: str | None = None) -> np.ndarray:
    """A FAB-MAP-style loop-closure matrix file -> ``N x N`` symmetric bool matrix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mat":
        from scipy.io import loadmat

        contents = {k: v for k, v in loadmat(path).items() if not k.startswith("__")}
        if variable is not None:
            if variable not in contents:
                raise ValueError(f"{path}: no variable {variable!r} (has {sorted(contents)})")
            matrix = contents[variable]
        else:
            planes = [k for k, v in contents.items() if getattr(v, "ndim", 0) == 2]
            if len(planes) != 1:
                raise ValueError(f"{path}: name the ground-truth variable, one of {sorted(planes)}")
            matrix = contents[planes[0]]
    elif suffix == ".npy":
        matrix = np.load(path)
    elif suffix in (".csv", ".txt"):
        text = path.read_text().replace(",", " ")
        matrix = np.loadtxt(text.splitlines(), ndmin=2)
    else:
        raise ValueError(f"{path}: loop-closure matrix must be .mat, .npy, .csv or .txt")
    matrix = np.asarray(matrix)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f"{path}: a loop-closure matrix is square, got shape {matrix.shape}")
    truth = matrix != 0
    return truth | truth.T


def loops_from_matrix(truth: np.ndarray) -> list[frozenset[int]]:
    """Each frame's earlier loop-closure partners (the diagonal is ignored)."""
    return [frozenset(int(j) for j in np.flatnonzero(truth[t, :t])) for t in range(len(truth))]


def trajectory_from_matrix(images: Path, matrix: Path, variable: str | None = None) -> Trajectory:
    """A folder of one trajectory's images (natural name order) and its matrix file."""
    frames = list_images(Path(images))
    truth = read_loop_closure_matrix(matrix, variable)
    if len(truth) != len(frames):
        raise ValueError(
            f"{matrix} is {len(truth)} x {len(truth)} but {images} holds {len(frames)} images"
        )
    starts = np.zeros(len(frames), dtype=bool)
    starts[:1] = True
    return Trajectory(
        name=Path(images).name,
        images=frames,
        loops=loops_from_matrix(truth),
        starts=starts,
        ground_truth=f"loop-closure matrix {Path(matrix).name} (FAB-MAP layout)",
    )


def trajectory_from_traversals(dataset: Dataset) -> Trajectory:
    """The map traversal driven first, then the query traversal: query frame i closes a loop
    with the references the dataset lists for it; each traversal is its own run."""
    n_refs = len(dataset.references)
    images = [r.path for r in dataset.references] + [q.path for q in dataset.queries]
    loops: list[frozenset[int]] = [frozenset() for _ in range(n_refs)] + [
        q.positives for q in dataset.queries
    ]
    starts = np.zeros(len(images), dtype=bool)
    starts[[0, n_refs]] = True
    return Trajectory(
        name=f"{dataset.name}-single-trajectory",
        images=images,
        loops=loops,
        starts=starts,
        ground_truth=(
            f"{dataset.name}: map traversal ({n_refs} frames) then query traversal "
            f"({len(dataset.queries)} frames) as one robot's trajectory; {dataset.ground_truth}"
        ),
        root=Path(dataset.root),
    )
