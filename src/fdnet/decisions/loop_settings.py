"""What loop closure is set with, as objects passed whole: :class:`LoopClosureSettings` (how a
:class:`~fdnet.decisions.loop_closure.LoopClosureDetector` decides and stores),
:class:`~fdnet.descriptors.pipeline.PipelineSettings` (how frames are decoded and described) and
:class:`TraverseSettings` (one ``fdnet loop-closure`` run: the detector's settings, the outputs, the ground truth, the
calibration to make). Each checks its values when made, so a bad setting is refused before
anything is opened or described.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from fdnet.decisions.loop_gates import LoopGates
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError

#: how the detector finds a frame's candidates: every place, an index, or the index once the map
#: has ``index_from`` places (:mod:`fdnet.decisions.loop_search`)
SEARCH_KINDS = ("auto", "exact", "index")


def _whole(value, minimum: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ConfigError(f"{what} must be a whole number of at least {minimum}, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class LoopClosureSettings:
    """How a :class:`~fdnet.decisions.loop_closure.LoopClosureDetector` decides and stores.

    ``exclude_last``: how many of this traverse's most recent frames are never candidates (a
    floor under the recent past the detector finds itself). ``rule``: an acceptance expression
    (``"margin"``, ``"margin+verified"``) or a parsed
    :class:`~fdnet.decisions.acceptance.AcceptanceSpec`, with ``rule_settings`` (``{"radius": 5}``
    or ``["margin:radius=5"]``); ``threshold``: the score at which a candidate is accepted; or
    ``calibration``: a calibration (file, run directory or object) giving rule, settings,
    threshold, sequence length and gates for this model. ``sequence_length``: score by sequences
    of the robot's last N frames (1 = single images; None: the calibration's, else 1).
    ``gates``: :class:`~fdnet.decisions.loop_gates.LoopGates`. ``search``: one of
    :data:`SEARCH_KINDS`, with ``index_from`` places for ``auto``; ``compressed_from``: the map
    size from which the index holds compressed codes re-ranked exactly (None: the default,
    :data:`~fdnet.decisions.loop_search.COMPRESSED_FROM`). ``method_options``: what
    rebuilds the descriptor, recorded in a database created by the detector.
    ``allow_duplicates``: add a frame whose name the database already holds. ``commit_every``:
    frames stored per database transaction (1: every frame durable before ``process`` returns).
    ``frame_threads``: torch threads describing a frame in ``process`` (None: one or torch's own
    count, whichever measures faster, :class:`~fdnet.decisions.loop_threads.FrameThreads`).
    """

    exclude_last: int = 0
    rule: Any = None
    rule_settings: Any = None
    threshold: float | None = None
    calibration: Any = None
    sequence_length: int | None = None
    gates: LoopGates | None = None
    search: str = "auto"
    index_from: int | None = None
    compressed_from: int | None = None
    method_options: dict | None = None
    allow_duplicates: bool = False
    commit_every: int = 1
    frame_threads: int | None = None

    def __post_init__(self):
        _whole(self.exclude_last, 0, "exclude-last")
        if self.sequence_length is not None:
            from fdnet.matching.sequence import check_sequence_length

            check_sequence_length(self.sequence_length, "sequence length")
        _whole(self.commit_every, 1, "commit-every")
        if self.search not in SEARCH_KINDS:
            raise ConfigError(f"search must be one of {', '.join(SEARCH_KINDS)}, got {self.search!r}")
        if self.index_from is not None:
            _whole(self.index_from, 0, "index-from")
        if self.compressed_from is not None:
            _whole(self.compressed_from, 0, "compressed-from")
        if self.frame_threads is not None:
            _whole(self.frame_threads, 1, "frame-threads")
        if self.gates is not None and not isinstance(self.gates, LoopGates):
            raise ConfigError(f"gates must be a LoopGates, got {type(self.gates).__name__}")

    def with_options(self, **options) -> "LoopClosureSettings":
        """These settings with ``options`` (field names) replaced; an unknown name is refused."""
        unknown = sorted(set(options) - {f.name for f in fields(self)})
        if unknown:
            raise ConfigError(
                f"unknown loop-closure setting(s) {', '.join(unknown)}; known: "
                f"{', '.join(f.name for f in fields(self))}"
            )
        return replace(self, **options) if options else self


@dataclass(frozen=True)
class TraverseSettings:
    """One run over a traverse (:func:`~fdnet.decisions.loop_traverse.run_traverse`).

    ``events_csv`` (and ``events_jsonl``): where each accepted closure is written as it is
    accepted. ``ground_truth``: a CSV whose queries are the frames and whose references are the
    database's places; the run is then evaluated. ``calibrate_to``: also choose the threshold
    that reaches ``target_precision`` on this traverse (needs ground truth) and write that
    calibration there. ``resume``: the database holds the first frames of this traverse from an
    interrupted run; replay them and go on."""

    events_csv: str | os.PathLike
    detector: LoopClosureSettings = field(default_factory=LoopClosureSettings)
    pipeline: PipelineSettings = field(default_factory=lambda: PipelineSettings(batch_size=16))
    events_jsonl: str | os.PathLike | None = None
    ground_truth: str | os.PathLike | None = None
    calibrate_to: str | os.PathLike | None = None
    target_precision: float = 1.0
    resume: bool = False

    def __post_init__(self):
        if not isinstance(self.detector, LoopClosureSettings):
            raise ConfigError(f"detector settings must be a LoopClosureSettings, got {type(self.detector).__name__}")
        if not isinstance(self.pipeline, PipelineSettings):
            raise ConfigError(f"pipeline settings must be a PipelineSettings, got {type(self.pipeline).__name__}")
