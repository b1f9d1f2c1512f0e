"""The one in-memory map of places: what a place database has loaded and what the loop-closure
detector searches, append-only.

A :class:`PlaceMap` holds, per place in insertion order: its name, position (or None), metadata
(the stored JSON text, parsed on demand) and, when kept, its vector; and what loop closure reads
from the metadata (timestamp, the gates' flags, the recording it belongs to). Both
:class:`~fdnet.matching.database.PlaceDatabase` (which persists a map: load, append, commit) and
:class:`~fdnet.decisions.loop_closure.LoopClosureDetector` (gates, rule and consistency over a
map) hold one, so the two never keep parallel copies of the same columns.
"""

from __future__ import annotations

import json
import operator
from typing import Sequence

import numpy as np

from fdnet.errors import ConfigError


class GrowingArray:
    """Rows appended one at a time (capacity doubles, so adding N rows copies O(N) rows in all,
    where np.vstack per row would copy O(N^2)). With ``dim`` None it holds one value per place
    (bool unless ``dtype`` says otherwise)."""

    def __init__(self, dim: int | None, initial: np.ndarray | None = None, dtype=None):
        dtype = dtype if dtype is not None else bool if dim is None else np.float32
        shape = () if dim is None else (dim,)
        rows = np.zeros((0, *shape), dtype) if initial is None else np.asarray(initial, dtype)
        self._data = np.empty((max(1024, 2 * len(rows)), *shape), dtype=dtype)
        self._data[: len(rows)] = rows
        self._count = len(rows)

    def __len__(self) -> int:
        return self._count

    def append(self, row) -> None:
        if self._count == len(self._data):
            grown = np.empty((2 * len(self._data), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._count] = self._data[: self._count]
            self._data = grown
        self._data[self._count] = row
        self._count += 1

    def extend(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, dtype=self._data.dtype)
        need = self._count + len(rows)
        if need > len(self._data):
            grown = np.empty((max(2 * len(self._data), need), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._count] = self._data[: self._count]
            self._data = grown
        self._data[self._count : need] = rows
        self._count = need

    def truncate(self, count: int) -> None:
        """Forget the rows from ``count`` on."""
        self._count = min(int(count), self._count)

    def view(self, count: int | None = None) -> np.ndarray:
        return self._data[: self._count if count is None else count]


def _hash32(value) -> int:
    return hash(value) & 0xFFFF_FFFF


class _Column:
    """What the per-place columns below share: a column reads like a list of its values (indexes,
    slices to lists, iterates in blocks, compares equal to a list of the same values) and forgets
    only its last values. A column gives ``__len__``, ``extend``, ``truncate`` and
    ``_slice(start, stop)``: the values start..stop - 1 as a list, read at once."""

    def append(self, value) -> None:
        self.extend([value])

    def __getitem__(self, key):
        if isinstance(key, slice):
            rows = range(*key.indices(len(self)))
            if rows.step == 1:
                return self._slice(rows.start, max(rows.start, rows.stop))
            return [self._slice(i, i + 1)[0] for i in rows]
        i = operator.index(key)
        i = i + len(self) if i < 0 else i
        if not 0 <= i < len(self):
            raise IndexError(f"place {key} of {len(self)}")
        return self._slice(i, i + 1)[0]

    def __iter__(self):
        # in blocks, so iterating a long column never holds a decoded copy of all of it
        for start in range(0, len(self), 65_536):
            yield from self._slice(start, min(start + 65_536, len(self)))

    def __delitem__(self, key) -> None:
        if not isinstance(key, slice) or key.stop is not None or key.step not in (None, 1):
            raise TypeError("a column only forgets its last values: del column[count:]")
        self.truncate(key.indices(len(self))[0])

    def __eq__(self, other) -> bool:
        if isinstance(other, (_Column, list, tuple)):
            return len(self) == len(other) and list(self) == list(other)
        return NotImplemented

    __hash__ = None


class StringColumn(_Column):
    """Strings (or None) in insertion order, held as one UTF-8 byte buffer and each string's end
    offset: about 20 bytes a 16-character name, where a list of str objects costs about 70 and
    leaves the allocator one small object per place to keep (10^7 names loaded from a database
    held 0.7 GB so, and pinned more of the heap the load had freed). The offsets are 4 bytes
    until the buffer passes 4 GB, and a column that has held no string but "" or None keeps only
    its presence flags (a map's metadata when no place has any: 1 byte a place). Indexes, slices
    (to lists), iterates, and compares equal to a list of the same strings; :meth:`contains`
    looks a string up through a sorted array of 4-byte hashes and 4-byte places (8 bytes a
    string, where a set of str objects costs about 100; among 10^7 strings a lookup meets another's
    hash about once in 400). Any str round-trips, lone surrogates of undecodable file names
    included."""

    #: strings added after the hash index was sorted that are looked up in a dict before it is
    #: sorted again (a sort of 10^7 hashes takes about a second)
    UNSORTED = 65_536
    #: the largest end offset held in 4 bytes: past it the offsets become 8 bytes each
    NARROW_UP_TO = int(np.iinfo(np.uint32).max)

    def __init__(self, values: Sequence[str | None] = ()):
        self._bytes = GrowingArray(None, dtype=np.uint8)
        self._ends: GrowingArray | None = None  # None: every string so far is empty (ends all 0)
        self._present = GrowingArray(None, dtype=bool)
        self._hashes = self._order = None  # the sorted hash index, made by the first lookup
        self._sorted_up_to = 0  # the strings it covers: those after it are in _unsorted
        self._unsorted: dict[int, list[int]] = {}
        self.extend(values)

    def __len__(self) -> int:
        return len(self._present)

    def _end(self, count: int) -> int:
        return int(self._ends.view()[count - 1]) if count and self._ends is not None else 0

    def _ends_of(self, start: int, stop: int) -> np.ndarray:
        if self._ends is None:
            return np.zeros(stop - start, np.int64)
        return self._ends.view()[start:stop].astype(np.int64)

    def _extend_ends(self, first: int, ends: np.ndarray) -> None:
        """Append the end offsets of the strings from ``first`` on (int64 ``ends``)."""
        if self._ends is None:
            if not len(ends) or ends[-1] == 0:
                return  # still no byte in the buffer
            self._ends = GrowingArray(None, np.zeros(first, np.uint32), np.uint32)
        if self._ends.view().dtype == np.uint32 and len(ends) and ends[-1] > self.NARROW_UP_TO:
            self._ends = GrowingArray(None, self._ends.view().astype(np.int64), np.int64)
        self._ends.extend(ends)

    def extend(self, values) -> None:
        first = len(self)
        if isinstance(values, StringColumn):
            count = len(values)
            self._bytes.extend(values._bytes.view())
            self._extend_ends(first, values._ends_of(0, count) + self._end(first))
            self._present.extend(values._present.view())
        else:
            values = list(values)
            if not values:
                return
            encoded = [b"" if v is None else v.encode("utf-8", "surrogatepass") for v in values]
            lengths = np.fromiter((len(e) for e in encoded), np.int64, len(encoded))
            self._extend_ends(first, self._end(first) + np.cumsum(lengths))
            self._bytes.extend(np.frombuffer(b"".join(encoded), np.uint8))
            self._present.extend(np.fromiter((v is not None for v in values), bool, len(values)))
        if self._hashes is not None:
            for i, value in enumerate(self._range(first, len(self)), start=first):
                if value is not None:
                    self._unsorted.setdefault(_hash32(value), []).append(i)
            if len(self) - self._sorted_up_to > self.UNSORTED:
                self._hashes = None  # sorted again, with them, at the next lookup

    def truncate(self, count: int) -> None:
        """Forget the strings from ``count`` on."""
        count = max(0, min(int(count), len(self)))
        self._bytes.truncate(self._end(count))
        if self._ends is not None:
            self._ends.truncate(count)
        self._present.truncate(count)
        self._hashes = None

    def _range(self, start: int, stop: int):
        """The strings start..stop - 1, decoded from one read of their bytes."""
        if stop <= start:
            return
        base = self._end(start)
        data = self._bytes.view()[base : self._end(stop)].tobytes()
        previous = 0
        ends = (self._ends_of(start, stop) - base).tolist()
        for end, present in zip(ends, self._present.view()[start:stop].tolist()):
            yield data[previous:end].decode("utf-8", "surrogatepass") if present else None
            previous = end

    def _slice(self, start: int, stop: int) -> list:
        return list(self._range(start, stop))

    def contains(self, value: str) -> bool:
        """Whether ``value`` is one of the strings (None is never looked up)."""
        if self._hashes is None:
            hashes = np.fromiter((_hash32(v) for v in self), np.uint32, len(self))
            present = np.flatnonzero(self._present.view())
            order = present[np.argsort(hashes[present], kind="stable")]
            self._order = order.astype(np.uint32) if len(self) <= np.iinfo(np.uint32).max else order
            self._hashes = hashes[order]
            self._sorted_up_to, self._unsorted = len(self), {}
        key = _hash32(value)
        # the key in the hashes' own dtype: a Python int makes numpy convert all of them on each
        # call (10 ms at 10^7 places, against microseconds)
        probe = np.uint32(key)
        low, high = np.searchsorted(self._hashes, probe, "left"), np.searchsorted(self._hashes, probe, "right")
        candidates = [*self._order[low:high].tolist(), *self._unsorted.get(key, ())]
        return any(self[i] == value for i in candidates)

    def __repr__(self) -> str:
        return f"StringColumn({len(self)} strings)"


class CategoryColumn(_Column):
    """Strings (or None) that repeat, such as the session that added each place: each place holds
    a 4-byte code into the distinct values (a 32-character session id costs 4 bytes a place, not
    37). Indexes, slices (to lists), iterates, and compares equal to a list of the same strings."""

    def __init__(self, values: Sequence[str | None] = ()):
        self._codes = GrowingArray(None, dtype=np.int32)  # -1: None
        self._values: list[str] = []
        self._code_of: dict[str, int] = {}
        self.extend(values)

    def __len__(self) -> int:
        return len(self._codes)

    def _code(self, value: str | None) -> int:
        if value is None:
            return -1
        code = self._code_of.get(value)
        if code is None:
            code = self._code_of[value] = len(self._values)
            self._values.append(value)
        return code

    def extend(self, values) -> None:
        codes = [self._code(v) for v in values]
        if codes:
            self._codes.extend(np.asarray(codes, np.int32))

    def truncate(self, count: int) -> None:
        """Forget the values from ``count`` on (the distinct values stay known)."""
        self._codes.truncate(max(0, min(int(count), len(self))))

    def _slice(self, start: int, stop: int) -> list:
        return [None if c < 0 else self._values[c] for c in self._codes.view()[start:stop].tolist()]

    def __repr__(self) -> str:
        return f"CategoryColumn({len(self)} places, {len(self._values)} values)"


class OptionalFloats(_Column):
    """A float per place (``width`` None: a timestamp) or a row of ``width`` floats (2: a
    position), each possibly missing, held as one float64 array with NaN for a missing value. The
    array is made by the first value, so a column that never held one (a map without times) keeps
    only its count, where a list costs 8 bytes a place (80 MB at 10^7) and a list of (x, y) tuples
    about 110. Indexes (a float or tuple, or None), slices (to lists), iterates, and compares equal
    to a list of the same values; :meth:`array` gives the values as one array, without a copy."""

    def __init__(self, width: int | None = None, values=()):
        self.width = width
        self._values: GrowingArray | None = None
        self._count = 0
        self._missing = 0
        self.extend(values)

    def __len__(self) -> int:
        return self._count

    def _row(self, value) -> list[float]:
        if value is None:
            return [np.nan] * (self.width or 1)
        if self.width is None:
            return [float(value)]
        row = [float(c) for c in tuple(value)[: self.width]]
        if len(row) != self.width:
            raise ConfigError(f"a position needs {self.width} values (x, y), got {tuple(value)!r}")
        return row

    def extend(self, values) -> None:
        rows = [self._row(v) for v in values]
        if not rows:
            return
        missing = sum(1 for r in rows if np.isnan(r[0]))
        if self._values is None and missing < len(rows):
            self._values = GrowingArray(self.width, np.full((self._count, *self._shape), np.nan), np.float64)
        if self._values is not None:
            block = np.asarray(rows, np.float64)
            self._values.extend(block[:, 0] if self.width is None else block)
        self._count += len(rows)
        self._missing += missing

    @property
    def _shape(self) -> tuple:
        return () if self.width is None else (self.width,)

    def all_present(self) -> bool:
        """Whether every place has its value (so times or positions can be used)."""
        return self._missing == 0

    def array(self, count: int | None = None) -> np.ndarray:
        """The first ``count`` values (None: all), NaN where missing: a view while any is held."""
        count = self._count if count is None else min(int(count), self._count)
        if self._values is None:
            return np.full((count, *self._shape), np.nan)
        return self._values.view(count)

    def truncate(self, count: int) -> None:
        """Forget the values from ``count`` on."""
        self._count = max(0, min(int(count), self._count))
        if self._values is None:
            self._missing = self._count
            return
        self._values.truncate(self._count)
        kept = self._values.view()
        self._missing = int(np.isnan(kept if self.width is None else kept[:, 0]).sum())

    def _value(self, row):
        if self.width is None:
            return None if np.isnan(row) else float(row)
        return None if np.isnan(row[0]) else tuple(float(c) for c in row)

    def _slice(self, start: int, stop: int) -> list:
        if self._values is None:
            return [None] * (stop - start)
        return [self._value(row) for row in self._values.view()[start:stop]]

    def __repr__(self) -> str:
        return f"OptionalFloats({len(self)} places, {self._missing} missing)"


def _first_within(idx: np.ndarray, scores: np.ndarray, searchable: int, want: int) -> tuple[np.ndarray, np.ndarray]:
    """Each row's first ``want`` entries with an id below ``searchable``, padded with -1 / -inf."""
    out_idx = np.full((len(idx), want), -1, np.int64)
    out_scores = np.full((len(idx), want), -np.inf, np.float32)
    for row, (ids, values) in enumerate(zip(idx, scores)):
        keep = (ids >= 0) & (ids < searchable)
        chosen = ids[keep][:want]
        out_idx[row, : len(chosen)] = chosen
        out_scores[row, : len(chosen)] = values[keep][:want]
    return out_idx, out_scores


def _number(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


class PlaceMap:
    """Places in insertion order (see the module docstring). ``dim``: the vectors' length, or
    None for a map that keeps no vectors in memory (its ``index`` holds them). ``index``: a
    :class:`~fdnet.matching.index.VectorIndex` over the same places in the same order, searched
    instead of the vectors (a dot-product database's, or ``fdnet match --index``'s); whoever adds
    places adds their vectors to it."""

    def __init__(self, dim: int | None = None, index=None):
        self.dim = dim
        self.vectors = GrowingArray(dim) if dim is not None else None
        self.index = index
        self.names = StringColumn()
        self.positions = OptionalFloats(2)
        self.metadata_text = StringColumn()
        self._loop: dict | None = None  # loop closure's columns, made from the metadata when first read
        #: False once :meth:`keep_loop_columns_only`: the metadata's text is no longer held
        self.keeps_metadata_text = True

    def __len__(self) -> int:
        return len(self.names)

    # ------------------------------------------------------------------ growing
    def extend(
        self,
        names: Sequence[str],
        positions: Sequence,
        metadata_text: Sequence[str | None],
        vectors: np.ndarray | None = None,
        metadata: Sequence[dict | None] | None = None,
    ) -> None:
        """Append places: names, positions ((x, y) or None), metadata as stored JSON text (or None;
        with ``metadata``, the same already parsed), and their vectors when the map keeps them."""
        if self._loop is not None:
            self._read_loop_columns(metadata_text, metadata)
        self.names.extend(names)
        self.positions.extend(positions)
        self.metadata_text.extend(metadata_text if self.keeps_metadata_text else [None] * len(names))
        if self.vectors is not None and vectors is not None:
            self.vectors.extend(vectors)

    def keep_loop_columns_only(self) -> None:
        """Read loop closure's columns and stop holding the metadata's text, which a map only loop
        closure searches never reads again (JSON of some 100 bytes a place: 1 GB at 10^7 places);
        :meth:`metadata` then gives None."""
        self.loop_column("session")
        self.metadata_text = StringColumn()
        self.metadata_text.extend([None] * len(self))
        self.keeps_metadata_text = False

    def append(self, vector: np.ndarray | None, name: str, position, metadata: dict | None) -> None:
        """Append one place (its metadata as a dict, stored as the JSON a database would hold)."""
        text = None if metadata is None or not self.keeps_metadata_text else json.dumps(metadata, sort_keys=True)
        self.extend([name], [position], [text], None if vector is None else np.asarray(vector)[None], [metadata])

    def truncate(self, count: int) -> None:
        """Forget the places from ``count`` on (a resumed traverse replays them)."""
        del self.names[count:], self.positions[count:], self.metadata_text[count:]
        if self.vectors is not None:
            self.vectors.truncate(count)
        if self._loop is not None:
            for column in self._loop.values():
                column.truncate(count)

    @classmethod
    def of_vectors(cls, names: Sequence[str], vectors: np.ndarray | None = None, index=None) -> "PlaceMap":
        """A map of ``names`` with their ``vectors`` (kept in memory) or ``index`` (searched
        instead), no positions or metadata: the references of ``fdnet match``."""
        out = cls(None if vectors is None else np.asarray(vectors).shape[1], index=index)
        out.extend(list(names), [None] * len(names), [None] * len(names), vectors)
        return out

    # ------------------------------------------------------------------ searching
    def search(
        self, queries: np.ndarray, k: int, searchable: int | None = None, similarity=None, sequence_length: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """The one batch search over a map (``fdnet match``, ``fdnet database query``): the best
        ``k`` of the first ``searchable`` places (None: all) for each query, as (place ids, scores),
        each (Q, min(k, searchable)), best first, ties to the lower id; -1 (score -inf) pads a row
        the index could not fill. Through :attr:`index` when the map has one, else exhaustively
        with ``similarity`` (default: dot product), by SeqSLAM sequence similarity when
        ``sequence_length`` > 1 (exhaustive search only: a sequence needs every place's score)."""
        q = np.asarray(queries, dtype=np.float32)
        count = len(self)
        searchable = count if searchable is None else max(0, min(int(searchable), count))
        want = min(int(k), searchable)
        if want <= 0:
            return np.full((len(q), 0), -1, np.int64), np.zeros((len(q), 0), np.float32)
        if self.index is not None:
            if sequence_length > 1:
                raise ConfigError("sequence similarity needs every place's score: search the vectors, not an index")
            # the excluded places are the last ones: ask for as many more, then drop them
            idx, scores = self.index.search(q, min(count, want + count - searchable))
            if searchable == count:
                return idx, scores
            return _first_within(idx, scores, searchable, want)
        if self.vectors is None:
            raise ConfigError("this map keeps neither vectors nor an index to search")
        references = self.vectors.view(searchable)
        if sequence_length > 1:
            from fdnet.matching.sequence import sequence_top_k

            return sequence_top_k(q, references, want, sequence_length, similarity=similarity)
        from fdnet.matching.similarity import top_k

        return top_k(q, references, want, similarity=similarity)

    # ------------------------------------------------------------------ reading
    def metadata(self, index: int) -> dict | None:
        text = self.metadata_text[index]
        return None if text is None else json.loads(text)

    def all_metadata(self) -> list[dict | None]:
        return [None if text is None else json.loads(text) for text in self.metadata_text]

    def __contains__(self, name: str) -> bool:
        return self.names.contains(name)

    def loop_column(self, key: str):
        """What loop closure reads from each place's metadata: ``timestamp`` (:class:`OptionalFloats`),
        ``informative``/``still`` (GrowingArray of bool: the gates' flags an earlier run stored),
        ``segment_start`` (GrowingArray of bool: the place starts a recording), ``session`` (the
        run that added it, or None: a :class:`CategoryColumn`)."""
        if self._loop is None:
            self._loop = {
                "timestamp": OptionalFloats(),
                "informative": GrowingArray(None),
                "still": GrowingArray(None),
                "segment_start": GrowingArray(None),
                "session": CategoryColumn(),
            }
            self._read_loop_columns(self.metadata_text)
        return self._loop[key]

    def _read_loop_columns(self, texts: Sequence[str | None], parsed: Sequence[dict | None] | None = None) -> None:
        """Extend loop closure's columns by the places of metadata ``texts`` (or the same, ``parsed``)."""
        # a block of places at a time, each column extended once per block (10^7 places load in
        # seconds, where a column append per place took minutes)
        for first in range(0, len(texts), 65_536):
            block = texts[first : first + 65_536]
            if parsed is not None:
                metadata = [m or {} for m in parsed[first : first + len(block)]]
            else:
                metadata = [(None if text is None else json.loads(text)) or {} for text in block]
            self._extend_loop_columns(metadata)

    def _extend_loop_columns(self, metadata: list[dict]) -> None:
        loop = self._loop
        loop["timestamp"].extend([_number(m.get("timestamp")) for m in metadata])
        loop["informative"].extend([not m.get("uninformative", False) for m in metadata])
        loop["still"].extend([bool(m.get("still", False)) for m in metadata])
        loop["segment_start"].extend([bool(m.get("segment_start")) for m in metadata])
        sessions = [m.get("session") for m in metadata]
        loop["session"].extend([s if s is None or isinstance(s, str) else str(s) for s in sessions])
