"""The FAISS index of an atlas's embeddings, and building it from stored features."""

from service.index.atlas_index import AtlasIndex, Hit
from service.index.faiss_parts import IndexPolicy, ivf_nlist

__all__ = ["AtlasIndex", "IndexPolicy", "Hit", "ivf_nlist"]
