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
* :mod:`~fdnet.matching.database.migration`: the old folder format and its conversion;
* :mod:`~fdnet.matching.database.places`: a batch of places checked and inserted.

``fdnet database build|add|query|info|migrate`` as library functions (describe images into a
database, rank its places for queries, decide) are :mod:`fdnet.tasks.database`, above the
decisions they use.

See ``docs/database.md`` for the file format and the guarantees.
"""

from fdnet.matching.database.identity import short_fingerprint
from fdnet.matching.database.index_cache import INDEX_CACHE_SUFFIX
from fdnet.matching.database.migration import MigrationReport, migrate_old_format, read_old_format
from fdnet.matching.database.storage import (
    APPLICATION_ID,
    BUSY_TIMEOUT_S,
    MEMORY,
    SCHEMA_VERSION,
    check_can_create,
    check_place_names,
    holds_a_database,
    place_name,
    migrate_command,
    refuse_old_format,
)
from fdnet.matching.database.store import AddResult, Match, PlaceDatabase

__all__ = [
    "APPLICATION_ID", "BUSY_TIMEOUT_S", "INDEX_CACHE_SUFFIX", "MEMORY", "SCHEMA_VERSION", "AddResult", "Match",
    "MigrationReport", "PlaceDatabase", "check_can_create", "check_place_names", "holds_a_database", "place_name", "migrate_command",
    "migrate_old_format", "read_old_format", "refuse_old_format", "short_fingerprint",
]
