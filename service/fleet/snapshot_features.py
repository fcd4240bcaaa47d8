"""Decoding a snapshot's ``features.npz`` into plain numeric arrays, without trusting it: the
exact set of arrays export writes, in the types export writes them, their declared shapes
checked against each other and against the manifest's frame count before any large array is
inflated, each inflated once (to a ``.npy`` file beside the archive's members, memory-mapped:
a restore holds in memory only what it works on) and never unpickled.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.domain.limits import ArchiveLimits
from service.errors import InvalidInput
from service.npz_reader import NpzReader

MAX_DIM = 4096  # widest feature, hidden layer or embedding accepted (RetrainParams.embed_dim)
CHECK_ROWS = 65_536  # rows checked for finite values at a time


@dataclass
class Features:
    """Every frame's stored features as flat arrays (ragged keypoints by offsets); the large
    ones memory-mapped from the restore's folder."""

    frame_ids: np.ndarray  # int64, n
    offsets: np.ndarray  # int64, n + 1
    descriptor_dim: int
    global_dim: int
    keypoints: np.ndarray  # float32, K x 2
    descriptors: np.ndarray  # float16, K x descriptor_dim
    scores: np.ndarray  # float32, K
    local_vectors: np.ndarray  # float32, n x descriptor_dim
    global_vectors: np.ndarray  # float32, n x global_dim (as archived; see as_stored)


# the type and number of dimensions of each array, as export writes them
NPZ_ARRAYS = {
    "frame_ids": ("<i8", 1),
    "keypoint_counts": ("<i8", 1),
    "descriptor_dim": ("<i8", 0),
    "global_dim": ("<i8", 0),
    "keypoints": ("<f4", 2),
    "descriptors": ("<f2", 2),
    "scores": ("<f4", 1),
    "local_vectors": ("<f4", 2),
    "global_vectors": ("<f4", 2),
}
SMALL = ("descriptor_dim", "global_dim")


def decode_features(path: Path, limits: ArchiveLimits, folder: Path, frames: int) -> Features:
    """The arrays of the archive's ``features.npz`` at ``path`` for ``frames`` frames (the
    manifest's count), inflated into ``folder``."""
    with NpzReader(path, "the snapshot's features.npz") as npz:
        if set(npz.members) != {f"{name}.npy" for name in NPZ_ARRAYS}:
            raise InvalidInput("the snapshot's features.npz does not hold the expected arrays")
        headers = {name: npz.header(name) for name in NPZ_ARRAYS}
        for name, (dtype, ndim) in NPZ_ARRAYS.items():
            header = headers[name]
            if header.dtype != np.dtype(dtype) or len(header.shape) != ndim:
                raise InvalidInput(
                    f"the snapshot's features.npz has {name} of type {header.dtype} and "
                    f"{len(header.shape)} dimensions (export writes {dtype}, {ndim})"
                )
        if headers["frame_ids"].shape != (frames,):
            raise InvalidInput(
                f"the snapshot's features.npz holds {headers['frame_ids'].shape[0]} frames, "
                f"its manifest {frames}"
            )
        if sum(h.nbytes for h in headers.values()) > limits.max_total_bytes:
            raise InvalidInput(
                "the snapshot's features.npz inflates beyond LOOPNET_SNAPSHOT_MAX_TOTAL_BYTES"
            )
        descriptor_dim, global_dim = (int(npz.read(name, 8)) for name in SMALL)
        if not (1 <= descriptor_dim <= MAX_DIM and 1 <= global_dim <= MAX_DIM):
            raise InvalidInput("the snapshot's feature sizes are out of range")
        counts = npz.read("keypoint_counts", 8 * frames)
        if (counts < 0).any():
            raise InvalidInput("the snapshot's features.npz has negative keypoint counts")
        total = int(counts.sum())
        expected = {
            "frame_ids": (frames,),
            "keypoint_counts": (frames,),
            "keypoints": (total, 2),
            "descriptors": (total, descriptor_dim),
            "scores": (total,),
            "local_vectors": (frames, descriptor_dim),
            "global_vectors": (frames, global_dim),
        }
        for name, shape in expected.items():
            if headers[name].shape != shape:
                raise InvalidInput(
                    f"the snapshot's features.npz has {name} of shape {headers[name].shape}, "
                    f"expected {shape}"
                )
        big = {
            name: npz.extract(name, folder / f"features-{name}.npy", limits.max_total_bytes)
            for name in ("frame_ids", *expected.keys() - {"frame_ids", "keypoint_counts"})
        }
    features = Features(
        frame_ids=np.asarray(big["frame_ids"]),
        offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        descriptor_dim=descriptor_dim,
        global_dim=global_dim,
        keypoints=big["keypoints"],
        descriptors=big["descriptors"],
        scores=big["scores"],
        local_vectors=big["local_vectors"],
        global_vectors=big["global_vectors"],
    )
    for name in ("keypoints", "scores", "local_vectors", "global_vectors"):
        array = getattr(features, name)
        for start in range(0, len(array), CHECK_ROWS):
            if not np.isfinite(array[start : start + CHECK_ROWS]).all():
                raise InvalidInput(f"the snapshot's features.npz has non-finite {name}")
    return features
