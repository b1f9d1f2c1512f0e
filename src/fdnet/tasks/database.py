"""The work of ``fdnet database build|add|query|info`` as library functions: describe a folder of
images into a new database or onto an existing one, rank a database's places for query images
(with a calibrated or rule-scored decision), report a database's identity. Each returns what the
command reports; messages go to ``log`` (default: this module's logger). Above
:mod:`fdnet.matching.database` (the file) and :mod:`fdnet.decisions` (the rules), which it
drives.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence, Union

import numpy as np

from fdnet.data.images import image_name
from fdnet.descriptors.pipeline import PipelineSettings

logger = logging.getLogger(__name__)

#: a method's options: a mapping, or a function of the method's name giving them (for ``add``,
#: where the method may be the database's own, known only once it is open)
MethodOptions = Union[Mapping, Callable[[str], Mapping], None]
Log = Callable[[str], None]


@dataclass(frozen=True)
class BuildSummary:
    """What :func:`build_database` wrote."""

    path: str
    places: int
    method: str
    dim: int
    fingerprint: str
    index_kind: str
    index_seconds: float | None = None  # None: no approximate index was built
    index_cache: str | None = None  # where it was cached, when it was

    def lines(self) -> list[str]:
        from fdnet.matching.database.identity import short_fingerprint

        note = ""
        if self.index_seconds is not None:
            note = f"; {self.index_kind} index built in {self.index_seconds:.1f} s" + (
                f", cached in {self.index_cache}" if self.index_cache is not None else ""
            )
        return [
            f"wrote {self.path}: {self.places} places, {self.method} ({self.dim}-d), "
            f"fingerprint {short_fingerprint(self.fingerprint)}{note}"
        ]


@dataclass(frozen=True)
class AddSummary:
    """What :func:`add_to_database` appended."""

    path: str
    added: int
    skipped: int  # already in the database (by name), not added
    places: int
    data_version: int

    def lines(self) -> list[str]:
        note = (
            f" (skipped {self.skipped} already in the database; --allow-duplicates adds them)" if self.skipped else ""
        )
        return [f"{self.path}: added {self.added} places{note}, {self.places} in all, data version {self.data_version}"]


@dataclass(frozen=True)
class QueryResult:
    """:func:`query_database`'s ranked candidates, as arrays for a program and as the CSV text the
    command prints (also written to ``out`` when given). ``indices`` (Q, top_k) place indices
    best first (-1 where fewer places), ``scores`` (Q, top_k) their similarities, ``place_names``
    the database's place names (index them with ``indices``), ``query_names`` the images asked
    about; with a rule or calibration ``acceptance_scores`` (Q,) and ``matches`` (Q,) the place
    its rule vouches for, and with a calibration ``accepted`` (Q,) bool."""

    csv_text: str
    queries: int
    places: int
    out: str | None = None
    indices: np.ndarray | None = None
    scores: np.ndarray | None = None
    query_names: list | None = None
    place_names: list | None = None
    acceptance_scores: np.ndarray | None = None
    matches: np.ndarray | None = None
    accepted: np.ndarray | None = None

    def lines(self) -> list[str]:
        return [f"wrote {self.out}: {self.queries} queries against {self.places} places"] if self.out else []


#: the database metadata key (:meth:`PlaceDatabase.set_metadata`) recording how a database was
#: built: ``{"world_size": N}`` when N processes described its images under torchrun (absent when
#: one process did, as for every database built before)
BUILD_KEY = "build"


def _pipeline() -> PipelineSettings:
    return PipelineSettings(batch_size=64, progress=True)


@dataclass(frozen=True)
class BuildRequest:
    """``fdnet database build``: describe the images of ``images`` (traversal order) with
    ``method`` into a new database file ``db``; ``method_options`` (file paths absolute; or a
    function of the method's name giving them) are recorded so later ``add`` and ``query`` calls
    rebuild the descriptor; ``device`` is where it runs, never recorded; ``index`` (flat, hnsw,
    ivf, ivfpq) with ``index_set`` (KEY=VALUE)."""

    images: str
    db: str
    method: str
    method_options: MethodOptions = None
    device: str | None = None
    overwrite: bool = False
    index: str = "flat"
    index_set: Sequence[str] = ()
    pipeline: PipelineSettings = field(default_factory=_pipeline)


@dataclass(frozen=True)
class AddRequest:
    """``fdnet database add``: describe the images of ``images`` and append them to ``db``,
    skipping names already there unless ``allow_duplicates``; with neither ``method`` nor
    ``method_options`` the descriptor is the one the database records."""

    db: str
    images: str
    method: str | None = None
    method_options: MethodOptions = None
    device: str | None = None
    allow_duplicates: bool = False
    pipeline: PipelineSettings = field(default_factory=_pipeline)


@dataclass(frozen=True)
class QueryRequest:
    """``fdnet database query``: rank ``db``'s places for each image of ``images``: ``top_k``
    candidates per query (the ``exclude_last`` most recent places ignored, those under
    ``min_score`` left out); ``accept`` (an AcceptanceSpec) or ``calibration`` (a file or run
    folder; default: the one stored in the database) decide; written to ``out`` when given."""

    db: str
    images: str
    top_k: int = 5
    exclude_last: int = 0
    min_score: float | None = None
    accept: object = None
    calibration: str | None = None
    out: str | None = None
    device: str | None = None
    pipeline: PipelineSettings = field(default_factory=_pipeline)


def build_database(request: BuildRequest) -> BuildSummary:
    """Describe ``request.images`` and write them as a new database file (:class:`BuildRequest`).
    Approximate indexes (hnsw, ivf, ivfpq) are built at the end and cached beside the file.

    Under torchrun (:mod:`fdnet.descriptors.sharding`) each process describes its block of the
    images and rank 0 alone writes the database, in one transaction as one process does, and
    builds its index on all the vectors; its metadata ``build`` records ``world_size``. Every
    process returns the summary (the others' without the index's timing)."""
    from fdnet.descriptors.sharding import check_same_inputs, current
    from fdnet.matching.database.store import PlaceDatabase

    shards = current()
    db = request.db
    settings, descriptor, paths, names = shards.collectively(
        lambda: _build_inputs(request, check_output=shards.is_main)
    )
    check_same_inputs(shards, paths, descriptor)
    with _spool(descriptor, paths, request.pipeline, Path(db).resolve().parent, shards) as spool:
        if not shards.is_main:
            return BuildSummary(
                str(db), len(paths), descriptor.name, descriptor.dim, descriptor.fingerprint(), settings.kind
            )
        database = PlaceDatabase.create(
            db,
            descriptor,
            index=settings,
            method_options=_options_for(request.method_options, request.method),
            overwrite=request.overwrite,
            places=_spooled_batches(spool, names, paths),
        )
    return _finish_build(db, database, descriptor, settings, shards.world_size)


def _build_inputs(request: BuildRequest, check_output=True):
    """``(index settings, descriptor, paths, place names)`` for :func:`build_database`, every
    refusal the output path can cause first (``check_output``), before minutes of describing."""
    from fdnet.data.images import list_images
    from fdnet.descriptors.sharding import current
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable
    from fdnet.matching.database.storage import check_can_create
    from fdnet.matching.index import parse_index_settings

    settings = parse_index_settings(request.index, list(request.index_set))
    if check_output:
        check_can_create(request.db, request.overwrite)
        ensure_writable(request.db, what="place database")
    descriptor = _create_descriptor(request.method, request.method_options, request.device)
    if descriptor.needs_fit:
        raise ConfigError(
            f"method {descriptor.name!r} must be given what it learns from (--fit DIR, or dbow's "
            "--vocabulary) to build a database that later queries can reuse"
        )
    if settings.kind != "flat" and not descriptor.dot_product_similarity:
        raise ConfigError(
            f"--index {settings.kind}: method {descriptor.name!r} does not compare vectors by dot "
            "product, so it is searched exhaustively with its own similarity; use --index flat"
        )
    current().check_device(descriptor.device)  # under torchrun: this process's own GPU
    paths = list_images(request.images)
    return settings, descriptor, paths, _place_names(paths)


def _finish_build(db, database, descriptor, settings, world_size: int) -> BuildSummary:
    """Record how many processes built ``database`` (the file ``db``), build its approximate
    index (if any) and summarise."""
    import time

    seconds = cache = None
    with database:
        if world_size > 1:
            database.set_metadata(BUILD_KEY, {"world_size": int(world_size)})
        places = len(database)
        if database.index_cache_path is not None and places:
            t0 = time.perf_counter()
            built = database.build_index()
            if built is not None:
                seconds = time.perf_counter() - t0
                cache = str(database.index_cache_path) if database.index_cache_path.exists() else None
    return BuildSummary(
        str(db), places, descriptor.name, descriptor.dim, database.fingerprint, settings.kind, seconds, cache
    )


def add_to_database(request: AddRequest) -> AddSummary:
    """Describe ``request.images`` and append them to the database in one transaction
    (:class:`AddRequest`); with a method or its options, that copy of the model (its fingerprint
    must match the database's)."""
    from fdnet.data.images import list_images
    from fdnet.errors import DataError

    db, images, method, method_options = request.db, request.images, request.method, request.method_options
    allow_duplicates = request.allow_duplicates
    database, descriptor = open_with_descriptor(
        db,
        method=method,
        method_options=method_options,
        device=request.device,
        given=method is not None or method_options is not None,
    )
    with database:
        if database.read_only:
            raise DataError(
                f"{db}: its folder cannot be written (read-only media or mount), so nothing can be "
                "added; copy it to a writable folder"
            )
        paths = list_images(images)
        names = _place_names(paths)
        known = set() if allow_duplicates else database.existing_names(names)
        todo = [i for i, name in enumerate(names) if name not in known]
        # described into a spool first (bounded memory), then stored in ONE transaction
        with _spool(descriptor, [paths[i] for i in todo], request.pipeline, Path(db).resolve().parent) as spool:
            result = database.add_batches(
                _spooled_batches(spool, [names[i] for i in todo], [paths[i] for i in todo]),
                fingerprint=descriptor.fingerprint(),
                allow_duplicates=allow_duplicates,
            )
    return AddSummary(str(db), result.added, len(known) + len(result.skipped), result.places, result.data_version)


def query_database(request: QueryRequest, log: Log | None = None) -> QueryResult:
    """Rank the database's places for each query image (:class:`QueryRequest`) as CSV rows
    ``query,rank,place,place_index,score``. ``accept`` adds its ``acceptance_score`` column;
    else a calibration adds ``acceptance_score`` and ``accepted`` (the accepted match is listed
    even below ``top_k``). Written atomically to ``out`` when given."""
    import numpy as np

    from fdnet.data.images import list_images
    from fdnet.descriptors.base import check_vectors
    from fdnet.errors import ConfigError
    from fdnet.io import atomic_write_text, ensure_writable

    db, images, top_k, accept, out = request.db, request.images, request.top_k, request.accept, request.out
    exclude_last = request.exclude_last
    if isinstance(exclude_last, bool) or not isinstance(exclude_last, int) or exclude_last < 0:
        raise ConfigError(f"{db}: exclude-last must be a whole number of at least 0, got {exclude_last!r}")
    log = log or logger.info
    if out:
        ensure_writable(out, what="query CSV")
    database, descriptor = open_with_descriptor(db, device=request.device)
    _note_read_only(database, log)
    with database:
        calibrated = (
            None if accept is not None else _query_calibration(database, descriptor, request.calibration, db, log)
        )
        rule = accept if accept is not None else (calibrated.spec if calibrated is not None else None)
        depth = top_k if rule is None else max(top_k, rule.depth)
        paths = list_images(images)
        vectors = _describe(descriptor, paths, request.pipeline)
        check_vectors(vectors, f"{descriptor.name} query vectors", lambda i: str(paths[i]), directions=False)
        # the most recent places (a robot's own last frames) are not searched
        results = database.query(vectors, k=depth, searchable=max(len(database) - exclude_last, 0))
        places = len(database)
        decision = accepted = None
        if calibrated is not None:
            decision, accepted = calibrated.decide(_candidates(database, descriptor, paths, results))
        elif accept is not None:
            from fdnet.decisions.acceptance import decide

            decision = decide(accept, _candidates(database, descriptor, paths, results))
        place_names = list(database.names)
    text = _query_csv(paths, results, top_k, request.min_score, decision, accepted)
    if out:
        atomic_write_text(out, text)
    indices = np.full((len(paths), top_k), -1, dtype=np.int64)
    scores = np.full((len(paths), top_k), np.nan, dtype=np.float32)
    for q, matches in enumerate(results):
        for rank, m in enumerate(matches[:top_k]):
            indices[q, rank], scores[q, rank] = m.index, m.score
    return QueryResult(
        text,
        len(paths),
        places,
        str(out) if out else None,
        indices=indices,
        scores=scores,
        query_names=[image_name(p) for p in paths],
        place_names=place_names,
        acceptance_scores=None if decision is None else np.asarray(decision.score, np.float64),
        matches=None if decision is None else np.asarray(decision.match, np.int64),
        accepted=None if accepted is None else np.asarray(accepted, bool),
    )


def database_info(db, log: Log | None = None) -> dict:
    """The database's identity and size (:meth:`PlaceDatabase.info`)."""
    from fdnet.matching.database.store import PlaceDatabase

    with PlaceDatabase.open(db) as database:
        info = database.info()
        build = database.get_metadata(BUILD_KEY)
        if build is not None:  # built by several processes (torchrun)
            info["build"] = build
        _note_read_only(database, log or logger.info)
    return info


def open_with_descriptor(
    db,
    *,
    method: str | None = None,
    method_options: MethodOptions = None,
    device: str | None = None,
    given: bool = False,
):
    """``(database, descriptor)``: ``db`` opened with the descriptor it records (rebuilt from its
    method_options), or with ``given``, ``method`` (default: the recorded one) made with
    ``method_options``; either way checked against the database's fingerprint on opening."""
    from fdnet.matching.database.store import PlaceDatabase

    with PlaceDatabase.open(db) as recorded:
        if given:
            descriptor = _create_descriptor(method or recorded.method, method_options, device)
        else:
            descriptor = recorded_descriptor(recorded, device)
    return PlaceDatabase.open(db, descriptor=descriptor), descriptor


def recorded_descriptor(database, device: str | None = None):
    """The descriptor the database's method_options rebuild; its fingerprint must still be the
    database's (weights retrained in place, or a vocabulary replaced, would change it)."""
    from fdnet.descriptors import create
    from fdnet.errors import ConfigError, FdnetError

    try:
        return create(database.method, **database.method_options, **_device(device))
    except FdnetError as exc:
        raise ConfigError(
            f"{database.path}: cannot rebuild its {database.method!r} descriptor from the recorded "
            f"options {database.method_options} ({exc})"
        ) from exc


def _options_for(method_options: MethodOptions, method: str) -> dict:
    if method_options is None:
        return {}
    return dict(method_options(method) if callable(method_options) else method_options)


def _create_descriptor(method: str, method_options: MethodOptions, device: str | None):
    from fdnet.descriptors import create

    return create(method, **_options_for(method_options, method), **_device(device))


def _device(device: str | None) -> dict:
    # where it runs is not what it is: never stored in the database's method_options
    return {"device": device} if device else {}


def _note_read_only(database, log: Log) -> None:
    if database.read_only:
        log(
            f"note: {database.path} is in a folder that cannot be written (read-only media or mount): opened "
            "read-only; query and info work, add does not"
        )


def _describe(descriptor, paths, pipeline: PipelineSettings):
    from fdnet.descriptors.base import describe_paths

    return describe_paths(descriptor, paths, pipeline.batch_size, progress=pipeline.progress, workers=pipeline.workers)


def _spool(descriptor, paths, pipeline: PipelineSettings, folder, shards=None):
    """Describe ``paths`` through the streaming pipeline into a spool file in ``folder`` (a few
    batches in memory whatever the folder's size). Non-finite vectors stop it here, naming the
    images, before the database is touched. Under torchrun (``shards``, default: the running
    launch's) every process describes its block and rank 0's spool receives every vector; the
    other processes get an empty ``with`` block's context (None)."""
    import contextlib

    from fdnet.descriptors.pipeline import VectorSpool
    from fdnet.descriptors.sharding import BlockOutput, current, describe_blocks

    shards = shards or current()
    spool = shards.collectively(lambda: VectorSpool(folder, descriptor.dim) if shards.is_main else None)
    try:
        output = BlockOutput(
            [descriptor.dim],
            lambda start, arrays: spool.write(arrays[0]),
            check=lambda start, arrays: _refuse_non_finite(paths, start, arrays[0], descriptor),
        )
        describe_blocks(shards, descriptor, paths, output, pipeline)
    except BaseException:
        if spool is not None:
            spool.close()
        raise
    return spool if spool is not None else contextlib.nullcontext()


def _refuse_non_finite(paths, start: int, vectors, descriptor) -> None:
    """The batch's vectors through the one guard of vectors coming in (NaN, infinity, and for
    dot-product methods an all-zero vector, which no query could ever match), naming the image."""
    from fdnet.descriptors.base import check_vectors

    check_vectors(
        vectors,
        f"nothing was added ({descriptor.name} vectors)",
        lambda i: str(paths[start + i]),
        directions=descriptor.dot_product_similarity,
    )


def _spooled_batches(spool, names, paths=None):
    """``(vectors, names)`` chunks; with ``paths`` that include frames of a video or bag,
    ``(vectors, names, positions, metadata)``: each frame's source and timestamp as metadata (the
    ``timestamp`` loop closure's ``radius_s`` reads) and a bag's interpolated position in metres."""
    positions = metadata = None
    if paths is not None:
        from fdnet.data.frame_records import frame_records, positions_in_metres

        records = frame_records(paths)
        if any(r.timestamp is not None for r in records):
            positions = positions_in_metres(records)
            metadata = [
                None
                if r.timestamp is None
                else {
                    "source": str(Path(r.source).resolve()),
                    "timestamp": r.timestamp,
                    **({"topic": r.topic} if r.topic else {}),
                }
                for r in records
            ]
    for start, vectors in spool.chunks():
        end = start + len(vectors)
        if metadata is None:
            yield vectors, names[start:end]
        else:
            yield vectors, names[start:end], positions[start:end], metadata[start:end]


def _place_names(paths) -> list[str]:
    """The place names of ``paths`` (:func:`~fdnet.matching.database.storage.place_name`), refused
    before anything is described or created when one is not UTF-8 (SQLite text is)."""
    from fdnet.matching.database.storage import check_place_names, place_name

    names = [place_name(p) for p in paths]
    check_place_names(names)
    return names


def _query_calibration(database, descriptor, calibration, db, log: Log):
    """``calibration`` (a file or run folder), else the database's stored calibration, else the
    one stored in the model's run directory (:func:`fdnet.decisions.calibration.stored_in_run`),
    else None; checked against the descriptor (another model's calibration is an error)."""
    from fdnet.decisions.calibration import DATABASE_KEY, Calibration, load_calibration, stored_in_run

    run_file = stored_in_run(descriptor.run_dir)
    stored = None if calibration else database.get_metadata(DATABASE_KEY)
    if calibration:
        calibrated, source = load_calibration(calibration), calibration
    elif stored is None and run_file is not None:  # the one rule: the database's, else the run's
        calibrated, source = load_calibration(run_file), str(run_file)
        log(
            f"using the calibration stored in the run, {run_file}: rule {calibrated.rule}, threshold "
            f"{calibrated.threshold:.6g} (it reached precision {calibrated.precision:.3f} on {calibrated.accepted} "
            f"accepted of {calibrated.num_queries} queries where it was measured; target "
            f"{calibrated.target_precision:g})"
        )
    else:
        if stored is None:
            return None
        source = f"{db} (stored calibration)"
        calibrated = Calibration.from_dict(stored, source=source)
        log(
            f"using the calibration stored in {db}: rule {calibrated.rule}, threshold "
            f"{calibrated.threshold:.6g} (it reached precision {calibrated.precision:.3f} on {calibrated.accepted} "
            f"accepted of {calibrated.num_queries} queries where it was measured; target "
            f"{calibrated.target_precision:g})"
        )
    calibrated.check(descriptor, sequence_length=1, source=source)
    return calibrated


def _candidates(database, descriptor, paths, results):
    """The database's answers as ranked candidates for the acceptance rules: place indices
    (insertion order) padded with -1, the places' positions when every place has one, and their
    times when every place's metadata has a numeric ``timestamp``."""
    import numpy as np

    from fdnet.decisions.acceptance import Candidates

    k = max((len(m) for m in results), default=0) or 1
    idx = np.full((len(results), k), -1, dtype=np.int64)
    scores = np.zeros((len(results), k))
    for q, matches in enumerate(results):
        for j, m in enumerate(matches):
            idx[q, j], scores[q, j] = m.index, m.score
    positions = database.positions
    metadata = database.metadata
    times = [None if not isinstance(m, dict) else m.get("timestamp") for m in metadata]
    return Candidates(
        idx,
        scores,
        similarity_ceiling=float(descriptor.similarity_ceiling),
        reference_positions=np.asarray(positions, dtype=float)
        if positions and all(p is not None for p in positions)
        else None,
        reference_times=np.asarray(times, dtype=float)
        if times and all(isinstance(t, (int, float)) and not isinstance(t, bool) for t in times)
        else None,
        query_paths=list(paths),
        reference_paths=None,
    )


def _query_csv(paths, results, top_k, min_score, decision, accepted) -> str:
    """The query CSV: ``top_k`` rows per query scoring at least ``min_score``, plus the accepted
    match when a calibrated decision took one below ``top_k``."""
    import csv
    import io

    from fdnet.io import spreadsheet_text
    from fdnet.tasks.match import decision_cells, decision_columns

    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(
        ["query_index", "query", "rank", "place", "place_index", "score"] + decision_columns(decision, accepted)
    )
    for q, (path, matches) in enumerate(zip(paths, results)):
        for rank, m in enumerate(matches, start=1):
            chosen = accepted is not None and m.index == decision.match[q] and bool(accepted[q])
            if (min_score is None or m.score >= min_score) and (rank <= top_k or chosen):
                row = [q, spreadsheet_text(image_name(path)), rank, spreadsheet_text(m.name), m.index, f"{m.score:.6f}"]
                writer.writerow(row + decision_cells(q, chosen, decision, accepted))
    return buffer.getvalue()
