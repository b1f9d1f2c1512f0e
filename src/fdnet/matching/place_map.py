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


class StringColumn:
    """Strings (or None) in insertion order, held as one UTF-8 byte buffer and each string's end
    offset: about 25 bytes a 16-character name, where a list of str objects costs about 70 and
    leaves the allocator one small object per place to keep (10^7 names loaded from a database
    held 0.7 GB so, and pinned more of the heap the load had freed). Indexes, slices (to lists),
    iterates, and compares equal to a list of the same strings; :meth:`contains` looks a string
    up through a sorted array of hashes (16 bytes a string, where a set of str objects costs
    about 100). Any str round-trips, lone surrogates of undecodable file names included."""

    #: strings added after the hash index was sorted that are looked up in a dict before it is
    #: sorted again (a sort of 10^7 hashes takes about a second)
    UNSORTED = 65_536

    def __init__(self, values: Sequence[str | None] = ()):
        self._bytes = GrowingArray(None, dtype=np.uint8)
        self._ends = GrowingArray(None, dtype=np.int64)
        self._present = GrowingArray(None, dtype=bool)
        self._hashes = self._order = None  # the sorted hash index, made by the first lookup
        self._sorted_up_to = 0  # the strings it covers: those after it are in _unsorted
        self._unsorted: dict[int, list[int]] = {}
        self.extend(values)

    def __len__(self) -> int:
        return len(self._ends)

    def _end(self, count: int) -> int:
        return int(self._ends.view()[count - 1]) if count else 0

    def extend(self, values) -> None:
        first = len(self)
        if isinstance(values, StringColumn):
            offset = self._end(first)
            self._bytes.extend(values._bytes.view())
            self._ends.extend(values._ends.view() + offset)
            self._present.extend(values._present.view())
        else:
            values = list(values)
            if not values:
                return
            encoded = [b"" if v is None else v.encode("utf-8", "surrogatepass") for v in values]
            lengths = np.fromiter((len(e) for e in encoded), np.int64, len(encoded))
            self._ends.extend(self._end(first) + np.cumsum(lengths))
            self._bytes.extend(np.frombuffer(b"".join(encoded), np.uint8))
            self._present.extend(np.fromiter((v is not None for v in values), bool, len(values)))
        if self._hashes is not None:
            for i, value in enumerate(self._range(first, len(self)), start=first):
                if value is not None:
                    self._unsorted.setdefault(hash(value), []).append(i)
            if len(self) - self._sorted_up_to > self.UNSORTED:
                self._hashes = None  # sorted again, with them, at the next lookup

    def append(self, value: str | None) -> None:
        self.extend([value])

    def truncate(self, count: int) -> None:
        """Forget the strings from ``count`` on."""
        count = max(0, min(int(count), len(self)))
        self._bytes.truncate(self._end(count))
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
        ends = (self._ends.view()[start:stop] - base).tolist()
        for end, present in zip(ends, self._present.view()[start:stop].tolist()):
            yield data[previous:end].decode("utf-8", "surrogatepass") if present else None
            previous = end

    def __getitem__(self, key):
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if step == 1:
                return list(self._range(start, stop))
            return [self[i] for i in range(start, stop, step)]
        i = operator.index(key)
        i = i + len(self) if i < 0 else i
        if not 0 <= i < len(self):
            raise IndexError(f"place {key} of {len(self)}")
        return next(self._range(i, i + 1))

    def __iter__(self):
        # in blocks, so iterating a long column never holds a decoded copy of all of it
        for start in range(0, len(self), 65_536):
            yield from self._range(start, min(start + 65_536, len(self)))

    def contains(self, value: str) -> bool:
        """Whether ``value`` is one of the strings (None is never looked up)."""
        if self._hashes is None:
            hashes = np.fromiter((hash(v) for v in self), np.int64, len(self))
            present = np.flatnonzero(self._present.view())
            self._order = present[np.argsort(hashes[present], kind="stable")]
            self._hashes = hashes[self._order]
            self._sorted_up_to, self._unsorted = len(self), {}
        key = hash(value)
        low, high = np.searchsorted(self._hashes, key, "left"), np.searchsorted(self._hashes, key, "right")
        candidates = [*self._order[low:high].tolist(), *self._unsorted.get(key, ())]
        return any(self[i] == value for i in candidates)

    def __delitem__(self, key) -> None:
        if not isinstance(key, slice) or key.stop is not None or key.step not in (None, 1):
            raise TypeError("a column only forgets its last strings: del column[count:]")
        self.truncate(key.indices(len(self))[0])

    def __eq__(self, other) -> bool:
        if isinstance(other, (StringColumn, list, tuple)):
            return len(self) == len(other) and list(self) == list(other)
        return NotImplemented

    __hash__ = None

    def __repr__(self) -> str:
        return f"StringColumn({len(self)} strings)"


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
        self.positions: list[tuple[float, float] | None] = []
        self.metadata_text = StringColumn()
        self._loop: dict | None = None  # loop closure's columns, made from the metadata when first read

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
        start = len(self.names)
        self.names.extend(names)
        self.positions.extend(None if p is None else (float(p[0]), float(p[1])) for p in positions)
        self.metadata_text.extend(metadata_text)
        if self.vectors is not None and vectors is not None:
            self.vectors.extend(vectors)
        if self._loop is not None:
            self._read_loop_columns(start, metadata)

    def append(self, vector: np.ndarray | None, name: str, position, metadata: dict | None) -> None:
        """Append one place (its metadata as a dict, stored as the JSON a database would hold)."""
        text = None if metadata is None else json.dumps(metadata, sort_keys=True)
        self.extend([name], [position], [text], None if vector is None else np.asarray(vector)[None], [metadata])

    def truncate(self, count: int) -> None:
        """Forget the places from ``count`` on (a resumed traverse replays them)."""
        del self.names[count:], self.positions[count:], self.metadata_text[count:]
        if self.vectors is not None:
            self.vectors.truncate(count)
        if self._loop is not None:
            for column in self._loop.values():
                if isinstance(column, GrowingArray):
                    column.truncate(count)
                else:
                    del column[count:]

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
        """What loop closure reads from each place's metadata: ``timestamp`` (float or None),
        ``informative``/``still`` (GrowingArray of bool: the gates' flags an earlier run stored),
        ``segment_start`` (bool list: the place starts a recording), ``session`` (the run that
        added it, or None)."""
        if self._loop is None:
            self._loop = {
                "timestamp": [],
                "informative": GrowingArray(None),
                "still": GrowingArray(None),
                "segment_start": [],
                "session": StringColumn(),
            }
            self._read_loop_columns(0)
        return self._loop[key]

    def _read_loop_columns(self, start: int, parsed: Sequence[dict | None] | None = None) -> None:
        loop = self._loop
        texts = self.metadata_text[start:]
        for k, text in enumerate(texts):
            m = (parsed[k] if parsed is not None else None if text is None else json.loads(text)) or {}
            loop["timestamp"].append(_number(m.get("timestamp")))
            loop["informative"].append(not m.get("uninformative", False))
            loop["still"].append(bool(m.get("still", False)))
            loop["segment_start"].append(bool(m.get("segment_start")))
            session = m.get("session")
            loop["session"].append(session if session is None or isinstance(session, str) else str(session))
