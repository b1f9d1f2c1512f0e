"""Query x reference similarity in blocks, and top-k per query.

Blocks keep memory bounded: a 100k x 100k float32 matrix would be 40 GB, but top-k only ever
needs one (block_q x block_r) tile plus the running best k per query.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

SimilarityFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def dot_similarity(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    return q @ r.T


def similarity_matrix(
    queries: np.ndarray, references: np.ndarray, similarity: SimilarityFn | None = None, block: int = 4096
) -> np.ndarray:
    """Full (Q, R) float32 similarity; ``similarity`` defaults to the dot product
    (cosine for L2-normalised vectors). Pass ``descriptor.similarity`` for other methods."""
    fn = similarity or dot_similarity
    q = np.asarray(queries)
    r = np.asarray(references)
    out = np.empty((len(q), len(r)), dtype=np.float32)
    for i in range(0, len(q), block):
        for j in range(0, len(r), block):
            out[i : i + block, j : j + block] = fn(q[i : i + block], r[j : j + block])
    return out


def top_k(
    queries: np.ndarray,
    references: np.ndarray,
    k: int = 1,
    similarity: SimilarityFn | None = None,
    block_queries: int = 1024,
    block_references: int = 16384,
) -> tuple[np.ndarray, np.ndarray]:
    """Best ``k`` references per query without materialising the (Q, R) matrix.

    Returns ``(indices, scores)``, both (Q, k), best first. Ties keep the lower index first.
    """
    fn = similarity or dot_similarity
    q = np.asarray(queries)
    r = np.asarray(references)
    k = int(min(k, len(r)))
    if k <= 0:
        raise ValueError("k must be >= 1 and there must be at least one reference")
    best_idx = np.zeros((len(q), k), dtype=np.int64)
    best_score = np.zeros((len(q), k), dtype=np.float32)
    for i in range(0, len(q), block_queries):
        qb = q[i : i + block_queries]
        run_idx = np.zeros((len(qb), 0), dtype=np.int64)
        run_score = np.zeros((len(qb), 0), dtype=np.float32)
        for j in range(0, len(r), block_references):
            tile = np.asarray(fn(qb, r[j : j + block_references]), dtype=np.float32)
            cand_score = np.concatenate([run_score, tile], axis=1)
            cand_idx = np.concatenate([run_idx, np.broadcast_to(np.arange(j, j + tile.shape[1]), tile.shape)], axis=1)
            if cand_score.shape[1] > k:
                part = np.argpartition(-cand_score, k - 1, axis=1)[:, :k]
                cand_score = np.take_along_axis(cand_score, part, axis=1)
                cand_idx = np.take_along_axis(cand_idx, part, axis=1)
            run_idx, run_score = cand_idx, cand_score
        # Sort best first; lexsort with index as the secondary key makes ties deterministic.
        order = np.lexsort((run_idx, -run_score), axis=1)
        best_idx[i : i + block_queries] = np.take_along_axis(run_idx, order, axis=1)
        best_score[i : i + block_queries] = np.take_along_axis(run_score, order, axis=1)
    return best_idx, best_score


def top_k_of_matrix(similarity: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(Q, R) similarity -> (indices, scores), both (Q, k), best first.

    Ties keep the lower reference index first, like ``np.argmax`` (VPR-Bench's top-1) and
    :func:`fdnet.matching.similarity.top_k`. Hand-written because numpy has no stable top-k:
    argpartition narrows to k candidates per row (ties at the k-th value are widened so no
    lower-index tie is dropped), then a lexsort orders them.
    """
    s = np.asarray(similarity)
    r = s.shape[1]
    k = int(min(max(k, 1), r))
    cand = np.argpartition(-s, k - 1, axis=1)[:, :k] if k < r else np.broadcast_to(np.arange(r), s.shape)
    cand = np.array(cand)
    kth = np.take_along_axis(s, cand, axis=1).min(axis=1)
    # Rows where more than k entries reach the k-th best value have a tie at the boundary, and
    # argpartition may have kept a higher index than a tied lower one: redo those rows exactly.
    tied = np.flatnonzero((s >= kth[:, None]).sum(axis=1) > k)
    if len(tied):
        cand[tied] = np.argsort(-s[tied], axis=1, kind="stable")[:, :k]
    cand_scores = np.take_along_axis(s, cand, axis=1)
    order = np.lexsort((cand, -cand_scores), axis=1)
    idx = np.take_along_axis(cand, order, axis=1).astype(np.int64)
    return idx, np.take_along_axis(s, idx, axis=1)
