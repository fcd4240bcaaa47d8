"""The FAISS index of an atlas's embeddings, and building it from stored features."""

from service.index.atlas_index import AtlasIndex, Hit, IndexPolicy, ivf_nlist

__all__ = ["AtlasIndex", "IndexPolicy", "Hit", "ivf_nlist"]
