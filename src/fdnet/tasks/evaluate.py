"""The work of ``fdnet evaluate`` as one library call: check the settings (output paths before any
image is described), score methods on a reference/query split or a precomputed similarity
matrix, write the JSON and plots asked for, and return the results with their table.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from typing import Callable, Mapping, Sequence, Union

logger = logging.getLogger(__name__)

#: a method's options: a mapping (the same for every method), or a function of the method's name
MethodOptions = Union[Mapping, Callable[[str], Mapping], None]


@dataclasses.dataclass
class EvaluateSettings:
    """What to evaluate, on which data, and where the results go (the flags of ``fdnet evaluate``).
    Give ``method`` (names, comma-separated) with ``data``, or ``similarity`` (a .npy matrix)."""

    # methods on images, or a precomputed matrix
    method: str | None = None
    method_options: MethodOptions = None  # device excluded: ``device`` says where torch methods run
    similarity: str | None = None
    distance: bool = False  # the similarity file holds distances
    name: str | None = None  # method name reported for ``similarity``
    # data (:func:`fdnet.evaluation.splits.build_split`)
    data: str | None = None
    reference: str | None = None
    query: str | None = None
    tolerance: int | None = None
    filter_frames: bool = False
    dataset_format: str | None = None
    split: str | None = None
    format_set: Sequence[str] = ()
    frames: str | None = None
    ground_truth: str | None = None
    #: evaluate a trained method on frames it was trained on (refused by default)
    allow_training_frames: bool = False
    # describing and ranking
    batch_size: int = 64
    workers: int | None = None
    device: str | None = None
    sequence_length: int = 1
    threads: int | None = None  # torch CPU threads while describing; None: every core
    # metrics and output
    protocol: str = "recall-over-queries"
    thresholds: int | None = None
    accept: str | None = None  # acceptance rules; None: margin (raw under vprbench)
    accept_set: Sequence[str] = ()
    json: str | None = None
    include_curve: bool = True
    plots: str | None = None
    examples: int | None = None  # queries in the example-matches figure (with ``plots``); None: 6
    #: per-query predictions (this many best references each) in the JSON; 0 = none
    predictions: int = 0
    #: also print a method x data table as csv, markdown or latex
    table: str | None = None
    #: the command line, recorded in the JSON
    command: str | None = None


@dataclasses.dataclass(frozen=True)
class EvaluationOutcome:
    """:func:`evaluate_command`'s results (one per method) and their table."""

    results: list
    table: str


def evaluate_command(
    settings: EvaluateSettings, log: Callable[[str], None] | None = None, show: Callable[[str], None] | None = None
) -> EvaluationOutcome:
    """Evaluate as ``settings`` say; progress and the files written go to ``log`` (default: this
    module's logger). ``show`` gets the results table as soon as it is made, before the JSON and
    plots are written (the command prints it there). Every setting and output path is checked
    before any image is described."""
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE, parse_acceptance_list
    from fdnet.evaluation.report import TABLE_STYLES, format_results_table, format_table, write_json
    from fdnet.evaluation.splits import ground_truth_path

    log = log or logger.info
    _check_settings(settings)
    if settings.table is not None and settings.table not in TABLE_STYLES:
        from fdnet.errors import ConfigError

        raise ConfigError(f"--table {settings.table!r}: choose one of {', '.join(TABLE_STYLES)}")
    if isinstance(settings.predictions, bool) or not isinstance(settings.predictions, int) or settings.predictions < 0:
        from fdnet.errors import ConfigError

        raise ConfigError(f"--predictions must be a whole number of at least 0, got {settings.predictions!r}")
    ground_truth_path(settings.ground_truth)
    # the field's protocol first (the raw best-match score, as papers and VPR-Bench report), fdnet's
    # default acceptance rule beside it
    default_rule = "raw" if settings.protocol == "vprbench" else f"raw,{DEFAULT_ACCEPTANCE}"
    acceptance = parse_acceptance_list(settings.accept or default_rule, list(settings.accept_set))  # before any work
    if settings.similarity:
        results = [_evaluate_matrix(settings, acceptance)]
    else:
        results = _evaluate_methods(settings, acceptance, log)
    table = format_table(results, settings.protocol)
    if settings.table:
        table += "\n\n" + format_results_table(results, settings.table, settings.protocol)
    if show is not None:
        show(table)
    if settings.json:
        write_json(
            settings.json,
            results,
            settings.protocol,
            include_curve=settings.include_curve,
            command=settings.command,
            settings=_recorded(settings),
            predictions=settings.predictions,
        )
        log(f"wrote {settings.json}")
    if settings.plots:
        from fdnet.evaluation.plots import write_result_plots

        examples = DEFAULT_EXAMPLES if settings.examples is None else settings.examples
        for path in write_result_plots(results, settings.protocol, settings.plots, examples):
            log(f"wrote {path}")
    return EvaluationOutcome(results, table)


#: queries in the example-matches figure when ``examples`` is not given
DEFAULT_EXAMPLES = 6


def _check_nowhere_to_go(settings: EvaluateSettings) -> None:
    """Refuse a setting whose effect would go nowhere (it was ignored without a word): what only
    the JSON holds without ``json``, the figure's size without ``plots``, the matrix's options
    without ``similarity``."""
    from fdnet.errors import ConfigError

    needs = [
        ("--predictions K", bool(settings.predictions), settings.json, "--json FILE", "the JSON holds them"),
        (
            "--no-curve",
            not settings.include_curve,
            settings.json,
            "--json FILE",
            "the curve is left out of " "the JSON",
        ),
        ("--examples N", settings.examples is not None, settings.plots, "--plots DIR", "the figure is a plot"),
        (
            "--distance",
            settings.distance,
            settings.similarity,
            "--similarity FILE.npy",
            "it says what the " "matrix holds",
        ),
        (
            "--name",
            settings.name is not None,
            settings.similarity,
            "--similarity FILE.npy",
            "methods are " "named by --method",
        ),
    ]
    for flag, given, target, needed, why in needs:
        if given and not target:
            raise ConfigError(f"{flag} needs {needed} ({why}); without it the flag would do nothing")


def _check_settings(settings: EvaluateSettings) -> None:
    from fdnet.errors import ConfigError
    from fdnet.io import ensure_writable

    _check_nowhere_to_go(settings)
    if settings.examples is not None and (isinstance(settings.examples, bool) or settings.examples < 1):
        raise ConfigError(f"--examples must be at least 1, got {settings.examples!r}")

    if settings.similarity and settings.method:
        raise ConfigError("give either --similarity FILE.npy or --method NAME, not both")
    if not settings.similarity and not settings.method:
        raise ConfigError("nothing to evaluate: give --method NAME with --data, or --similarity FILE.npy")
    if settings.thresholds is not None and settings.protocol != "recall-over-queries":
        raise ConfigError(
            "--thresholds applies to --protocol recall-over-queries only (vprbench uses "
            "every top-1 score, as VPR-Bench does)"
        )
    if settings.thresholds is not None and settings.thresholds < 2:
        raise ConfigError(f"--thresholds must be at least 2, got {settings.thresholds}")
    if settings.tolerance is not None and settings.tolerance < 0:
        raise ConfigError(f"--tolerance must be >= 0, got {settings.tolerance}")
    from fdnet.matching.sequence import check_sequence_length

    check_sequence_length(settings.sequence_length)
    if settings.similarity and settings.sequence_length > 1:
        # it was silently ignored: single-image numbers reported as if sequence-matched
        raise ConfigError(
            "--sequence-length applies to --method; a --similarity matrix is evaluated as given "
            "(apply fdnet.matching.sequence.sequence_similarity to it first)"
        )
    # Outputs are checked before minutes of describing images, not after.
    if settings.json:
        ensure_writable(settings.json, what="JSON results")
    if settings.plots:
        ensure_writable(settings.plots, what="plots", directory=True)


def _split(settings: EvaluateSettings):
    from fdnet.evaluation.splits import SplitSpec, build_split

    return build_split(
        SplitSpec(
            settings.data,
            settings.reference,
            settings.query,
            dataset_format=settings.dataset_format,
            split=settings.split,
            format_set=tuple(settings.format_set),
            frames=settings.frames,
            tolerance=settings.tolerance,
            filter_frames=settings.filter_frames,
            ground_truth=settings.ground_truth,
        )
    )


def _evaluate_matrix(settings: EvaluateSettings, acceptance):
    from fdnet.evaluation.splits import evaluate_similarity_file

    split = _split(settings) if settings.data else None
    return evaluate_similarity_file(
        settings.similarity,
        split=split,
        ground_truth=settings.ground_truth,
        distance=settings.distance,
        name=settings.name,
        protocols=(settings.protocol,),
        thresholds=settings.thresholds,
        acceptance=acceptance,
    )


def _evaluate_methods(settings: EvaluateSettings, acceptance, log) -> list:
    from fdnet.backbones import check_device_spec, torch_threads
    from fdnet.descriptors.pipeline import PipelineSettings, check_pipeline_settings
    from fdnet.errors import ConfigError
    from fdnet.evaluation.experiment import ScoringSettings, evaluate_method
    from fdnet.evaluation.splits import check_descriptors_held_out

    if not settings.data:
        raise ConfigError("--method needs --data DIR (one sub-folder per condition)")
    check_pipeline_settings(settings.batch_size, settings.workers)
    device = check_device_spec(settings.device) if settings.device is not None else None
    entries = method_names(settings.method)
    names = [label for label, _ in entries]
    split = _split(settings)
    results = []
    with torch_threads(settings.threads or os.cpu_count() or 1):
        descriptors = [_create_descriptor(entry, settings.method_options, device) for entry in entries]  # fail fast
        check_descriptors_held_out(
            descriptors,
            settings.data,
            [split.reference.name, split.query.name],
            settings.frames,
            settings.dataset_format,
            settings.split,
            settings.allow_training_frames,
        )
        log(
            f"evaluating {', '.join(names)} on {split.description}: {len(split.query)} queries x "
            f"{len(split.reference)} references"
        )
        for (label, method), descriptor in zip(entries, descriptors):
            result = evaluate_method(
                descriptor,
                split,
                ScoringSettings((settings.protocol,), settings.thresholds, acceptance=acceptance),
                PipelineSettings(settings.batch_size, settings.workers, progress=True),
                sequence_length=settings.sequence_length,
                keep_similarity=bool(settings.plots),
                log=log,
            )
            if label != method:  # a row of its own name; the settings say which method made it
                result.method = label
                result.settings = {"method": method, **result.settings}
            results.append(result)
    return results


def method_names(text: str) -> list[tuple[str, str]]:
    """``(label, method)`` of a comma-separated ``--method`` list
    (:func:`fdnet.descriptors.registry.method_entries`): a label given twice is refused, since its
    two rows could not be told apart; ``LABEL=METHOD`` names each row of one method
    (``--method a=onnx,b=onnx``)."""
    from fdnet.descriptors.registry import method_entries

    return method_entries(text)


def _create_descriptor(entry: tuple[str, str], method_options: MethodOptions, device: str | None):
    """Method ``entry`` = (label, method) with the options given for its label."""
    from fdnet.descriptors import create

    label, method = entry
    options = dict((method_options(label) if callable(method_options) else method_options) or {})
    if device is not None:
        options.setdefault("device", device)  # a --method-set device=... wins, as in every command
    return create(method, **options)


def _recorded(settings: EvaluateSettings) -> dict:
    """The settings as the JSON records them (what was asked; callables left out)."""
    return {
        f.name: getattr(settings, f.name)
        for f in dataclasses.fields(settings)
        if f.name not in ("method_options", "command") and not callable(getattr(settings, f.name))
    }
