"""`fdnet database`: a persistent place database (one SQLite file) for loop closure and
relocalisation. See docs/database.md for the format and its guarantees."""

from __future__ import annotations

import argparse

from fdnet.matching.index import INDEX_KINDS
from fdnet.cli.common import (
    acceptance_from_arguments, add_decision_arguments, add_device_argument, add_method_arguments, add_pipeline_arguments,
)


def _positive_int(text: str) -> int:
    value = _whole_number(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    value = _whole_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def _finite_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):  # nan would keep no row, inf all or none
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _whole_number(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None


def register(sub) -> None:
    from fdnet.cli.flags import add_old_spelling

    p = sub.add_parser("database", help="build, extend, query, inspect and migrate a persistent place database")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    build = actions.add_parser("build", help="describe a folder of images and write them as a new database file")
    build.add_argument("--images", required=True, help="folder of map images (traversal order)")
    build.add_argument("--db", required=True, help="database file to write, e.g. map.db")
    build.add_argument("--overwrite", action="store_true",
                       help="replace an existing place database at --db (in one transaction)")
    add_method_arguments(build)
    build.add_argument("--index", choices=list(INDEX_KINDS), default="flat",
                       help="faiss index for dot-product methods: flat = exact (default); ivf (IVF-Flat), "
                            "ivfpq (IVF-PQ, compressed) and hnsw are approximate, for maps of 10^5-10^6 places. "
                            "Approximate indexes are built at the end of build and cached beside the file "
                            "(FILE.fdnet-index, derived data: deleting it only costs a rebuild)")
    build.add_argument("--index-set", action="append", default=[], metavar="KEY=VALUE",
                       help="an index setting (repeatable): ivf_lists, ivf_probe, pq_bytes, refine, train_points, "
                            "hnsw_neighbors, hnsw_ef_construction, hnsw_ef_search (see docs/performance.md)")
    add_pipeline_arguments(build)
    add_device_argument(build)
    add_old_spelling(build, "--out", "--db")
    build.set_defaults(func=run_build)

    add = actions.add_parser(
        "add", help="describe more images and append them to a database (one transaction)",
        description="Describe the images with the descriptor the database records and append them in one "
                    "transaction. The method options are optional: give them to describe with another copy of "
                    "that model (e.g. its run directory moved); its fingerprint must match the database's.")
    add.add_argument("--db", required=True, help="database file")
    add.add_argument("--images", required=True, help="folder of images to append")
    add.add_argument("--allow-duplicates", action="store_true",
                     help="add images whose name is already in the database (default: skip and report them)")
    add_method_arguments(add, required=False)
    add_pipeline_arguments(add)
    add_device_argument(add)
    add.set_defaults(func=run_add)

    query = actions.add_parser("query", help="rank the database's places for each query image")
    query.add_argument("--db", required=True, help="database file")
    query.add_argument("--images", required=True, help="folder of query images")
    query.add_argument("--top-k", type=_positive_int, default=5, help="candidates per query (at least 1)")
    query.add_argument("--exclude-last", type=_non_negative_int, default=0,
                       help="ignore the most recently added N places (a robot's own recent frames)")
    query.add_argument("--min-score", type=_finite_number, default=None, help="only report candidates scoring at least this")
    add_decision_arguments(query, "a calibration from `fdnet calibrate` (default: the one stored in the database by "
                                  "`fdnet calibrate --db`, if any): adds acceptance_score and accepted columns")
    query.add_argument("--out", help="CSV to write (query,rank,place,place_index,score[,acceptance_score,accepted]); "
                                     "default: print")
    add_pipeline_arguments(query)
    add_device_argument(query)
    query.set_defaults(func=run_query)

    info = actions.add_parser("info", help="print the database's identity and size as one JSON object")
    info.add_argument("--db", required=True, help="database file")
    info.set_defaults(func=run_info)

    migrate = actions.add_parser("migrate", help="convert an old-format folder (database.json + vectors.npy) "
                                                 "into a database file")
    migrate.add_argument("--from", dest="source", required=True, help="old-format database folder")
    migrate.add_argument("--db", required=True, help="database file to write, e.g. map.db")
    migrate.add_argument("--overwrite", action="store_true", help="replace an existing place database at --db")
    add_old_spelling(migrate, "--out", "--db")
    migrate.set_defaults(func=run_migrate)


def _describe(descriptor, paths, args):
    from fdnet.descriptors.base import describe_paths

    return describe_paths(descriptor, paths, args.batch_size, progress=True, workers=args.workers)


def _spool(descriptor, paths, args, folder):
    """Describe ``paths`` through the streaming pipeline into a spool file in ``folder`` (a few
    batches in memory whatever the folder's size). Non-finite vectors stop it here, naming the
    images, before the database is touched."""
    from fdnet.descriptors.pipeline import VectorSpool, describe_stream
    from fdnet.errors import DataError

    import numpy as np

    spool = VectorSpool(folder, descriptor.dim)
    try:
        for start, vectors in describe_stream(descriptor, paths, args.batch_size, workers=args.workers,
                                              progress=True):
            vectors = np.asarray(vectors, dtype=np.float32)
            bad = np.flatnonzero(~np.isfinite(vectors).all(axis=1))
            if len(bad):
                listed = ", ".join(str(paths[start + i]) for i in bad[:5])
                raise DataError(f"refusing {len(bad)} non-finite vector(s) (NaN or inf) for {listed}; "
                                "nothing was added (a NaN place can never be matched)")
            spool.write(vectors)
    except BaseException:
        spool.close()
        raise
    return spool


def _spooled_batches(spool, names, paths=None):
    """``(vectors, names)`` chunks; with ``paths`` that include frames of a video or bag,
    ``(vectors, names, positions, metadata)``: each frame's source and timestamp as metadata (the
    ``timestamp`` loop closure's ``radius_s`` reads) and a bag's interpolated position in metres."""
    positions = metadata = None
    if paths is not None:
        from pathlib import Path

        from fdnet.data.sources import frame_records, positions_in_metres

        records = frame_records(paths)
        if any(r.timestamp is not None for r in records):
            positions = positions_in_metres(records)
            metadata = [None if r.timestamp is None else
                        {"source": str(Path(r.source).resolve()), "timestamp": r.timestamp,
                         **({"topic": r.topic} if r.topic else {})}
                        for r in records]
    for start, vectors in spool.chunks():
        end = start + len(vectors)
        if metadata is None:
            yield vectors, names[start:end]
        else:
            yield vectors, names[start:end], positions[start:end], metadata[start:end]


def _place_names(paths) -> list[str]:
    # Absolute: the same image added from another working directory is still the same place.
    import os

    from fdnet.errors import DataError

    names = [str(p.resolve()) for p in paths]
    for name in names:  # SQLite text is UTF-8: refuse before anything is described or created
        try:
            name.encode("utf-8")
        except UnicodeEncodeError:
            raise DataError(f"{os.fsencode(name)!r}: the file name is not valid UTF-8, which a place database "
                            f"cannot store as a place name; rename the file") from None
    return names


def _file_options(args, method: str) -> dict:
    from pathlib import Path

    from fdnet.cli.common import FILE_OPTIONS, method_options

    options = method_options(args, method)
    # Absolute paths: later `add`/`query` calls may run from another directory.
    options.update({k: str(Path(v).resolve()) for k, v in options.items() if k in FILE_OPTIONS})
    # --method-set device=...: where it runs is the command's business, not the database's
    options.pop("device", None)
    return options


def _recorded_descriptor(db, args=None):
    """The descriptor the database's method_options rebuild; its fingerprint must still be the
    database's (weights retrained in place, or a vocabulary replaced, would change it)."""
    from fdnet.descriptors import create
    from fdnet.errors import ConfigError, FdnetError

    try:
        return create(db.method, **db.method_options, **(_device(args) if args is not None else {}))
    except FdnetError as exc:
        raise ConfigError(f"{db.path}: cannot rebuild its {db.method!r} descriptor from the recorded options "
                          f"{db.method_options} ({exc})") from None


def _open_with_descriptor(path, args=None, device_args=None):
    from fdnet.cli.common import FILE_OPTIONS
    from fdnet.matching.database import PlaceDatabase

    with PlaceDatabase.open(path) as recorded:
        given = args is not None and (args.method or args.method_set
                                      or any(getattr(args, k) for k in FILE_OPTIONS))
        descriptor = (_create_descriptor(args.method or recorded.method, args) if given
                      else _recorded_descriptor(recorded, device_args or args))
    return PlaceDatabase.open(path, descriptor=descriptor), descriptor


def _create_descriptor(method: str, args):
    from fdnet.descriptors import create

    return create(method, **_file_options(args, method), **_device(args))


def _device(args) -> dict:
    # where it runs is not what it is: never stored in the database's method_options
    return {"device": args.device} if getattr(args, "device", None) else {}


def run_build(args) -> int:
    import time
    from pathlib import Path

    from fdnet.cli.common import check_pipeline_arguments
    from fdnet.data.images import list_images
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable
    from fdnet.matching.database import PlaceDatabase, check_can_create, short_fingerprint
    from fdnet.matching.index import parse_index_settings

    # Every refusal the output path can cause comes before minutes of describing images.
    check_pipeline_arguments(args)
    index = parse_index_settings(args.index, args.index_set)
    check_can_create(args.db, args.overwrite)
    ensure_writable(args.db, what="place database")
    descriptor = _create_descriptor(args.method, args)
    if descriptor.needs_fit:
        raise ConfigError(f"method {descriptor.name!r} must be given what it learns from (--fit DIR, or dbow's --vocabulary) "
                          "to build a database that later queries can reuse")
    if index.kind != "flat" and not descriptor.dot_product_similarity:
        raise ConfigError(f"--index {index.kind}: method {descriptor.name!r} does not compare vectors by dot "
                          "product, so it is searched exhaustively with its own similarity; use --index flat")
    paths = list_images(args.images)
    names = _place_names(paths)
    with _spool(descriptor, paths, args, Path(args.db).resolve().parent) as spool:
        db = PlaceDatabase.create(args.db, descriptor, index=index,
                                  method_options=_file_options(args, args.method), overwrite=args.overwrite,
                                  batches=_spooled_batches(spool, names, paths))
    with db:
        places = len(db)
        note = ""
        if db.index_cache_path is not None and places:
            t0 = time.perf_counter()
            built = db.build_index()
            note = (f"; {index.kind} index built in {time.perf_counter() - t0:.1f} s"
                    + (f", cached in {db.index_cache_path}" if db.index_cache_path.exists() else "")
                    if built is not None else "")
    print(f"wrote {args.db}: {places} places, {descriptor.name} ({descriptor.dim}-d), "
          f"fingerprint {short_fingerprint(db.fingerprint)}{note}")
    return 0


def run_add(args) -> int:
    from pathlib import Path

    from fdnet.cli.common import check_pipeline_arguments
    from fdnet.data.images import list_images

    check_pipeline_arguments(args)
    db, descriptor = _open_with_descriptor(args.db, args)
    with db:
        if db.read_only:
            from fdnet.errors import DataError

            raise DataError(f"{args.db}: its folder cannot be written (read-only media or mount), so nothing can be "
                            "added; copy it to a writable folder")
        paths = list_images(args.images)
        names = _place_names(paths)
        known = set() if args.allow_duplicates else db.existing_names(names)
        todo = [i for i, name in enumerate(names) if name not in known]
        # described into a spool first (bounded memory), then stored in ONE transaction
        with _spool(descriptor, [paths[i] for i in todo], args, Path(args.db).resolve().parent) as spool:
            result = db.add_batches(_spooled_batches(spool, [names[i] for i in todo], [paths[i] for i in todo]),
                                    fingerprint=descriptor.fingerprints(), allow_duplicates=args.allow_duplicates)
    skipped = len(known) + len(result.skipped)
    note = f" (skipped {skipped} already in the database; --allow-duplicates adds them)" if skipped else ""
    print(f"{args.db}: added {result.added} places{note}, {result.places} in all, data version {result.data_version}")
    return 0


def run_query(args) -> int:
    import csv
    import io
    import sys

    import numpy as np

    from fdnet.data.images import list_images
    from fdnet.errors import DataError
    from fdnet.io import atomic_write_text, ensure_writable, spreadsheet_text

    from fdnet.cli.common import check_pipeline_arguments

    check_pipeline_arguments(args)
    if args.out:
        ensure_writable(args.out, what="query CSV")
    spec = acceptance_from_arguments(args)
    db, descriptor = _open_with_descriptor(args.db, device_args=args)
    _note_read_only(db)
    with db:
        calibration = None if spec is not None else _query_calibration(db, descriptor, args)
        rule = spec if spec is not None else (calibration.spec if calibration is not None else None)
        depth = args.top_k if rule is None else max(args.top_k, rule.depth)
        paths = list_images(args.images)
        vectors = _describe(descriptor, paths, args)
        bad = np.flatnonzero(~np.isfinite(vectors).all(axis=1))
        if len(bad):
            raise DataError(f"{paths[bad[0]]}: its {descriptor.name} vector is not finite (NaN or inf); "
                            f"{len(bad)} query image(s) affected")
        results = db.query(vectors, k=depth, exclude_last=args.exclude_last)
        places = len(db)
        decision = accepted = None
        if calibration is not None:
            decision, accepted = calibration.decide(_candidates(db, descriptor, paths, results))
        elif spec is not None:
            from fdnet.decisions.acceptance import decide

            decision = decide(spec, _candidates(db, descriptor, paths, results))
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["query", "rank", "place", "place_index", "score"]
                    + ([] if decision is None else ["acceptance_score"]) + ([] if accepted is None else ["accepted"]))
    for q, (path, matches) in enumerate(zip(paths, results)):
        for rank, m in enumerate(matches, start=1):
            chosen = accepted is not None and m.index == decision.match[q] and bool(accepted[q])
            if (args.min_score is None or m.score >= args.min_score) and (rank <= args.top_k or chosen):
                row = [spreadsheet_text(path.name), rank, spreadsheet_text(m.name), m.index, f"{m.score:.6f}"]
                if decision is not None:
                    row.append(f"{decision.score[q]:.6f}")
                if accepted is not None:
                    row.append(int(chosen))
                writer.writerow(row)
    if args.out:
        atomic_write_text(args.out, buffer.getvalue())
        print(f"wrote {args.out}: {len(paths)} queries against {places} places")
    else:
        sys.stdout.write(buffer.getvalue())
    return 0


def _note_read_only(db) -> None:
    import sys

    if db.read_only:
        print(f"note: {db.path} is in a folder that cannot be written (read-only media or mount): opened "
              "read-only; query and info work, add does not", file=sys.stderr)


def _query_calibration(db, descriptor, args):
    """``--calibration``, else the database's stored calibration, else None; checked against the
    descriptor (another model's calibration is an error)."""
    import sys

    from fdnet.decisions.calibration import DATABASE_KEY, Calibration, load_calibration

    if args.calibration:
        calibration, source = load_calibration(args.calibration), args.calibration
    else:
        stored = db.get_metadata(DATABASE_KEY)
        if stored is None:
            return None
        source = f"{args.db} (stored calibration)"
        calibration = Calibration.from_dict(stored, source=source)
        print(f"using the calibration stored in {args.db}: rule {calibration.rule}, threshold "
              f"{calibration.threshold:.6g} (precision {calibration.target_precision:g})", file=sys.stderr)
    calibration.check(descriptor, sequence_length=0, source=source)
    return calibration


def _candidates(db, descriptor, paths, results):
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
    positions = db.positions
    metadata = db.metadata
    times = [None if not isinstance(m, dict) else m.get("timestamp") for m in metadata]
    return Candidates(
        idx, scores, similarity_ceiling=float(descriptor.similarity_ceiling),
        reference_positions=np.asarray(positions, dtype=float) if positions and all(p is not None for p in positions)
        else None,
        reference_times=np.asarray(times, dtype=float) if times and all(isinstance(t, (int, float)) and
                                                                        not isinstance(t, bool) for t in times)
        else None,
        query_paths=list(paths), reference_paths=None)


def run_info(args) -> int:
    import json

    from fdnet.matching.database import PlaceDatabase

    with PlaceDatabase.open(args.db) as db:
        info = db.info()
        _note_read_only(db)
    print(json.dumps(info, indent=2, sort_keys=True))
    return 0


def run_migrate(args) -> int:
    from fdnet.io import ensure_writable
    from fdnet.matching.database import check_can_create, migrate_old_format

    check_can_create(args.db, args.overwrite)
    ensure_writable(args.db, what="place database")
    report = migrate_old_format(args.source, args.db, overwrite=args.overwrite)
    print(f"wrote {args.db}: {report.places} places from {args.source}")
    if report.dropped_non_finite:
        listed = ", ".join(report.dropped_non_finite[:5])
        more = f" and {len(report.dropped_non_finite) - 5} more" if len(report.dropped_non_finite) > 5 else ""
        print(f"dropped {len(report.dropped_non_finite)} place(s) whose stored vector was NaN/inf "
              f"(they could never be matched): {listed}{more}")
    if report.duplicate_names:
        print(f"kept {report.duplicate_names} repeated place name(s), as the old database held them")
    return 0
