"""Matching queries against a reference map: similarity, top-k, indexed and sequence search."""

from fdnet.matching.similarity import similarity_matrix, top_k

__all__ = ["similarity_matrix", "top_k"]
