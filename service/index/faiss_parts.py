"""The FAISS pieces an atlas's index is made of: when to search exactly and how to tune the
inverted file (:class:`IndexPolicy`), building the two index types, adding vectors to their
lists, and id selectors for filtered search."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import faiss
import numpy as np

from service.index.assignment import ListAssigner

MIN_PER_LIST = 39  # k-means needs about this many training vectors per list (faiss warns below)


def ivf_nlist(n: int, per_sqrt: float = 1.0) -> int:
    """Inverted lists for ``n`` vectors: the power of two nearest ``per_sqrt * sqrt(n)``, with
    at least ``MIN_PER_LIST`` vectors per list (and at least 16 lists)."""
    nearest = 2 ** round(np.log2(per_sqrt * np.sqrt(max(n, 1))))
    most = 2 ** int(np.log2(max(n // MIN_PER_LIST, 1)))
    return int(max(16, min(nearest, most)))


@dataclass(frozen=True)
class IndexPolicy:
    """When the index switches from exact to approximate search, and how it is tuned.

    Attributes:
        flat_max_bytes: exact search while the flat index holds at most this many bytes of
            vectors (32k frames at 256-d, 6k at 1408-d; its query time is in
            benchmarks/RESULTS.md). A scan's cost is its bytes, so the threshold is in bytes.
        bytes_per_frame: memory budget of one frame's code in the inverted file (+ its 8-byte
            id); the finest scalar quantiser that fits is chosen (fp16, 8, 6 or 4 bits). 1500
            gives float16 codes at 256-d (520 B; 8-bit codes lose near ties there) and 8-bit
            codes at 1408-d (1416 B; 6-bit codes fit but lose recall, see benchmarks/RESULTS.md).
        nprobe: inverted lists visited per query.
        lists_per_sqrt: inverted lists per square root of the size (:func:`ivf_nlist`). Fewer
            lists train and assign faster (a rebuild's cost is size x lists) and scan more
            per probe: at 1M frames (256-d, synthetic) 1 (IVF1024) built in 72 s against 346 s
            for 4 (IVF4096) with recall@1 1.000 for both, p50 1.06 against 0.42 ms
            (benchmarks/RESULTS.md, *Re-embedding + index rebuild at 1M*).
        train_per_list: training vectors per list (k-means sample, taken in id order; faiss
            warns below 39).
        kmeans_iterations: k-means iterations when (re)training. 5: at 1M frames (256-d,
            synthetic, 1,000 queries, nprobe 32) recall@1 1.000 and recall@5 0.9996, as with
            10 (1.000, 0.9998), for half the training (1.2 against 2.3 CPU s); 3 gave 0.999.
            At 4 probes the centroids' quality shows, within k-means' own noise: recall@1
            0.940 (10 iterations), 0.918 (5), 0.934 (3).
        background: train and fill a new index in a thread while the old one serves (the
            service); off, the add that crosses a threshold waits for it.
    """

    flat_max_bytes: int = 32 << 20
    bytes_per_frame: int = 1500
    nprobe: int = 32
    lists_per_sqrt: float = 1.0
    train_per_list: int = MIN_PER_LIST + 1
    kmeans_iterations: int = 5
    background: bool = True

    def flat_max(self, dim: int) -> int:
        """The most frames searched exactly at ``dim``."""
        return self.flat_max_bytes // (4 * dim)

    def quantizer(self, dim: int) -> str:
        """The FAISS scalar-quantiser name whose codes fit the budget at ``dim``."""
        for name, bits in (("SQfp16", 16), ("SQ8", 8), ("SQ6", 6)):
            if dim * bits / 8 + 8 <= self.bytes_per_frame:
                return name
        return "SQ4"

    def wanted_nlist(self, dim: int, size: int) -> int | None:
        """The inverted lists ``size`` frames call for; None: exact search."""
        if size <= self.flat_max(dim):
            return None
        return ivf_nlist(size, self.lists_per_sqrt)

    def training_rows(self, ids: np.ndarray, nlist: int) -> np.ndarray:
        """Rows of the k-means sample for ``nlist`` lists: evenly spaced in id order (the same
        sample however the frames arrive), at least ``train_per_list`` a list."""
        step = max(1, len(ids) // (self.train_per_list * nlist))
        return np.argsort(ids, kind="stable")[::step]

    def new_ivf(self, dim: int, size: int) -> Any:
        """An untrained inverted file for ``size`` frames of ``dim`` values."""
        nlist = ivf_nlist(size, self.lists_per_sqrt)
        name = f"IVF{nlist},{self.quantizer(dim)}"
        index = faiss.index_factory(dim, name, faiss.METRIC_INNER_PRODUCT)
        faiss.extract_index_ivf(index).cp.niter = self.kmeans_iterations
        return index


def flat_index(dim: int) -> Any:
    return faiss.IndexIDMap2(faiss.IndexFlatIP(dim))


def assigner_of(index: Any) -> ListAssigner | None:
    return ListAssigner(index) if isinstance(index, faiss.IndexIVF) else None


def add_vectors(
    index: Any, ids: np.ndarray, vectors: np.ndarray, assigner: ListAssigner | None
) -> None:
    """Add to ``index``; the lists of an inverted file are ``assigner``'s (bf16 scoring)."""
    if assigner is None:
        index.add_with_ids(vectors, ids)
        return
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    vectors = np.ascontiguousarray(vectors, dtype=np.float32)
    lists = assigner.assign(vectors)
    index.add_core(len(ids), faiss.swig_ptr(vectors), faiss.swig_ptr(ids), faiss.swig_ptr(lists))


def quantizer_name(ivf: Any) -> str:
    names = {
        faiss.ScalarQuantizer.QT_fp16: "SQfp16",
        faiss.ScalarQuantizer.QT_8bit: "SQ8",
        faiss.ScalarQuantizer.QT_6bit: "SQ6",
        faiss.ScalarQuantizer.QT_4bit: "SQ4",
    }
    sq = getattr(ivf, "sq", None)
    return names.get(sq.qtype, "SQ") if sq is not None else type(ivf).__name__


def id_selector(include: np.ndarray | None, exclude: np.ndarray | None) -> Any:
    """A FAISS id selector: only ``include`` if given, else all but ``exclude``; None: all."""
    if include is not None:
        return faiss.IDSelectorBatch(np.ascontiguousarray(include, np.int64))
    if exclude is not None and len(exclude):
        dropped = faiss.IDSelectorBatch(np.ascontiguousarray(exclude, np.int64))
        selector: Any = faiss.IDSelectorNot(dropped)
        selector.referenced = dropped  # keep the wrapped selector alive
        return selector
    return None
