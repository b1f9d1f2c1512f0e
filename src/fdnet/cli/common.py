"""Arguments and helpers shared by several sub-commands (method selection, threads)."""

from __future__ import annotations

import argparse
import os

from fdnet.data.formats import format_names


def dataset_format_list(auto: bool = True) -> str:
    """The published layouts ``--dataset-format`` reads, for help texts (from the one list in
    :mod:`fdnet.data.formats`)."""
    return ", ".join(format_names()) + (", or auto to detect" if auto else "")


def add_method_arguments(parser: argparse.ArgumentParser, multiple: bool = False, required: bool = True) -> None:
    """--method plus the flags that set a method's settings (passed to ``fdnet.descriptors.create``).
    ``required=False`` for commands where --method is one of several input modes. Every flag here
    takes ``[LABEL:]VALUE`` (:func:`method_options` says where a value goes)."""
    from fdnet.descriptors.registry import fitting_methods, trained_methods

    parser.add_argument(
        "--method",
        required=required,
        help="descriptor method"
        + (
            " (comma-separated for several; LABEL=METHOD names a row, so "
            "two models of one method compare: a=onnx,b=onnx with "
            "--weights a:A.onnx --weights b:B.onnx)"
            if multiple
            else ""
        )
        + "; `fdnet methods` lists them",
    )
    scoped = (
        " ([METHOD:]VALUE: METHOD: names one method (or label) of --method; a bare value goes to every "
        "method that has this setting)"
    )
    parser.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        metavar="[METHOD:]RUN_DIR",
        help=f"run directory of a trained method ({', '.join(trained_methods())})" + scoped,
    )
    parser.add_argument(
        "--weights",
        action="append",
        default=[],
        metavar="[METHOD:]FILE",
        help="weights file a method accepts (conv3 AlexNet, hybridnet, the onnx model)" + scoped,
    )
    parser.add_argument(
        "--vocabulary",
        action="append",
        default=[],
        metavar="[METHOD:]FILE",
        help="DBoW vocabulary file (from `fdnet vocabulary build`)" + scoped,
    )
    parser.add_argument(
        "--vectors",
        action="append",
        default=[],
        metavar="[METHOD:]FILE",
        help="precomputed: vectors computed elsewhere, keyed by image (fdnet extract's .npz, "
        ".npy with a names list, hloc's .h5); repeatable, the files merge",
    )
    parser.add_argument(
        "--fit",
        action="append",
        default=[],
        metavar="[METHOD:]DIR",
        help="dataset folder a method that learns from images "
        f"({', '.join(fitting_methods())}) learns from: every condition sub-folder, no labels "
        "(default: the reference images; the output's settings say which as fitted_on)" + scoped,
    )
    parser.add_argument(
        "--fit-frames",
        action="append",
        default=[],
        metavar="[METHOD:]START:END",
        help="with --fit: only these frames of every condition (e.g. the training frames)",
    )
    parser.add_argument(
        "--method-set",
        action="append",
        default=[],
        metavar="[METHOD:]KEY=VALUE",
        help="a method setting (`fdnet methods` and docs/methods.md list them), e.g. --method-set "
        "dim=1024 (every method with a dim) or --method-set conv3:dim=1024 (repeatable)",
    )


#: flags that set one method setting each, flag's dest -> setting; every one takes [METHOD:]VALUE
METHOD_FLAGS = {
    "checkpoint": "checkpoint",
    "weights": "weights",
    "vocabulary": "vocabulary",
    "fit": "fit",
    "fit_frames": "fit_frames",
    "vectors": "vectors",
}
#: settings that name a file or folder (made absolute where a database records them)
FILE_OPTIONS = ("checkpoint", "weights", "vocabulary", "fit")
#: flags whose every value goes to the method (a list): several files merge
LIST_OPTIONS = ("vectors",)


def split_scope(text, scopes) -> tuple[str | None, str]:
    """The one parser of method-scoped values: ``LABEL:VALUE`` -> ``(LABEL, VALUE)`` when the text
    before the first ``:`` is one of ``scopes`` (the method names and the command's labels), else
    ``(None, text)``: an unscoped value (so ``START:END`` and ``BAG:TOPIC`` stay whole)."""
    text = str(text)
    label, sep, rest = text.partition(":")
    return (label, rest) if sep and label in scopes else (None, text)


def method_labels(args: argparse.Namespace) -> dict[str, str]:
    """label -> method of the command's ``--method`` list (:func:`fdnet.descriptors.registry.method_entries`:
    ``METHOD`` is its own label, ``LABEL=METHOD`` names a row); names it does not know are left
    for the method's creation to refuse."""
    from fdnet.descriptors.registry import parse_method_entry

    entries = (parse_method_entry(item) for item in (getattr(args, "method", None) or "").split(","))
    return {label: method for label, method in entries if label}


def _scoped_values(args: argparse.Namespace, scopes) -> list[tuple[str, str, str | None, object, str]]:
    """``(flag, setting, label or None, value, text as given)`` of every method option given:
    the flags of :data:`METHOD_FLAGS` and ``--method-set [LABEL:]KEY=VALUE`` (values read as YAML)."""
    from fdnet.config import parse_value
    from fdnet.errors import ConfigError

    out = []
    for dest, setting in METHOD_FLAGS.items():
        for text in getattr(args, dest, None) or []:
            label, value = split_scope(text, scopes)
            out.append((f"--{dest.replace('_', '-')}", setting, label, value, str(text)))
    for text in getattr(args, "method_set", None) or []:
        label, entry = split_scope(text, scopes)
        key, sep, value = entry.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--method-set {text!r}: expected [METHOD:]KEY=VALUE")
        where = f"--method-set {text.partition('=')[0].strip()}"
        out.append(("--method-set", key.strip(), label, parse_value(value.strip(), where), str(text)))
    return out


def _check_routes(values, labels: dict[str, str]) -> None:
    """Each value goes somewhere: a scoped one to a method of --method that has the setting, an
    unscoped one to at least one such method (the rule :func:`method_options` applies)."""
    from fdnet.descriptors.registry import available_methods, setting_names
    from fdnet.errors import ConfigError

    methods = ", ".join(labels)
    for flag, setting, label, _, text in values:
        if label is not None and label not in labels:
            raise ConfigError(f"{flag} {text}: {label} is not one of the methods of --method ({methods})")
        if label is not None and setting not in setting_names(labels[label]):
            raise ConfigError(
                f"{flag} {text}: method {labels[label]!r} has no setting {setting}; its settings: "
                f"{', '.join(setting_names(labels[label]))}"
            )
        if label is None and not any(setting in setting_names(m) for m in labels.values()):
            owners = [name for name in available_methods() if setting in setting_names(name)]
            raise ConfigError(
                f"{flag} {text}: none of the methods {methods} has a setting {setting}"
                + (f" ({', '.join(owners)} {'has' if len(owners) == 1 else 'have'})" if owners else "")
            )


def method_options(args: argparse.Namespace, method: str | None = None) -> dict:
    """Keyword settings for ``create(method, ...)`` from the method option flags, all read by one
    rule: a value ``LABEL:VALUE`` (:func:`split_scope`) goes to that method of ``--method`` only
    (refused when it has no such setting); a bare value goes to every method of the command whose
    settings declare it, and is refused when none does. A scoped ``--method-set`` value wins over
    a bare one; two different values of one file flag for one method are refused. ``method`` is a
    method's name, its label in ``--method LABEL=METHOD``, or a ``LABEL=METHOD`` entry; None: every
    value, unchecked (for commands without --method)."""
    from fdnet.descriptors.registry import available_methods, parse_method_entry, setting_names
    from fdnet.errors import ConfigError

    labels = method_labels(args)
    known = available_methods()
    commanded = {label: kind for label, kind in labels.items() if kind in known}
    values = _scoped_values(args, set(known) | set(labels))
    if commanded:
        _check_routes(values, commanded)
    label = kind = None
    if method is not None:
        label, kind = parse_method_entry(method)
        kind = labels.get(label, kind) if "=" not in method else kind
    declared = set(setting_names(kind)) if kind in known else None

    def mine(setting, scope) -> bool:
        if method is None or declared is None:
            return scope is None or scope == label
        return setting in declared and scope in (None, label)

    options: dict = {}
    for dest, setting in METHOD_FLAGS.items():
        flag = f"--{dest.replace('_', '-')}"
        given = [(scope, value) for f, s, scope, value, _ in values if f == flag and mine(s, scope)]
        if dest in LIST_OPTIONS:
            if given:
                options[setting] = [value for _, value in given]
            continue
        chosen = [value for scope, value in given if scope is not None] or [value for _, value in given]
        chosen = list(dict.fromkeys(chosen))
        if len(chosen) > 1:
            raise ConfigError(
                f"{flag} gives {label or 'a method'} {len(chosen)} values ({', '.join(chosen)}); one "
                "method takes one: give each model its own label, e.g. --method a=onnx,b=onnx "
                "--weights a:A.onnx --weights b:B.onnx"
            )
        if chosen:
            options[setting] = chosen[0]
    method_set = [(setting, scope, value) for f, setting, scope, value, _ in values if f == "--method-set"]
    for setting, scope, value in sorted(method_set, key=lambda item: item[1] is not None):  # scoped last: it wins
        if mine(setting, scope):
            options[setting] = value
    return options


def create_descriptor(name: str, args: argparse.Namespace, options: dict | None = None):
    """Method ``name`` (or ``LABEL=METHOD``, or a label of ``--method``) with its settings from
    ``args`` (or ``options``, what :func:`method_options` gave) and the command's ``--device``
    (which goes to the torch methods only; see :func:`fdnet.descriptors.create`)."""
    from fdnet.descriptors import create
    from fdnet.descriptors.registry import parse_method_entry

    label, kind = parse_method_entry(name)
    kind = method_labels(args).get(label, kind) if "=" not in name else kind
    options = dict(method_options(args, name) if options is None else options)
    if getattr(args, "device", None) is not None:
        options.setdefault("device", args.device)
    return create(kind, **options)


def add_decision_arguments(parser, calibration_help: str) -> None:
    """--calibration, --accept and --accept-set of the commands that write ranked candidates
    (match, database query): a calibrated decision, or a rule's score without a threshold."""
    parser.add_argument("--calibration", metavar="FILE|RUN_DIR", help=calibration_help)
    parser.add_argument(
        "--accept",
        metavar="RULE",
        help="instead of a calibration: add this acceptance rule's acceptance_score column (margin, "
        "ratio, raw, ...; docs/decisions.md), with no threshold",
    )
    parser.add_argument(
        "--accept-set",
        action="append",
        default=[],
        metavar="[RULE:]KEY=VALUE",
        help="a setting of the --accept rule (repeatable), e.g. radius=3",
    )


def acceptance_from_arguments(args: argparse.Namespace):
    """The ``--accept`` rule (an AcceptanceSpec) or None; refuses --accept-set without --accept
    and --accept with --calibration (the calibration holds its rule and settings)."""
    from fdnet.errors import ConfigError

    if args.calibration and (args.accept or args.accept_set):
        raise ConfigError(
            "--accept/--accept-set and --calibration: the calibration holds its rule and settings; "
            "give one or the other"
        )
    if args.accept_set and not args.accept:
        raise ConfigError("--accept-set needs --accept RULE")
    if not args.accept:
        return None
    from fdnet.decisions.acceptance import parse_acceptance

    return parse_acceptance(args.accept, args.accept_set)


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """``--device`` for commands that run a model for inference."""
    from fdnet.backbones import DEVICE_HELP
    from fdnet.descriptors.registry import torch_methods

    parser.add_argument(
        "--device",
        default="auto",
        metavar="auto|cpu|cuda|cuda:N",
        help=DEVICE_HELP + f". Methods that run on a device ({', '.join(torch_methods())}) run "
        "there (the torch ones get images as uint8); the numpy/OpenCV methods run on the CPU",
    )


#: options whose value may be a folder of images, so also a video or ROS bag (fdnet.data.sources)
IMAGE_OPTIONS = ("--images", "--reference", "--query", "--data", "--positions", "--fit")


def add_source_arguments(parser: argparse.ArgumentParser) -> None:
    """How frames are taken from videos and ROS bags given where a folder of images is accepted
    (every command whose parser has one of :data:`IMAGE_OPTIONS`; ``fdnet.cli.build_parser`` adds
    them, so no command declares them itself). Folders of images ignore them."""
    if not any(option in parser._option_string_actions for option in IMAGE_OPTIONS):
        return
    group = parser.add_argument_group(
        "videos and ROS bags",
        "a video file (.mp4, .avi, .mkv, ...) or a ROS bag (.bag, .db3, .mcap, a ROS 2 bag "
        "folder, or BAG:TOPIC) is accepted wherever a folder of images is; docs/sources.md",
    )
    group.add_argument(
        "--fps",
        type=float,
        metavar="N",
        help="take at most N frames per second (the first frame of each 1/N-second slot; default: " "every frame)",
    )
    group.add_argument("--every", type=int, metavar="K", help="take every K-th frame")
    group.add_argument(
        "--window",
        metavar="START:END",
        help="only frames from START to END seconds after a source's first frame (either may be empty)",
    )
    group.add_argument(
        "--topic", help="a bag's image topic (sensor_msgs/Image or CompressedImage); needed when the " "bag has several"
    )
    group.add_argument(
        "--position-topic",
        metavar="TOPIC",
        help="a bag's sensor_msgs/NavSatFix or nav_msgs/Odometry topic whose positions are "
        "interpolated to the image times (default: the bag's only NavSatFix topic, else its "
        "only Odometry topic)",
    )


def source_options(args: argparse.Namespace):
    """The :class:`fdnet.data.sources.SourceOptions` the flags of :func:`add_source_arguments` give."""
    from fdnet.data.sources import SourceOptions, parse_window

    return SourceOptions(
        fps=getattr(args, "fps", None),
        every=getattr(args, "every", None),
        window=parse_window(getattr(args, "window", None)),
        topic=getattr(args, "topic", None),
        position_topic=getattr(args, "position_topic", None),
    ).check()


def add_pipeline_arguments(parser: argparse.ArgumentParser, batch_size: int = 64) -> None:
    """``--batch-size`` and ``--workers`` of the streaming image pipeline."""
    parser.add_argument(
        "--batch-size", type=int, default=batch_size, help=f"images described per batch (default {batch_size})"
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="image decoding processes running alongside the model (default: one per spare "
        "core, at least 1; 0 = decode in the main process)",
    )


def check_pipeline_arguments(args: argparse.Namespace) -> None:
    from fdnet.backbones import check_device_spec
    from fdnet.descriptors.pipeline import check_pipeline_settings

    check_pipeline_settings(getattr(args, "batch_size", 1), getattr(args, "workers", None))
    if hasattr(args, "device"):
        args.device = check_device_spec(args.device)


def set_threads(threads: int | None) -> None:
    """Use all cores by default; an explicit count makes runs comparable on shared machines."""
    import torch

    torch.set_num_threads(threads or os.cpu_count() or 1)


def add_training_arguments(parser: argparse.ArgumentParser, data_required: bool = True) -> None:
    """The flags of ``fdnet train [METHOD]``, the same for every trained method; each sets a
    setting of the run config (docs/runs.md)."""
    parser.add_argument(
        "--data",
        required=data_required,
        help="dataset folder with one sub-folder per condition (or a published layout, "
        "with --dataset-format)" + ("" if data_required else "; optional with --resume"),
    )
    parser.add_argument("--out", required=True, help="run directory to write (or to continue with --resume)")
    parser.add_argument("--conditions", help="comma-separated conditions to train on (default: all sub-folders)")
    parser.add_argument(
        "--frames", help="START:END slice of every condition to train on (END exclusive); " "keep the test frames out"
    )
    parser.add_argument(
        "--dataset-format", help=f"read --data in a published layout ({dataset_format_list()}); " "see docs/datasets.md"
    )
    parser.add_argument(
        "--split", help="with --dataset-format: a named split (default: the format's train split) " "or START:END"
    )
    parser.add_argument("--config", help="YAML file of settings applied on top of the preset")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one setting, e.g. --set optim.lr=1e-4 (repeatable)",
    )
    parser.add_argument(
        "--max-minutes",
        type=float,
        help="stop cleanly (with a checkpoint) after M minutes of the whole command, choosing the " "start included",
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its newest complete checkpoint"
    )
    parser.add_argument(
        "--override",
        action="store_true",
        help="with --resume: accept settings that differ from the run's (recorded in "
        "RUN_DIR/changes.yaml with the step they took effect)",
    )
    parser.add_argument(
        "--validate-reference",
        help="condition used as reference for periodic validation (which picks best/; FDNet's "
        "cpu preset also picks its trunk block on this pair before training)",
    )
    parser.add_argument("--validate-query", help="condition used as query for periodic validation")
    parser.add_argument("--validate-frames", help="START:END frames for validation (keep them out of your test split)")
    parser.add_argument("--validate-tolerance", type=int, help="frame tolerance of a correct validation match")
    parser.add_argument("--validate-every", type=int, help="validate every N steps")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--device",
        default=None,
        metavar="auto|cpu|cuda|cuda:N",
        help="where training runs (runtime.device, for every method; default auto: a GPU when " "there is one)",
    )
    parser.add_argument(
        "--threads",
        type=thread_count(0),
        default=None,
        help="torch CPU threads (runtime.threads; default: the preset's, 0 = torch's own choice)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=None,
        help="training steps in all (default: the preset's; FDNet: the joint stage takes what "
        "the pretraining stages leave)",
    )


def apply_training_arguments(config, args: argparse.Namespace):
    """Run config <- --config YAML <- data/validation/runtime flags (--device, --threads, --steps,
    --tolerance) <- --set overrides.

    Data flags are set on the dataclasses directly: through ``replace_dotted`` a frame range such
    as "10:20" given to a non-text field would be read by YAML as a base-60 integer.
    """
    import dataclasses

    from fdnet.config import apply_yaml, parse_overrides, replace_dotted

    if getattr(args, "config", None):
        config = apply_yaml(config, args.config)
    data = config.data
    if args.data is not None:
        data = dataclasses.replace(data, root=str(args.data))
    if args.conditions is not None:
        data = dataclasses.replace(data, conditions=tuple(c.strip() for c in args.conditions.split(",") if c.strip()))
    for flag in ("frames", "dataset_format", "split"):
        if getattr(args, flag, None) is not None:
            data = dataclasses.replace(data, **{flag: str(getattr(args, flag))})
    validation = config.validation
    for flag, field_name in (
        ("validate_reference", "reference"),
        ("validate_query", "query"),
        ("validate_frames", "frames"),
        ("validate_tolerance", "tolerance"),
        ("validate_every", "every"),
    ):
        if getattr(args, flag, None) is not None:
            validation = dataclasses.replace(validation, **{field_name: getattr(args, flag)})
    config = dataclasses.replace(config, data=data, validation=validation)
    # the runtime section every trained method has (fdnet.methods.settings.RuntimeConfig)
    runtime = config.runtime
    if getattr(args, "device", None) is not None:
        from fdnet.backbones import check_device_spec

        runtime = dataclasses.replace(runtime, device=check_device_spec(args.device))
    if getattr(args, "threads", None) is not None:
        from fdnet.errors import ConfigError

        if args.threads < 1:
            raise ConfigError(f"--threads must be >= 1, got {args.threads}")
        runtime = dataclasses.replace(runtime, threads=int(args.threads))
    config = dataclasses.replace(config, runtime=runtime)
    if getattr(args, "tolerance", None) is not None:
        from fdnet.errors import ConfigError

        if not hasattr(config.data, "tolerance"):
            raise ConfigError(
                f"--tolerance: {config.method if hasattr(config, 'method') else 'this method'} learns "
                "without place labels and takes no tolerance"
            )
        config = dataclasses.replace(config, data=dataclasses.replace(config.data, tolerance=int(args.tolerance)))
    if getattr(args, "steps", None) is not None:
        config = config.with_total_steps(int(args.steps))
    return replace_dotted(config, parse_overrides(args.set))


def check_resume_target(args: argparse.Namespace) -> None:
    """``--resume`` needs a run in --out; ``--override`` needs ``--resume``."""
    from fdnet import runs
    from fdnet.errors import ConfigError

    if args.override and not args.resume:
        raise ConfigError("--override only applies with --resume")
    if args.resume:
        runs.check_run_state(args.out, resume=True)


#: the most CPU threads a command takes (no machine fdnet runs on has more cores)
MAX_THREADS = 1024


def thread_count(minimum: int = 1):
    """The argparse type of every ``--threads``: a whole number in [minimum, MAX_THREADS]; other
    values are the command's one-line error, before any work (one check for every command)."""

    def parse(text: str) -> int:
        import argparse

        try:
            value = int(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"must be a whole number of threads, got {text!r}") from exc
        if not minimum <= value <= MAX_THREADS:
            raise argparse.ArgumentTypeError(f"must be between {minimum} and {MAX_THREADS}, got {text}")
        return value

    return parse


def file_options(args, method: str | None, options: dict | None = None) -> dict:
    """The method's settings from the flags (or ``options``, what :func:`method_options` gave),
    with file paths made absolute (a database records them, and later `add`/`query` calls may run
    from another directory)."""
    from pathlib import Path

    options = dict(method_options(args, method) if options is None else options)
    options.update({k: str(Path(v).resolve()) for k, v in options.items() if k in FILE_OPTIONS})
    # --method-set device=...: where it runs is the command's business, not the database's
    options.pop("device", None)
    return options
