"""What the experiments of one ``fdnet reproduce`` run share: its settings
(:class:`ReproduceSettings`), the evaluation pairs (:func:`build_pairs`), the methods
(:class:`MethodHandle`, each built once) and the :class:`Context` that holds them with the vectors,
similarity matrices and metrics computed once per run; and what several experiments ask of a pair
(:func:`condition_traverses`, :func:`matched_reference`). :mod:`fdnet.reproduce.runner` builds it
and runs the experiments with it.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fdnet.data.split import EvaluationSplit
from fdnet.descriptors.base import Descriptor
from fdnet.errors import ConfigError, FdnetError
from fdnet.metrics import RECALL_OVER_QUERIES
from fdnet.reproduce.cache import DescriptorCache, image_list_key


def default_cache_root() -> Path:
    """$FDNET_CACHE/reproduce (default ~/.cache/fdnet/reproduce): outside the report's folder."""
    import os

    return Path(os.environ.get("FDNET_CACHE") or Path.home() / ".cache" / "fdnet") / "reproduce"


#: the paper's protocol (section 5.1.2): 500 uniform thresholds, recall over queries
PROTOCOL = RECALL_OVER_QUERIES
THRESHOLDS = 500


@dataclass
class ReproduceSettings:
    """What ``fdnet reproduce`` was asked to do (the CLI fills this from its flags)."""

    data: Path
    out: Path
    checkpoint: Path | None = None
    #: where vectors are cached (default: $FDNET_CACHE/reproduce/descriptors, ~/.cache/fdnet/...)
    cache: Path | None = None
    #: recall-over-queries (the paper's, 500 thresholds) or vprbench (VPR-Bench's, every top-1 score)
    protocol: str = RECALL_OVER_QUERIES
    dataset_format: str | None = None
    conditions: list[str] | None = None
    frames: str | None = None
    split: str | None = None
    tolerance: int | None = None
    format_options: dict = field(default_factory=dict)
    methods: list[str] | None = None
    method_options: dict[str, dict] = field(default_factory=dict)
    experiments: list[str] | None = None
    length_runs: dict[int, Path] = field(default_factory=dict)
    length_preset: str | None = None
    length_train_frames: str | None = None
    length_overrides: dict = field(default_factory=dict)
    #: the ablation study's given runs, (variant, run directory) pairs; grouped by each run's preset
    ablation_runs: list[tuple[str, Path]] = field(default_factory=list)
    #: presets whose ablation variants are trained here (None: cpu, when training is asked for)
    ablation_presets: list[str] | None = None
    ablation_train_frames: str | None = None
    #: training settings of the ablation variants: "" -> for every preset, PRESET -> for that one
    ablation_overrides: dict[str, dict] = field(default_factory=dict)
    #: how many times each variant and length trained here is trained (seeds S, S+1, ...; default once)
    seeds: int = 1
    viewpoint_pair: tuple[str, str] | None = None  # (reference, query)
    overlaps: tuple[float, ...] = (1.0, 0.9, 0.75, 0.65)
    examples: int = 5
    runtime_images: int = 32
    embedding_points: int = 300
    batch_size: int = 32
    #: CPU threads for numpy's BLAS and scikit-learn's OpenMP (None = theirs); torch's are the caller's
    threads: int | None = None
    progress: bool = False
    command: str = ""


@dataclass
class Pair:
    """One ordered pair of conditions: ``query`` images matched against the ``reference`` map."""

    reference: str
    query: str
    split: EvaluationSplit

    @property
    def label(self) -> str:
        return f"{self.query} -> {self.reference}"

    @property
    def slug(self) -> str:
        return re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{self.query}_vs_{self.reference}")


def build_pairs(settings: ReproduceSettings) -> list[Pair]:
    """Every ordered pair of the chosen conditions. Plain folders: frame-aligned within
    ``tolerance`` frames, ``frames`` slicing every condition. With a dataset format: the adapter's
    split and ground truth for each pair (only its default pair when no conditions are named)."""
    from fdnet.data.dataset import RouteDataset, parse_frame_range
    from fdnet.data.split import aligned_split

    if settings.dataset_format:
        from fdnet.data.formats import detect_format, open_split

        if settings.frames and settings.split:
            raise ConfigError("give --split or --frames, not both")
        name = detect_format(settings.data) if settings.dataset_format == "auto" else settings.dataset_format
        options = dict(settings.format_options)
        if settings.tolerance is not None:
            options["tolerance"] = settings.tolerance
        split = settings.split or settings.frames
        if not settings.conditions:
            one = open_split(settings.data, dataset_format=name, split=split, **options)
            return [Pair(one.reference.name, one.query.name, one)]
        return [
            Pair(r, q, open_split(settings.data, r, q, dataset_format=name, split=split, **options))
            for r, q in itertools.permutations(settings.conditions, 2)
        ]
    if settings.split or settings.format_options:
        raise ConfigError("--split and --format-set need --dataset-format")
    dataset = RouteDataset.from_folder(settings.data, settings.conditions)
    if len(dataset.conditions) < 2:
        raise ConfigError(
            f"{settings.data}: needs at least two conditions to compare, found "
            f"{', '.join(dataset.conditions) or 'none'}"
        )
    start, end = parse_frame_range(settings.frames)
    return [
        Pair(r, q, aligned_split(dataset, r, q, settings.tolerance or 0, start, end))
        for r, q in itertools.permutations(dataset.conditions, 2)
    ]


class MethodHandle:
    """One method of this run, built once. ``descriptor`` is None when it cannot run here
    (``reason`` says why). A method that learns from the map (``needs_fit``, e.g. DBoW without a
    vocabulary) gets one fitted copy per reference image list, made when first needed; its vectors
    are cached under the unfitted fingerprint plus that list (fitting is deterministic), so a rerun
    does not describe them again. It is fitted again for its comparison, which may depend on what
    it learnt."""

    def __init__(self, label: str, name: str, options: dict, factory: Callable, compared: bool = True) -> None:
        self.label, self.name, self.options, self.factory = label, name, dict(options), factory
        #: one of the methods compared in every experiment (False: e.g. the lengths study's runs)
        self.compared = compared
        self.descriptor = None
        self.reason: str | None = None
        self._fitted: dict[str, object] = {}
        self._identity: dict | None = None

    def build(self, required: bool) -> None:
        try:
            self.descriptor = self.factory(self.name, **self.options)
        except FdnetError as exc:
            if required:
                raise
            self.reason = str(exc)

    @property
    def available(self) -> bool:
        return self.descriptor is not None

    @property
    def identity(self) -> dict:
        if self._identity is None:
            d = self.descriptor
            self._identity = {"method": d.name, "settings": d.settings(), "fingerprint": d.fingerprint()}
        return self._identity

    def fitted(self, fit_paths: Sequence[Path] | None):
        """The descriptor ready to describe (fitted on ``fit_paths`` when it learns from the map)."""
        d = self.descriptor
        if not d.needs_fit:
            return d
        if fit_paths is None:
            raise ConfigError(f"{self.label} learns from the reference images; no reference set was given")
        key = image_list_key(fit_paths)
        if key not in self._fitted:
            fresh = self.factory(self.name, **self.options)
            fresh.fit(list(fit_paths))
            self._fitted[key] = fresh
        return self._fitted[key]


class _AppearanceView(Descriptor):
    """A descriptor whose ``describe`` is FDNet's ``describe_appearance`` (for batching/loading)."""

    def __init__(self, descriptor) -> None:
        self.inner = descriptor
        self.name = f"{descriptor.name} appearance"
        self.input_size = descriptor.input_size
        self._dim = descriptor.dim

    @property
    def dim(self) -> int:
        return self._dim

    def describe(self, images):
        return self.inner.describe_appearance(images)


class Context:
    """What the experiments share in one run: settings, pairs, methods, the cache, the log."""

    def __init__(
        self, settings: ReproduceSettings, pairs: list[Pair], factory: Callable, log: Callable[[str], None]
    ) -> None:
        self.settings = settings
        self.pairs = pairs
        #: the protocol every experiment measures with (``--protocol``); the paper's by default
        self.protocol = settings.protocol
        self.thresholds = THRESHOLDS if self.protocol == RECALL_OVER_QUERIES else None
        self.protocol_label = (
            f"{self.protocol}, {THRESHOLDS} thresholds" if self.thresholds else f"{self.protocol}, every top-1 score"
        )
        self.factory = factory
        self.log = log
        self.out = Path(settings.out)
        # shared across reports and runs (it can reach hundreds of MB): $FDNET_CACHE/reproduce by
        # default, --cache DIR to choose; its keys name methods, settings and images
        self.cache = DescriptorCache(Path(settings.cache) if settings.cache else default_cache_root() / "descriptors")
        self.handles: dict[str, MethodHandle] = {}
        self._similarities: dict[tuple[str, str], np.ndarray] = {}
        self._results: dict[tuple[str, str], object] = {}
        from fdnet.paper import dataset_key

        self.dataset = dataset_key(settings.dataset_format, Path(settings.data).resolve().name)
        self.experiment = ""
        #: figure files handed out in this run (see remove_stale_figures)
        self.figures: set[Path] = set()

    # --------------------------------------------------------------------- methods
    def add_method(self, label: str, name: str, options: dict, required: bool, compared: bool = True) -> MethodHandle:
        handle = MethodHandle(label, name, options, self.factory, compared)
        handle.build(required)
        if handle.reason:
            self.log(f"{label}: not run ({handle.reason})")
        self.handles[label] = handle
        return handle

    def methods(self) -> list[MethodHandle]:
        """The compared methods (not the extra FDNet runs of the lengths study), in order."""
        return [h for h in self.handles.values() if h.compared]

    def available(self) -> list[MethodHandle]:
        return [h for h in self.methods() if h.available]

    def skipped(self) -> list[dict]:
        return [{"method": h.label, "reason": h.reason} for h in self.methods() if not h.available]

    # --------------------------------------------------------------------- vectors
    def vectors(
        self,
        handle: MethodHandle,
        paths: Sequence[Path],
        fit_paths: Sequence[Path] | None = None,
        kind: str = "content",
        what: str = "",
    ) -> np.ndarray:
        """``handle``'s vectors of ``paths`` (``kind`` "content", or "appearance" for FDNet's
        v_a), from the cache or described now."""
        from fdnet.descriptors.base import describe_paths

        paths = list(paths)
        d = handle.descriptor
        parts = {
            **handle.identity,
            "kind": kind,
            "images": image_list_key(paths),
            "fitted_on": image_list_key(fit_paths) if d.needs_fit else None,
        }

        def compute() -> np.ndarray:
            self.log(
                f"[{self.experiment}] {handle.label}: describing {what or 'images'} ({len(paths)} images"
                f"{', ' + kind if kind != 'content' else ''})"
            )
            describer = handle.fitted(fit_paths)
            if kind == "appearance":
                describer = _AppearanceView(describer)
            return describe_paths(describer, paths, self.settings.batch_size, progress=self.settings.progress)

        return self.cache.vectors(parts, compute, label=f"{handle.label}/{kind}/{what}")

    def pair_vectors(self, handle: MethodHandle, split: EvaluationSplit) -> tuple[np.ndarray, np.ndarray]:
        """(query vectors, reference vectors) of one split; learning methods fit on its references."""
        refs = split.reference.paths
        q = self.vectors(handle, split.query.paths, refs, what=split.query.name)
        r = self.vectors(handle, refs, refs, what=split.reference.name)
        return q, r

    def similarity(self, handle: MethodHandle, split: EvaluationSplit, key: str) -> np.ndarray:
        """(Q, R) similarity of one split by the method's own comparison (kept for this run)."""
        from fdnet.matching.similarity import similarity_matrix

        memo = (handle.label, key)
        if memo not in self._similarities:
            q, r = self.pair_vectors(handle, split)
            compare = (
                handle.fitted(split.reference.paths).similarity
                if handle.descriptor.needs_fit
                else handle.descriptor.similarity
            )
            self._similarities[memo] = similarity_matrix(q, r, compare)
        return self._similarities[memo]

    def result(self, handle: MethodHandle, split: EvaluationSplit, key: str):
        """The :class:`~fdnet.evaluation.experiment.MethodResult` of one split under the paper's
        protocol (500 thresholds), with the descriptor's settings. Its PR numbers are the paper's
        (``raw``: the best-match similarity); ``per_acceptance`` adds fdnet's default acceptance
        rule (:data:`fdnet.decisions.acceptance.DEFAULT_ACCEPTANCE`) beside it."""
        from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE
        from fdnet.evaluation.experiment import ScoringSettings, evaluate_matrix

        memo = (handle.label, key)
        if memo not in self._results:
            scoring = ScoringSettings(
                (self.protocol,), self.thresholds, acceptance=list(dict.fromkeys(["raw", DEFAULT_ACCEPTANCE]))
            )
            result = evaluate_matrix(
                self.similarity(handle, split, key),
                split.ground_truth,
                handle.label,
                scoring,
                dataset=split.description,
                query_paths=split.query.paths,
                reference_paths=split.reference.paths,
                similarity_ceiling=float(handle.descriptor.similarity_ceiling),
            )
            result.settings = dict(handle.descriptor.settings())
            self._results[memo] = result
        return self._results[memo]

    def limit_threads(self) -> None:
        """Apply ``--threads`` to every BLAS/OpenMP pool loaded so far, including those a method
        loaded on first use (OpenCV bundles its own BLAS); called before anything is timed."""
        if self.settings.threads:
            from threadpoolctl import threadpool_limits

            threadpool_limits(limits=self.settings.threads)

    # --------------------------------------------------------------------- outputs
    def figure_path(self, name: str) -> Path:
        path = self.out / "figures" / self.experiment / name
        self.figures.add(path)
        return path

    def remove_stale_figures(self) -> None:
        """Delete this experiment's figure files that this run did not draw (other pairs or
        methods of an earlier run), so the folder holds what the JSON describes."""
        folder = self.out / "figures" / self.experiment
        if folder.is_dir():
            for path in folder.iterdir():
                if path.is_file() and path not in self.figures:
                    path.unlink()

    def relative(self, path: Path) -> str:
        return Path(path).relative_to(self.out).as_posix()


def condition_traverses(pairs: Sequence[Pair]) -> dict:
    """Condition name -> its traverse (the first pair that holds it), in first-seen order."""
    out: dict = {}
    for pair in pairs:
        for traverse in (pair.split.reference, pair.split.query):
            out.setdefault(traverse.name, traverse)
    return out


def matched_reference(split: EvaluationSplit, query: int) -> int | None:
    """The reference showing the same place as ``query``: the true match with the same frame id
    when there is one (frame-aligned traverses), else the middle of its true matches; None when
    the query has no true match."""
    positives = split.ground_truth.positives[query]
    if not len(positives):
        return None
    same_frame = positives[split.reference.frame_ids[positives] == split.query.frame_ids[query]]
    return int(same_frame[0]) if len(same_frame) else int(positives[len(positives) // 2])
