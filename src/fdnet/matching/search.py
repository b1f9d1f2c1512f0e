"""Rank a reference map's images for each query: the search (``exact`` blocked top-k for any
method, SeqSLAM sequences, or a faiss index for dot-product methods) and the saved-index cache
(an index file is reused when it was built for the same method, reference names and build
settings). ``fdnet match`` (:mod:`fdnet.tasks.match`) decides on the ranked candidates and writes
them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from fdnet.errors import ConfigError
from fdnet.matching.index import INDEX_KINDS

logger = logging.getLogger(__name__)

#: ``exact`` (blocked numpy top-k, any method) or one of the faiss index kinds
INDEX_CHOICES = ["exact", *INDEX_KINDS]


def map_digest(paths) -> str:
    """SHA-256 of what a map's vectors were computed from, in order: each image's absolute path as
    listed and the size and modification time of the file behind it (for a frame of a video or
    bag, that file's), so an index built for one folder is not reused for another whose images
    share file names (two conditions of one route), nor for rewritten images."""
    from fdnet.data.identity import images_digest

    return images_digest(paths)


def cached_index(path, descriptor, ref_paths, settings, log: Callable[[str], None] | None = None):
    """The index in ``path`` when it was built for this descriptor, these reference images
    (:func:`map_digest`: paths, sizes, modification times) and these build settings; else None
    (with the reason given to ``log``)."""
    from fdnet.matching.index import SEARCH_SETTINGS, VectorIndex

    if not Path(path).is_file():
        return None
    header = VectorIndex.read_header(path)
    meta = header.get("metadata", {})
    build = {k: v for k, v in vars(settings).items() if k not in SEARCH_SETTINGS}
    saved = {k: v for k, v in header["settings"].items() if k not in SEARCH_SETTINGS}
    reasons = []
    if meta.get("fingerprint") != descriptor.fingerprint():
        reasons.append("another method or model")
    if meta.get("references") != map_digest(ref_paths) or header["count"] != len(ref_paths):
        reasons.append("other reference images")
    if saved != build:
        reasons.append(f"other build settings ({saved})")
    if reasons:
        (log or logger.info)(f"{path}: holds an index of {', '.join(reasons)}; building a new one")
        return None
    return VectorIndex.load(path, search={k: getattr(settings, k) for k in SEARCH_SETTINGS})


def reference_times_and_positions(paths) -> dict:
    """``reference_times`` (seconds) when every reference is a frame of a video or bag, and
    ``reference_positions`` (metres) when every one has a position (a bag's GPS/odometry): what
    the acceptance settings radius_s / radius_m need. Image files have neither."""
    from fdnet.data.frame_records import frame_records, positions_in_metres

    records = frame_records(paths)
    out = {}
    if records and all(r.timestamp is not None for r in records):
        out["reference_times"] = np.array([r.timestamp for r in records], dtype=np.float64)
    positions = positions_in_metres(records)
    if records and all(p is not None for p in positions):
        out["reference_positions"] = np.array(positions, dtype=np.float64)
    return out


def index_settings(index: str, index_set=(), index_file=None, sequence_length: int = 1):
    """The faiss :class:`~fdnet.matching.index.IndexSettings` of ``index`` with ``index_set``
    (``KEY=VALUE``) applied, or None for ``exact``; refuses combinations that cannot work."""
    from fdnet.matching.index import parse_index_settings

    if index not in INDEX_CHOICES:
        raise ConfigError(f"--index {index!r}: choose from {', '.join(INDEX_CHOICES)}")
    if index == "exact" and (index_set or index_file):
        raise ConfigError("--index-set and --index-file apply to the faiss indexes (--index flat|ivf|ivfpq|hnsw)")
    if sequence_length > 1 and index != "exact":
        raise ConfigError("--sequence-length needs the full similarity matrix; use --index exact")
    return parse_index_settings(index, list(index_set)) if index != "exact" else None


@dataclass(frozen=True)
class SearchSettings:
    """How references are ranked: ``index`` (faiss :class:`~fdnet.matching.index.IndexSettings`,
    or None for exact search), ``sequence_length`` (SeqSLAM sequences, exact search only; 1 =
    single images) and ``index_file`` (where a built index is kept and reloaded)."""

    index: object = None
    sequence_length: int = 1
    index_file: str | None = None


def rank_references(
    descriptor,
    ref_paths,
    query_paths,
    depth: int,
    search: SearchSettings | None = None,
    pipeline=None,
    log: Callable[[str], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``depth`` best references of each query (indices, scores; (Q, depth) each): exact
    search (by SeqSLAM sequence similarity when ``search.sequence_length`` > 1) when
    ``search.index`` is None, else through a faiss index built chunk by chunk from the map (or
    loaded from ``search.index_file`` when it holds this map's index; saved there when built):
    the references become a :class:`~fdnet.matching.place_map.PlaceMap`, searched by its one
    batch search, as a place database's are.
    ``pipeline``: :class:`~fdnet.descriptors.pipeline.PipelineSettings` (default: batches of 64,
    a progress bar)."""
    from fdnet.descriptors.base import describe_paths
    from fdnet.descriptors.pipeline import PipelineSettings

    search = search or SearchSettings()
    pipeline = pipeline or PipelineSettings(batch_size=64, progress=True)
    settings, sequence_length = search.index, search.sequence_length

    def describe(paths):
        return describe_paths(
            descriptor, paths, pipeline.batch_size, progress=pipeline.progress, workers=pipeline.workers
        )

    from fdnet.matching.place_map import PlaceMap

    names = [str(p) for p in ref_paths]
    if settings is None:
        references = PlaceMap.of_vectors(names, describe(ref_paths))
    else:
        if not descriptor.dot_product_similarity:
            raise ConfigError(
                f"method {descriptor.name!r} does not compare vectors by dot product, so a "
                "faiss index would rank by the wrong measure; use --index exact"
            )
        references = PlaceMap.of_vectors(
            names, index=_build_or_load(descriptor, ref_paths, search, pipeline, log or logger.info)
        )
    return references.search(
        describe(query_paths), depth, similarity=descriptor.similarity, sequence_length=sequence_length
    )


def _build_or_load(descriptor, ref_paths, search: SearchSettings, pipeline, say):
    import time

    from fdnet.descriptors.pipeline import describe_stream
    from fdnet.matching.index import VectorIndex

    settings, index_file = search.index, search.index_file
    index = cached_index(index_file, descriptor, ref_paths, settings, say) if index_file else None
    if index is not None:
        say(f"loaded the {settings.kind} index of {len(ref_paths)} references from {index_file}")
        return index
    index = VectorIndex(descriptor.dim, settings)
    for _, vectors in describe_stream(descriptor, ref_paths, pipeline):
        index.add(vectors)  # the map goes into the index chunk by chunk
    t0 = time.perf_counter()
    index.build()
    built = time.perf_counter() - t0
    if index_file:
        index.save(
            index_file,
            metadata={
                "fingerprint": descriptor.fingerprint(),
                "references": map_digest(ref_paths),
                "method": descriptor.name,
            },
        )
        say(f"built the {settings.kind} index of {len(ref_paths)} references ({built:.1f} s), saved to {index_file}")
    return index
