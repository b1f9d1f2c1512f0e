"""The runner of ``fdnet reproduce``: checks the settings, builds the methods and the shared
:class:`~fdnet.reproduce.context.Context`, runs the chosen experiments with it and writes the
manifest, each experiment's JSON and the report.

Every experiment module (``comparison``, ``lengths``, ``similarity``, ``disentanglement``,
``viewpoint``, ``runtime`` (module ``table5_runtime``), ``examples``, and ``ablation``, which runs
only when named) has ``NAME``, ``TITLE``, ``PAPER`` (the figures/tables it reproduces),
``unavailable(ctx)`` (why it cannot run, or None), ``run(ctx) -> dict`` (the numbers, written to
``OUT/<NAME>.json``; figures under ``OUT/figures/<NAME>/``) and ``render(document)`` (the report
section's blocks, from that JSON alone, so a section survives reruns of the others).
After each experiment the report is rendered again, so an interrupted run still leaves a report of
what finished, and a rerun resumes from the descriptor cache (``OUT/cache/``).
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Callable

from fdnet.descriptors.registry import reproduce_methods
from fdnet.errors import ConfigError, FdnetError
from fdnet.evaluation.report import json_fallback
from fdnet.io import atomic_write_text, ensure_writable
from fdnet.metrics import PROTOCOLS
from fdnet.provenance import provenance
from fdnet.reproduce.context import THRESHOLDS, Context, MethodHandle, Pair, ReproduceSettings, build_pairs
from fdnet.reproduce.sections import ALL_EXPERIMENTS, EXPERIMENTS, MANIFEST, experiment_module
from fdnet.runs.lock import local_time_stamp
from fdnet.version import __version__

#: FDNet, the trunk alone and every baseline; those that cannot run here (no trained model, no
#: weights) are listed in the report with the reason, unless named explicitly with --method
DEFAULT_METHODS = reproduce_methods()  # from the method registry (its ``reproduce`` column)


def _check_fit_size(handle: MethodHandle, pairs: list[Pair], required: bool, data, log) -> None:
    """A method that learns from each comparison's reference images (no ``--fit`` folder) needs
    enough of them (``min_fit_images``); a default method without enough is listed as not run,
    one named in ``--method`` stops the command before anything is described."""
    d = handle.descriptor
    if d is None or not d.needs_fit or not pairs:
        return
    fewest = min(len(p.split.reference.paths) for p in pairs)
    if fewest >= d.min_fit_images:
        return
    reason = (
        f"learns from each comparison's reference images, which needs at least {d.min_fit_images} and "
        f"{data} gives {fewest}; give it a folder to learn from (--fit {handle.name}=DIR) or fewer "
        "dimensions (--method-set)"
    )
    if required:
        raise ConfigError(f"{handle.label}: {reason}")
    handle.descriptor, handle.reason = None, reason
    log(f"{handle.label}: not run ({reason})")


def _check(settings: ReproduceSettings) -> list[str]:
    """Settings errors before any work; returns the experiments to run."""
    from fdnet.descriptors.registry import available_methods

    if settings.protocol not in PROTOCOLS:
        raise ConfigError(f"--protocol {settings.protocol!r}: choose one of {', '.join(PROTOCOLS)}")
    chosen = list(settings.experiments or EXPERIMENTS)
    unknown = [e for e in chosen if e not in ALL_EXPERIMENTS]
    if unknown:
        raise ConfigError(f"unknown experiment(s) {', '.join(unknown)}; choose from {', '.join(ALL_EXPERIMENTS)}")
    known = available_methods()
    bad = [m for m in settings.methods or [] if m not in known]
    if bad:
        raise ConfigError(f"unknown method(s) {', '.join(bad)}; available: {', '.join(known)}")
    if settings.methods is not None and not settings.methods:
        raise ConfigError("--method is empty")
    for overlap in settings.overlaps:
        if not 0.0 < overlap <= 1.0:
            raise ConfigError(f"overlap {overlap}: must be in (0, 1] (e.g. 1,0.9,0.75,0.65)")
    if not isinstance(settings.seeds, int) or settings.seeds < 1:
        raise ConfigError(f"--seeds must be a whole number >= 1 (runs per trained variant), got {settings.seeds}")
    if settings.threads is not None and settings.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {settings.threads}")
    for name, value in (
        ("--examples", settings.examples),
        ("--runtime-images", settings.runtime_images),
        ("--batch-size", settings.batch_size),
        ("--embedding-points", settings.embedding_points),
    ):
        if value < 1:
            raise ConfigError(f"{name} must be >= 1, got {value}")
    if settings.tolerance is not None and settings.tolerance < 0:
        raise ConfigError(f"--tolerance must be >= 0, got {settings.tolerance}")
    if not Path(settings.data).is_dir():
        raise ConfigError(f"{settings.data}: dataset folder not found")
    return chosen


def _default_factory(name: str, **options):
    from fdnet.descriptors import create

    return create(name, **options)


def reproduce(
    settings: ReproduceSettings, factory: Callable | None = None, log: Callable[[str], None] | None = None
) -> Path:
    """Run the chosen experiments (default all) and write ``OUT/report.html``; returns its path.

    ``factory(name, **options)`` builds a descriptor (default :func:`fdnet.descriptors.create`);
    ``log`` receives the progress messages (default: this module's logger, at INFO).
    """
    from fdnet.reproduce.report import write_report

    log = log or logging.getLogger(__name__).info
    chosen = _check(settings)
    ensure_writable(settings.out, what="reproduce output", directory=True)
    pairs = build_pairs(settings)
    log(f"{len(pairs)} condition pair(s): {'; '.join(p.label for p in pairs)}")
    ctx = Context(settings, pairs, factory or _default_factory, log)
    methods = settings.methods or list(DEFAULT_METHODS)
    for name in methods:
        options = dict(settings.method_options.get(name, {}))
        if name in ("fdnet", "trunk", "trunk-whitened") and settings.checkpoint is not None:
            options.setdefault("checkpoint", str(settings.checkpoint))
        # named explicitly, or the FDNet run the command was given: a failure to load is an error
        required = settings.methods is not None or (name == "fdnet" and settings.checkpoint is not None)
        handle = ctx.add_method(name, name, options, required=required)
        _check_fit_size(handle, pairs, required, settings.data, log)
    # an experiment that reads only runs of its own (COMPARES_METHODS = False) needs none of them
    if not ctx.available() and any(getattr(experiment_module(n), "COMPARES_METHODS", True) for n in chosen):
        raise ConfigError(
            "none of the methods can run here: " + "; ".join(f"{s['method']}: {s['reason']}" for s in ctx.skipped())
        )
    # what cannot run is known before anything runs: an experiment asked for by name is an error
    reasons = {name: experiment_module(name).unavailable(ctx) for name in chosen}
    for name, reason in reasons.items():
        if reason and settings.experiments:
            raise ConfigError(f"experiment {name}: {reason}")
    with _thread_limits(settings.threads):
        return _run_experiments(ctx, chosen, reasons, write_report)


def _thread_limits(threads: int | None):
    """Limit BLAS and OpenMP thread pools to ``threads`` for the run (None: leave them); restored
    on exit for the pools loaded now. BLAS threads beyond the cores that are free make small
    matrix products 100x slower on a busy machine (a 100 x 10240 matrix-vector product: 0.06 ms
    with one thread, 9 ms with two on 2 loaded cores), which would be timed as matching cost.
    Libraries loaded later bring pools of their own: :meth:`Context.limit_threads` covers them."""
    import contextlib

    if not threads:
        return contextlib.nullcontext()
    # scipy and scikit-learn, which the experiments use, are loaded first so the limit covers them
    import scipy.linalg  # noqa: F401
    import sklearn.manifold  # noqa: F401
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads)


def _run_experiments(ctx: Context, chosen: list[str], reasons: dict, write_report: Callable) -> Path:
    settings, out, log = ctx.settings, ctx.out, ctx.log
    manifest = {
        "fdnet_version": __version__,
        "command": settings.command,
        "created": local_time_stamp(),
        "dataset": str(settings.data),
        "dataset_format": settings.dataset_format or "folders (one sub-folder per condition)",
        "pairs": [
            {
                "reference": p.reference,
                "query": p.query,
                "description": p.split.description,
                "num_queries": len(p.split.query),
                "num_references": len(p.split.reference),
            }
            for p in ctx.pairs
        ],
        "protocol": ctx.protocol,
        "protocol_definition": PROTOCOLS[ctx.protocol],
        "thresholds": (
            f"{THRESHOLDS} uniform over min-max-normalised best-match scores (paper 5.1.2)"
            if ctx.thresholds
            else "every top-1 score (VPR-Bench)"
        ),
        "checkpoint": str(settings.checkpoint) if settings.checkpoint else None,
        "experiments_run": chosen,
    }
    run = _checkpoint_run(settings.checkpoint)
    manifest.update(
        checkpoint_run=run,
        smoke_test=_smoke_test(run),
        provenance=provenance(
            settings.command, seeds={"checkpoint": run and run["seed"]}, device=getattr(settings, "device", None)
        ),
    )
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    for name in chosen:
        module = experiment_module(name)
        ctx.experiment = name
        reason = reasons[name]
        log(f"[{name}] {module.TITLE}" + (f": not run ({reason})" if reason else ""))
        started = time.monotonic()
        document = {"not_run": reason} if reason else module.run(ctx)
        document = {
            "experiment": name,
            "title": module.TITLE,
            "paper": module.PAPER,
            "fdnet_version": __version__,
            "command": settings.command,
            "created": local_time_stamp(),
            "dataset": str(settings.data),
            "checkpoint": manifest["checkpoint"],
            "protocol": ctx.protocol,
            "smoke_test": manifest["smoke_test"],
            **document,
            "provenance": provenance(
                settings.command, seeds=_seeds(run, document), device=getattr(settings, "device", None)
            ),
        }
        atomic_write_text(
            out / f"{name}.json", json.dumps(document, indent=1, allow_nan=False, default=json_fallback) + "\n"
        )
        ctx.remove_stale_figures()
        write_report(out)
        log(f"[{name}] done in {time.monotonic() - started:.1f} s")
    log(f"described {len(ctx.cache.computed)} image set(s), reused {ctx.cache.hits} from the cache")
    report = write_report(out)
    log(f"wrote {report}")
    return report


#: the most training steps a run may have and still be called a smoke test in the report
SMOKE_TEST_STEPS = 100


def _checkpoint_run(checkpoint) -> dict | None:
    """The FDNet run behind ``checkpoint``: its preset, seed, planned and trained steps (None
    when there is none, or it is not an FDNet run)."""
    if checkpoint is None:
        return None
    from fdnet.methods.fdnet.config import FDNetRunConfig
    from fdnet.runs import latest_checkpoint, load_config, weights_folder

    try:
        folder = weights_folder(checkpoint)
        config = load_config(folder, FDNetRunConfig)
        found = re.match(r"step-(\d+)", latest_checkpoint(folder).name)  # a generation's folder names its step
    except (FdnetError, OSError, ValueError):
        return None
    step = int(found.group(1)) if found else None
    return {"preset": config.preset, "seed": config.runtime.seed, "total_steps": config.total_steps, "step": step}


def _smoke_test(run: dict | None) -> str | None:
    """The report's warning when the FDNet run is a smoke test (the ``tiny`` preset, or at most
    :data:`SMOKE_TEST_STEPS` steps): its numbers say the pipeline runs, not what FDNet does."""
    if run is None:
        return None
    steps = run["step"] if isinstance(run.get("step"), int) else run["total_steps"]
    if run["preset"] != "tiny" and steps > SMOKE_TEST_STEPS:
        return None
    return (
        f"the FDNet run ({run['preset']} preset, {steps} training steps) is a smoke test of the pipeline, not a "
        "result: its FDNet numbers say that training, evaluation and the report run, not what FDNet does "
        "(train with --preset cpu for that)"
    )


def _seeds(run: dict | None, document: dict) -> dict:
    """The seeds an experiment's numbers depend on: the checkpoint run's, and every variant it
    trained or read (the ablation's; a list for a variant trained with several seeds)."""
    seeds = {"checkpoint": run and run["seed"]}
    for group in document.get("groups") or []:
        for info in group.get("runs") or []:
            if "seed" in info:
                key = f"{group.get('preset')}/{info['variant']}"
                if key in seeds:  # a variant trained with several seeds (--seeds N): all of them
                    seeds[key] = [*(seeds[key] if isinstance(seeds[key], list) else [seeds[key]]), info["seed"]]
                else:
                    seeds[key] = info["seed"]
    for length, values in (document.get("run_seeds") or {}).items():  # the lengths' runs, with --seeds N
        seeds[f"L{length}"] = values
    return seeds
