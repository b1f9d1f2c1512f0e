"""The main job end to end on an embedded SYNTHETIC route (no download), as ``fdnet demo`` runs it:

1. render a route under summer/autumn/winter/night (what ``fdnet synth`` writes);
2. train FDNet (``cpu`` preset by default) on the first part of the route, all conditions, no
   place labels, validating on a held-out middle part (what ``fdnet train`` does);
3. evaluate FDNet against the trunk it reads (alone and PCA-whitened to 512 on the training
   frames) and the SAD (SeqSLAM front end) and HOG baselines on the last part of the route,
   night -> summer and winter -> summer, with tables, JSON and plots (what ``fdnet evaluate`` does).

Each step calls the library function its command calls; ``say`` gets each step's heading with the
equivalent command line, and the results (the commands' standard output).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from fdnet.errors import ConfigError

DEFAULT_METHODS = "fdnet,trunk,trunk-whitened,sad,hog"
MIN_FRAMES = 40


def demo_frames(num_frames: int) -> tuple[int, int, str]:
    """(training end, validation end, test START:END): 0:250 trains, 250:300 validates and
    300:400 tests of 400 frames (the test frames are never seen in training)."""
    if num_frames < MIN_FRAMES:
        raise ConfigError(
            f"--num-frames must be at least {MIN_FRAMES} for a train/validation/test split, " f"got {num_frames}"
        )
    train_end, val_end = int(num_frames * 0.625), int(num_frames * 0.75)
    return train_end, val_end, f"{val_end}:{num_frames}"


@dataclass(frozen=True)
class DemoSettings:
    """``fdnet demo``'s settings: frames per condition of the synthetic route, the training's
    time budget, preset and seed, the methods evaluated, and whether to resume the run."""

    num_frames: int = 400
    max_minutes: float = 9.0
    preset: str = "cpu"
    methods: str = DEFAULT_METHODS
    seed: int = 0
    resume: bool = False


def run_demo(out, settings: DemoSettings | None = None, say: Callable[[str], None] = lambda line: None) -> dict:
    """Synthesise, train and evaluate into the folder ``out`` (``route/``, ``fdnet-run/``,
    ``results-QUERY-summer.json``, ``plots-QUERY-summer/``); returns {query: [MethodResult]}."""
    from fdnet.io import ensure_writable

    settings = settings or DemoSettings()
    num_frames, max_minutes, preset, seed, resume = (
        settings.num_frames,
        settings.max_minutes,
        settings.preset,
        settings.seed,
        settings.resume,
    )
    train_end, val_end, test = demo_frames(num_frames)
    out = Path(out)
    ensure_writable(out, what="demo output", directory=True)  # a file or read-only path: refused first
    route, run_dir = out / "route", out / "fdnet-run"
    started = time.perf_counter()
    say(
        "\n=== 1/3 synthetic route (SYNTHETIC images, a demo and test route, not a benchmark)\n"
        f"$ fdnet synth --out {route} --num-frames {num_frames} --seed {seed}"
    )
    _synthesise(route, num_frames, seed, say)
    say(
        f"\n=== 2/3 train FDNet on frames 0:{train_end} of every condition (no place labels)\n"
        f"$ fdnet train --data {route}" + ("" if resume else f" --preset {preset}") + f" --out {run_dir} "
        f"--frames 0:{train_end} --max-minutes {max_minutes:g} --validate-reference summer --validate-query night "
        f"--validate-frames {train_end}:{val_end} --validate-tolerance 1 --set runtime.seed={seed}"
        + (" --resume" if resume else "")
    )
    config = _train(route, run_dir, settings, say)
    chosen = [m.strip() for m in settings.methods.split(",") if m.strip()]
    if config.model.backbone == "none":  # a preset whose encoders read pixels has no trunk to compare with
        chosen = [m for m in chosen if not m.startswith("trunk")]
    results = {}
    for query in ("night", "winter"):
        fit = f" --fit {route} --fit-frames 0:{train_end}" if "trunk-whitened" in chosen else ""
        say(
            f"\n=== 3/3 evaluate {query} -> summer on frames {test} (tolerance 1 frame)\n"
            f"$ fdnet evaluate --data {route} --reference summer --query {query} --frames {test} --tolerance 1 "
            f"--method {','.join(chosen)} --checkpoint {run_dir}{fit} --json {out / f'results-{query}-summer.json'} "
            f"--plots {out / f'plots-{query}-summer'}"
        )
        results[query] = _evaluate(route, run_dir, query, chosen, settings, out, say)
    say(
        f"\ndemo finished in {(time.perf_counter() - started) / 60:.1f} min; results, plots and the trained run "
        f"are in {out}/"
    )
    return results


def _synthesise(route: Path, num_frames: int, seed: int, say) -> None:
    from fdnet.data.synthetic import generate_route

    t0 = time.perf_counter()
    dataset = generate_route(route, frames=num_frames, seed=seed)
    counts = ", ".join(f"{name} {len(t)}" for name, t in dataset.traverses.items())
    say(f"wrote SYNTHETIC route to {dataset.root} ({counts} frames) in {time.perf_counter() - t0:.1f} s")


def _train(route: Path, run_dir: Path, settings: DemoSettings, say):
    from fdnet import runs
    from fdnet.config import replace_dotted
    from fdnet.descriptors.registry import spec

    method = spec("fdnet")
    train_end, val_end, _ = demo_frames(settings.num_frames)
    preset, max_minutes, seed, resume = settings.preset, settings.max_minutes, settings.seed, settings.resume
    if resume:
        runs.check_run_state(run_dir, resume=True)
        config = runs.load_config(run_dir, method.config_class())
    else:
        config = method.preset(preset)
    config = dataclasses.replace(
        config,
        data=dataclasses.replace(config.data, root=str(route), frames=f"0:{train_end}"),
        validation=dataclasses.replace(
            config.validation, reference="summer", query="night", frames=f"{train_end}:{val_end}", tolerance=1
        ),
    )
    config = replace_dotted(config, {"runtime.seed": str(seed)})
    summary = method.train_function()(
        config, run_dir, resume=resume, override=False, max_minutes=max_minutes, progress=True, command="fdnet demo"
    )
    line = (
        f"fdnet train: fdnet {summary['status']} at step {summary['step']}/{summary['total_steps']} after "
        f"{summary['elapsed_seconds'] / 60:.1f} min; run in {summary['run_dir']}"
    )
    if summary["best_step"] >= 0:
        line += f"; best validation R@1 {summary['best_recall@1']:.3f} at step {summary['best_step']} (in best/)"
    say(line)
    return config


def _evaluate(
    route: Path, run_dir: Path, query: str, methods: list[str], settings: DemoSettings, out: Path, say
) -> list:
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE, parse_acceptance_list
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.descriptors.registry import create, setting_names
    from fdnet.evaluation.experiment import ScoringSettings, evaluate_method
    from fdnet.evaluation.plots import write_result_plots
    from fdnet.evaluation.report import format_table, write_json
    from fdnet.evaluation.splits import SplitSpec, build_split
    from fdnet.metrics import RECALL_OVER_QUERIES

    train_end, _, test = demo_frames(settings.num_frames)
    seed = settings.seed
    split = build_split(SplitSpec(route, "summer", query, frames=test, tolerance=1))
    given = {"checkpoint": str(run_dir), "fit": str(route), "fit_frames": f"0:{train_end}"}
    descriptors = []
    for name in methods:  # each method gets the settings it declares, as --checkpoint/--fit give them
        takes = setting_names(name)
        descriptors.append(create(name, **{k: v for k, v in given.items() if k in takes}))
    acceptance = parse_acceptance_list(DEFAULT_ACCEPTANCE, [])
    results = [
        evaluate_method(
            d,
            split,
            ScoringSettings((RECALL_OVER_QUERIES,), acceptance=acceptance),
            PipelineSettings(progress=True),
            keep_similarity=True,
        )
        for d in descriptors
    ]
    say(format_table(results, RECALL_OVER_QUERIES))
    json_path, plots = out / f"results-{query}-summer.json", out / f"plots-{query}-summer"
    write_json(json_path, results, seeds={"synthetic_route": seed, "runtime": seed})  # the route's and training's
    write_result_plots(results, RECALL_OVER_QUERIES, plots)
    return results
