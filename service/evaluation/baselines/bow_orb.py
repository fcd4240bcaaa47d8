"""Bag of visual words over ORB, the loop detector of DBoW2 / ORB-SLAM in its single-frame form.

ORB keypoints and binary descriptors (OpenCV) on the grey frame resized to a working long side;
a visual vocabulary learned with k-means (scikit-learn) on the *reference* descriptors only;
each frame becomes a tf-idf weighted word histogram (scikit-learn, idf from the references);
frames are compared by the cosine of their histograms (the L2 score of DBoW2 and of Sivic &
Zisserman's Video Google). The binary descriptors are clustered as 256-d 0/1 vectors, whose
squared Euclidean distance is their Hamming distance.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class OrbBowConfig:
    """Settings, chosen on reference images only.

    Attributes:
        long_side: the grey frame is resized (up or down) to this long side.
        max_features: ORB keypoints per frame (ORB-SLAM uses 1000 at 640x480).
        patch_size: ORB's patch and border size (15 instead of 31 leaves small frames usable).
        fast_threshold: FAST corner threshold (10 instead of 20 finds corners on blurry,
            upsampled thumbnails).
        vocabulary_size: visual words (clipped to a tenth of the reference descriptors).
        seed: k-means seed.
    """

    long_side: int = 256
    max_features: int = 500
    patch_size: int = 15
    fast_threshold: int = 10
    vocabulary_size: int = 1000
    seed: int = 0


class BowOrbBaseline:
    name = "bow-orb"
    label = "BoW ORB (DBoW2-style, tf-idf)"

    def __init__(self, config: OrbBowConfig) -> None:
        import cv2

        self.config = config
        self._orb = cv2.ORB_create(  # type: ignore[attr-defined]
            nfeatures=config.max_features,
            edgeThreshold=config.patch_size,
            patchSize=config.patch_size,
            fastThreshold=config.fast_threshold,
        )
        self._kmeans: Any = None
        self._tfidf: Any = None
        self._reference_words: Any = None

    def settings(self) -> dict[str, Any]:
        return {**asdict(self.config), "vocabulary_learned": self._vocabulary_learned()}

    def _vocabulary_learned(self) -> int | None:
        return None if self._kmeans is None else int(self._kmeans.n_clusters)

    def describe(self, rgb: np.ndarray) -> np.ndarray:
        """``N x 256`` float32 0/1 bits of the frame's ORB descriptors (``N`` may be 0)."""
        import cv2

        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        height, width = grey.shape
        scale = self.config.long_side / max(height, width)
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        grey = cv2.resize(grey, size, interpolation=interpolation)
        _, descriptors = self._orb.detectAndCompute(grey, None)
        if descriptors is None:
            return np.zeros((0, 256), np.float32)
        return np.unpackbits(descriptors, axis=1).astype(np.float32)

    def fit(self, references: list[np.ndarray]) -> None:
        from sklearn.cluster import MiniBatchKMeans
        from sklearn.feature_extraction.text import TfidfTransformer

        stacked = np.concatenate([r for r in references if len(r)] or [np.zeros((0, 256))])
        if len(stacked) < 2:
            raise ValueError("ORB found fewer than two descriptors in the reference frames")
        words = int(min(self.config.vocabulary_size, max(2, len(stacked) // 10)))
        self._kmeans = MiniBatchKMeans(
            n_clusters=words, random_state=self.config.seed, n_init=1, batch_size=1024
        ).fit(stacked)
        self._tfidf = TfidfTransformer(norm="l2", smooth_idf=True)
        self._reference_words = self._tfidf.fit_transform(self._histograms(references))

    def _histograms(self, frames: list[np.ndarray]) -> Any:
        from scipy.sparse import csr_matrix

        rows, cols = [], []
        for i, bits in enumerate(frames):
            if len(bits):
                words = self._kmeans.predict(bits)
                rows.extend([i] * len(words))
                cols.extend(words.tolist())
        counts = np.ones(len(rows), np.float64)
        return csr_matrix(
            (counts, (rows, cols)), shape=(len(frames), self._kmeans.n_clusters)
        )  # duplicate (row, col) entries are summed: word counts

    def score(self, queries: list[np.ndarray]) -> np.ndarray:
        if self._tfidf is None:
            raise RuntimeError("fit the vocabulary on the reference frames first")
        query_words = self._tfidf.transform(self._histograms(queries))
        return np.asarray((query_words @ self._reference_words.T).todense(), dtype=np.float32)
