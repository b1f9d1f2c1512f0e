"""Matching queries against a reference map: similarity, top-k, indexed and sequence search, and
the persistent place database."""

from fdnet.matching.database import PlaceDatabase
from fdnet.matching.index import VectorIndex
from fdnet.matching.sequence import sequence_similarity
from fdnet.matching.similarity import similarity_matrix, top_k, top_k_of_matrix

__all__ = ["PlaceDatabase", "VectorIndex", "sequence_similarity", "similarity_matrix", "top_k", "top_k_of_matrix"]
