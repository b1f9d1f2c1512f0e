"""A persistent place database for loop closure and relocalisation, in one SQLite file.

Holds one vector per place with its name (image file), optional position and metadata, and
answers "which stored places look like this?" with ranked candidates and scores. The file also
records which descriptor made its vectors (method, settings, the options that rebuild it, and a
fingerprint of its weights), so vectors from another model are refused instead of mixed in.

The package, by concern:

* :mod:`~fdnet.matching.database.store`: :class:`PlaceDatabase` (make, open, add, query);
* :mod:`~fdnet.matching.database.storage`: the SQLite file (schema, connections, transactions,
  checks before a file is created or opened);
* :mod:`~fdnet.matching.database.identity`: which model made the vectors (fingerprints);
* :mod:`~fdnet.matching.database.index_cache`: the derived search index cached beside the file;
* :mod:`~fdnet.matching.database.vector_store`: from ``compressed_from`` places, the vectors in
  a file beside it searched through compressed codes, cached by
  :mod:`~fdnet.matching.database.codes_cache`;
* :mod:`~fdnet.matching.database.places`: a batch of places checked and inserted.

``fdnet database build|add|query|info`` as library functions (describe images into a
database, rank its places for queries, decide) are :mod:`fdnet.tasks.database`, above the
decisions they use.

See ``docs/database.md`` for the file format and the guarantees.
"""

from fdnet.matching.database.identity import short_fingerprint
from fdnet.matching.database.index_cache import INDEX_CACHE_SUFFIX
from fdnet.matching.database.storage import (
    APPLICATION_ID,
    BUSY_TIMEOUT_S,
    MEMORY,
    SCHEMA_VERSION,
    check_can_create,
    check_place_names,
    holds_a_database,
    place_name,
)
from fdnet.matching.database.store import AddResult, Match, PlaceDatabase

__all__ = [
    "APPLICATION_ID",
    "BUSY_TIMEOUT_S",
    "INDEX_CACHE_SUFFIX",
    "MEMORY",
    "SCHEMA_VERSION",
    "AddResult",
    "Match",
    "PlaceDatabase",
    "check_can_create",
    "check_place_names",
    "holds_a_database",
    "place_name",
    "short_fingerprint",
]
