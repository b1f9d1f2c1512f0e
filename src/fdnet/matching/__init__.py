"""Matching queries against a reference map: similarity, top-k, indexed and sequence search."""

from fdnet.matching.similarity import similarity_matrix, top_k, top_k_of_matrix

__all__ = ["similarity_matrix", "top_k", "top_k_of_matrix"]
