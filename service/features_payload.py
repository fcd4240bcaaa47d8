"""Precomputed features from robots that run the extractor on board: the payload and its checks.

A robot with its own accelerator runs the atlas's local extractor and global backbone itself
and posts what they produced; the server then only aggregates, fuses and searches. The payload
is an ``.npz`` archive (NumPy's zip of ``.npy`` arrays, written by ``numpy.savez`` or by any
language that can write a zip and a 128-byte header) holding exactly:

=================  ==============  =======================================================
array              dtype           meaning
=================  ==============  =======================================================
``signature``      unicode, 0-d    JSON of the atlas's ``feature_signature`` (must match)
``image_size``     integer, (2,)   (width, height) of the frame the extractor saw
``keypoints``      float, (N, 2)   (x, y) in that frame's pixels
``descriptors``    float, (N, D)   L2-normalised local descriptors (D: the extractor's)
``scores``         float, (N,)     detection scores
``global_vector``  float, (C,)     L2-normalised backbone vector (C: the backbone's)
=================  ==============  =======================================================

Everything is checked before anything is written: the signature, the names, shapes, dtypes and
sizes, finite values, unit norms, keypoints inside the frame, at most the signature's
``max_keypoints``. The archive is read by :class:`~service.npz_reader.NpzReader`: each array's
declared shape is checked against the most bytes it may take for this atlas's features before
a byte of it is inflated, so a zip bomb or a header declaring 10^12 values is refused unread,
and encrypted members, other compression methods or corrupt data are a 422 too. :func:`encode_features` writes the payload from the same
:class:`FrameFeatures` the server's own pipeline produces.
"""

from __future__ import annotations

import io
import json

import numpy as np

from service.errors import InvalidInput
from service.ml.aggregation import aggregate_descriptors
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.presets import FeatureSignature
from service.npz_reader import NpzReader

ARRAYS = ("signature", "image_size", "keypoints", "descriptors", "scores", "global_vector")
NORM_TOLERANCE = 1e-3  # unit vectors sent as float16 are within ~1e-3 of norm 1


def encode_features(features: FrameFeatures, signature: FeatureSignature) -> bytes:
    """The ``.npz`` payload of ``features`` extracted with ``signature`` (what a robot posts)."""
    buffer = io.BytesIO()
    np.savez(
        buffer,
        signature=np.array(json.dumps(signature.to_json(), sort_keys=True)),
        image_size=np.array(features.image_size, np.int64),
        keypoints=features.local.keypoints.astype(np.float32),
        descriptors=features.local.descriptors.astype(np.float32),
        scores=features.local.scores.astype(np.float32),
        global_vector=features.global_vector.astype(np.float32),
    )
    return buffer.getvalue()


def decode_features(
    data: bytes, signature: FeatureSignature, *, max_image_pixels: int
) -> FrameFeatures:
    """Check a payload against the atlas's ``signature`` and turn it into :class:`FrameFeatures`.

    Raises :class:`InvalidInput` (HTTP 422) saying what is wrong.
    """
    local_dim, global_dim = signature.dims
    max_keypoints = signature.local.max_keypoints
    arrays = _read_archive(data, _size_limits(local_dim, global_dim, max_keypoints))
    sent = _signature_of(arrays["signature"])
    if sent != signature:
        raise InvalidInput(
            f"the features were extracted with {sent.to_json()}, but this atlas holds features "
            f"of {signature.to_json()}; extract them with the atlas's settings"
        )
    width, height = _image_size(arrays["image_size"], max_image_pixels)
    keypoints = _float_array("keypoints", arrays["keypoints"], 2)
    if keypoints.shape[1] != 2:
        raise InvalidInput(f"keypoints must be N x 2 (x, y), got {keypoints.shape}")
    count = len(keypoints)
    if count > max_keypoints:
        raise InvalidInput(f"{count} keypoints sent; the atlas keeps at most {max_keypoints}")
    descriptors = _float_array("descriptors", arrays["descriptors"], 2)
    scores = _float_array("scores", arrays["scores"], 1)
    global_vector = _float_array("global_vector", arrays["global_vector"], 1)
    if descriptors.shape != (count, local_dim):
        raise InvalidInput(
            f"descriptors must be {count} x {local_dim} (one {local_dim}-d row per keypoint), "
            f"got {descriptors.shape}"
        )
    if scores.shape != (count,):
        raise InvalidInput(f"scores must hold one value per keypoint ({count}), got {scores.shape}")
    if global_vector.shape != (global_dim,):
        raise InvalidInput(
            f"global_vector must have {global_dim} values, got {global_vector.shape}"
        )
    inside = (keypoints >= -0.5) & (keypoints <= np.array([width, height]) - 0.5)
    if not inside.all():
        raise InvalidInput(f"keypoints must lie inside the {width}x{height} frame")
    _check_unit("descriptors", descriptors)
    _check_unit("global_vector", global_vector[None])
    local = LocalFeatures(keypoints, descriptors, scores)
    return FrameFeatures(
        local=local,
        local_vector=aggregate_descriptors(descriptors, scores),
        global_vector=global_vector,
        image_size=(width, height),
    )


def _size_limits(local_dim: int, global_dim: int, max_keypoints: int) -> dict[str, int]:
    """The most bytes each array may declare (float64 at worst)."""
    return {
        "signature": 64 * 1024,
        "image_size": 16,
        "keypoints": max_keypoints * 2 * 8,
        "descriptors": max_keypoints * local_dim * 8,
        "scores": max_keypoints * 8,
        "global_vector": global_dim * 8,
    }


def _read_archive(data: bytes, limits: dict[str, int]) -> dict[str, np.ndarray]:
    with NpzReader(data, "the features payload") as archive:
        if set(archive.members) != {f"{name}.npy" for name in ARRAYS}:
            raise InvalidInput(
                f"the features payload must hold exactly the arrays {list(ARRAYS)}; "
                f"got {sorted(archive.members)}"
            )
        return {name: archive.read(name, limits[name]) for name in ARRAYS}


def _signature_of(array: np.ndarray) -> FeatureSignature:
    if array.shape != () or array.dtype.kind != "U":
        raise InvalidInput("'signature' must be a 0-d unicode array holding JSON")
    try:
        return FeatureSignature.from_json(json.loads(str(array)))
    except json.JSONDecodeError as exc:
        raise InvalidInput(f"'signature' is not valid JSON: {exc.msg}") from exc
    except ValueError as exc:
        raise InvalidInput(f"'signature' is {exc}") from exc


def _image_size(array: np.ndarray, max_pixels: int) -> tuple[int, int]:
    if array.shape != (2,) or array.dtype.kind not in "iu":
        raise InvalidInput("'image_size' must be two integers (width, height)")
    width, height = int(array[0]), int(array[1])
    if width < 1 or height < 1 or width * height > max_pixels:
        raise InvalidInput(
            f"image_size {width}x{height} is not a frame size (1 to {max_pixels} pixels)"
        )
    return width, height


def _float_array(name: str, array: np.ndarray, ndim: int) -> np.ndarray:
    if array.dtype not in (np.float16, np.float32, np.float64) or array.ndim != ndim:
        raise InvalidInput(
            f"'{name}' must be a {ndim}-d float16/32/64 array, got {array.ndim}-d {array.dtype}"
        )
    values = np.ascontiguousarray(array, dtype=np.float32)
    if not np.isfinite(values).all():
        raise InvalidInput(f"'{name}' holds NaN or infinite values")
    return values


def _check_unit(name: str, rows: np.ndarray) -> None:
    norms = np.linalg.norm(rows, axis=1)
    if len(norms) and np.abs(norms - 1.0).max() > NORM_TOLERANCE:
        raise InvalidInput(
            f"'{name}' rows must be L2-normalised (norms {norms.min():.4f}..{norms.max():.4f})"
        )
