"""Local keypoint extractors behind one interface: DISK and XFeat, chosen by name.

Every extractor takes a decoded RGB frame and returns :class:`LocalFeatures` in the decoded
image's pixel coordinates, so stored keypoints serve geometric verification directly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np
import torch

from service.ml import weights
from service.ml.features import LocalFeatures
from service.ml.images import resize_long_side, to_tensor
from service.ml.precision import Precision, optimise


@dataclass(frozen=True)
class LocalExtractorConfig:
    """How a local extractor runs.

    Attributes:
        name: registry key ("disk", "xfeat").
        long_side: the image is resized (up or down) to this long side before extraction.
        max_keypoints: the strongest keypoints kept per frame.
        nms_window: non-maximum suppression window (the paper's 5; XFeat's is fixed at 5).
    """

    name: str = "disk"
    long_side: int = 512
    max_keypoints: int = 1024
    nms_window: int = 5


class LocalExtractor(Protocol):
    config: LocalExtractorConfig
    descriptor_dim: int

    def extract(self, rgb: np.ndarray) -> LocalFeatures: ...

    def extract_batch(self, rgbs: list[np.ndarray]) -> list[LocalFeatures]: ...


def to_decoded_pixels(
    keypoints: np.ndarray, working_size: tuple[int, int], decoded_size: tuple[int, int]
) -> np.ndarray:
    """Map ``N x 2`` (x, y) pixel centres of a resized image back to the decoded image.

    ``working_size`` and ``decoded_size`` are (width, height). Pixel ``i`` of the working image
    covers ``[i, i + 1)``; its centre lands at ``(i + 0.5) * scale - 0.5`` in the decoded image.
    """
    scale = np.array(decoded_size, np.float64) / np.array(working_size, np.float64)
    return ((keypoints.astype(np.float64) + 0.5) * scale - 0.5).astype(np.float32)


class DiskKeypoints(NamedTuple):
    """One frame's DISK keypoints (integer x, y of the working image), their L2-normalised
    descriptors and detection scores, all float32."""

    keypoints: torch.Tensor
    descriptors: torch.Tensor
    scores: torch.Tensor


class DiskExtractor:
    """DISK (kornia, pretrained ``depth`` weights) at a configurable long side."""

    descriptor_dim = 128

    def __init__(self, config: LocalExtractorConfig, precision: Precision = "fp32") -> None:
        from kornia.feature import DISK

        self.config = config
        self.model = DISK()
        checkpoint: dict[str, Any] = weights.load_checkpoint(weights.DISK_DEPTH)
        self.model.load_state_dict(checkpoint["extractor"])
        self.model.eval()
        self.model.unet = optimise(self.model.unet, "disk", precision)

    def extract(self, rgb: np.ndarray) -> LocalFeatures:
        return self.extract_batch([rgb])[0]

    @torch.inference_mode()
    def extract_batch(self, rgbs: list[np.ndarray]) -> list[LocalFeatures]:
        """Frames resized to the same working size run through the network as one batch."""
        return extract_grouped(rgbs, self.config.long_side, self.detect, self._to_local)

    def detect(self, images: torch.Tensor) -> list[DiskKeypoints]:
        """kornia's ``DISK.forward(images, n, window_size, pad_if_not_divisible=True)``, reading
        the network's output where it lies: in bf16 the dense maps stay bf16 and channels-last,
        and only the heatmap and the descriptors at the keypoints become float32 (converting the
        whole 129-channel map cost as much as the network's normalisations)."""
        from kornia.feature.disk.detector import heatmap_to_keypoints

        height, width = images.shape[-2:]
        padded = torch.nn.functional.pad(images, (0, -width % 16, 0, -height % 16), value=0.0)
        heatmaps, dense = self.model.heatmap_and_dense_descriptors(padded)
        heatmaps = heatmaps[..., :height, :width].float()
        found = []
        for i, keypoints in enumerate(
            heatmap_to_keypoints(
                heatmaps, n=self.config.max_keypoints, window_size=self.config.nms_window
            )
        ):
            x, y = keypoints.xys.T
            descriptors = dense[i, :, y, x].T.float()
            found.append(
                DiskKeypoints(
                    keypoints.xys.float(),
                    torch.nn.functional.normalize(descriptors, dim=-1),
                    keypoints.detection_logp,
                )
            )
        return found

    def _to_local(
        self, found: DiskKeypoints, image: torch.Tensor, rgb: np.ndarray
    ) -> LocalFeatures:
        if len(found.keypoints) == 0:
            return LocalFeatures.empty(self.descriptor_dim)
        working = (image.shape[-1], image.shape[-2])
        return LocalFeatures(
            keypoints=to_decoded_pixels(
                found.keypoints.numpy(), working, (rgb.shape[1], rgb.shape[0])
            ),
            descriptors=found.descriptors.numpy().astype(np.float32),
            scores=found.scores.numpy().astype(np.float32),
        )


class XFeatExtractor:
    """XFeat (kornia, pretrained ``xfeat.pt``): 64-d descriptors, several times faster than DISK.

    The frame is resized to ``long_side`` like DISK's; XFeat then works on that image rounded
    down to multiples of 32 and reports keypoint ``i`` at ``i * ratio`` of the image it got,
    which :meth:`extract` turns back into the pixel centre in the decoded frame.
    """

    descriptor_dim = 64
    NMS_WINDOW = 5  # fixed inside kornia's XFeat.detectAndCompute

    def __init__(self, config: LocalExtractorConfig, precision: Precision = "fp32") -> None:
        from kornia.feature import XFeat

        if config.nms_window != self.NMS_WINDOW:
            raise ValueError(
                f"XFeat's non-maximum suppression window is fixed at {self.NMS_WINDOW}, "
                f"got nms_window={config.nms_window}"
            )
        self.config = config
        self.model = XFeat(top_k=config.max_keypoints)
        self.model.net.load_state_dict(weights.load_checkpoint(weights.XFEAT))
        self.model.eval()
        self.model.net = optimise(self.model.net, "xfeat", precision)  # type: ignore[assignment]

    def extract(self, rgb: np.ndarray) -> LocalFeatures:
        return self.extract_batch([rgb])[0]

    @torch.inference_mode()
    def extract_batch(self, rgbs: list[np.ndarray]) -> list[LocalFeatures]:
        """Frames resized to the same working size run through the network as one batch."""
        return extract_grouped(rgbs, self.config.long_side, self._run, self._to_local)

    def _run(self, images: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        return self.model.detectAndCompute(images, top_k=self.config.max_keypoints)

    def _to_local(
        self, found: dict[str, torch.Tensor], image: torch.Tensor, rgb: np.ndarray
    ) -> LocalFeatures:
        if len(found["keypoints"]) == 0:
            return LocalFeatures.empty(self.descriptor_dim)
        resized_h, resized_w = image.shape[-2:]
        # XFeat's own working grid: the resized image rounded down to multiples of 32.
        grid_w, grid_h = max(32, resized_w // 32 * 32), max(32, resized_h // 32 * 32)
        ratio = np.array([resized_w / grid_w, resized_h / grid_h])
        grid_pixels = np.rint(found["keypoints"].numpy() / ratio)
        return LocalFeatures(
            keypoints=to_decoded_pixels(
                grid_pixels, (grid_w, grid_h), (rgb.shape[1], rgb.shape[0])
            ),
            descriptors=found["descriptors"].numpy().astype(np.float32),
            scores=found["scores"].numpy().astype(np.float32),
        )


def extract_grouped(
    rgbs: list[np.ndarray],
    long_side: int,
    run: Callable[[torch.Tensor], Sequence[Any]],
    to_local: Callable[[Any, torch.Tensor, np.ndarray], LocalFeatures],
) -> list[LocalFeatures]:
    """Resize every frame to ``long_side``, ``run`` each group of equal working size as one
    batch, and turn each frame's raw result into :class:`LocalFeatures` (input order kept)."""
    images = [resize_long_side(to_tensor(rgb), long_side) for rgb in rgbs]
    results: list[LocalFeatures | None] = [None] * len(rgbs)
    for members in group_by_shape(images):
        found = run(torch.cat([images[i] for i in members]))
        for i, one in zip(members, found, strict=True):
            results[i] = to_local(one, images[i], rgbs[i])
    return [r for r in results if r is not None]


def group_by_shape(images: list[torch.Tensor]) -> list[list[int]]:
    """Indices of ``images`` grouped by spatial shape, in first-seen order (one batch each)."""
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, image in enumerate(images):
        groups.setdefault(tuple(image.shape[-2:]), []).append(i)
    return list(groups.values())


LOCAL_EXTRACTORS: dict[str, type[DiskExtractor] | type[XFeatExtractor]] = {
    "disk": DiskExtractor,
    "xfeat": XFeatExtractor,
}


def build_local_extractor(
    config: LocalExtractorConfig, precision: Precision = "fp32"
) -> LocalExtractor:
    """Instantiate the extractor ``config.name`` with its pretrained weights, run in
    ``precision`` (already resolved, see :func:`service.ml.precision.resolve_precision`)."""
    try:
        cls = LOCAL_EXTRACTORS[config.name]
    except KeyError:
        raise ValueError(
            f"unknown local extractor {config.name!r}; choose one of {sorted(LOCAL_EXTRACTORS)}"
        ) from None
    return cls(config, precision)
