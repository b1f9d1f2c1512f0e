"""Calibrate once, apply anywhere: a loop-closure threshold calibrated on each loop, applied to
every other loop, for several descriptors, all with the same default settings (no frame count
to tune: ``fdnet loop-closure``'s defaults), and the calibrated probability ``p_correct`` checked
on loops it was not fitted on.

Each descriptor describes each loop's frames once; the detector then runs over each loop with
the command's defaults (margin, 10-frame sequences, the gates, the recent past found from the
traverse, a new segment at each condition) and records every frame's decision. A calibration is
made on each loop (:func:`fdnet.decisions.loop_evaluation.calibrate_decisions`: the threshold for
``--target-precision``, default 1.0, and the isotonic fit of ``p_correct``), and applied to the
decisions of every other loop (a threshold changes no decision without the consistency gate, so
the decisions are computed once per loop). A row is what ``fdnet loop-closure --calibration``
with that calibration prints on that loop. Usage (the numbers in docs/loop-closure.md):

    python benchmarks/loop_transfer.py \\
        --loop nl=../shared/data/nordland_trimmed:summer,winter:1576:2576:0 \\
        --loop nl-a=../shared/data/nordland_trimmed:summer,winter:1576:2076:0 \\
        --loop nl-b=../shared/data/nordland_trimmed:summer,winter:2076:2576:0 \\
        --loop gp=../shared/data/gardens_point:day_left,night_right,day_right:100:200:2 \\
        --loop synth=SYNTH:summer,autumn:0:600:1 \\
        --descriptor fdnet-nl=fdnet:checkpoint=runs/nordland --descriptor trunk=trunk \\
        --out loop-transfer.json --plot reliability.png

``--descriptor NAME=METHOD[:KEY=VALUE,...]`` (settings as ``--method-set``); ``--loop
NAME=DATA:A,B[,C]:START:END:TOLERANCE``. Loops that share frames (nl and nl-a) are not applied to
each other. Prints the whole-loop metrics of each (descriptor, loop), then the transfer table,
then the reliability of ``p_correct`` on loops not used to fit it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from fdnet.decisions.loop_closure import LoopClosureDetector  # noqa: E402
from fdnet.decisions.loop_evaluation import calibrate_decisions, evaluate_decisions, frame_outcomes  # noqa: E402
from fdnet.decisions.loop_traverse import DEFAULT_RULE, DEFAULT_SEQUENCE_LENGTH, route_traverse  # noqa: E402

from loop_closure_grid import describe  # noqa: E402

#: p_correct bins of the reliability table
BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0)


@dataclass
class Loop:
    name: str
    data: str
    conditions: list
    start: int
    end: int
    tolerance: int

    def overlaps(self, other: "Loop") -> bool:
        return (
            self.data == other.data
            and self.conditions == other.conditions
            and self.start < other.end
            and other.start < self.end
        )


def parse_loop(text: str) -> Loop:
    name, _, spec = text.partition("=")
    parts = spec.split(":")
    if not name or len(parts) != 5:
        raise SystemExit(f"--loop {text!r}: expected NAME=DATA:A,B[,C]:START:END:TOLERANCE")
    data, conditions, start, end, tolerance = parts
    return Loop(name, data, conditions.split(","), int(start), int(end), int(tolerance))


def parse_descriptor(text: str) -> tuple[str, str, dict]:
    import yaml

    name, _, spec = text.partition("=")
    method, _, settings = spec.partition(":")
    options = {}
    for item in filter(None, settings.split(",")):
        key, _, value = item.partition("=")
        options[key] = yaml.safe_load(value)
    return name, method, options


def decide_loop(descriptor, cache, traverse) -> LoopClosureDetector:
    """The command's defaults over one loop, every frame's decision kept (threshold +inf)."""
    detector = LoopClosureDetector(
        descriptor, None, rule=DEFAULT_RULE, threshold=math.inf, sequence_length=DEFAULT_SEQUENCE_LENGTH
    )
    starts = set(np.flatnonzero(np.diff(traverse.condition_of)) + 1)
    with detector:
        for i, path in enumerate(traverse.paths):
            vector, signals = cache[path]
            detector.process_vector(vector, name=str(path), signals=signals, new_segment=i in starts)
    return detector


def main(argv=None) -> int:
    from fdnet.descriptors import create

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loop", action="append", required=True, type=parse_loop)
    parser.add_argument("--descriptor", action="append", required=True, type=parse_descriptor)
    parser.add_argument("--target-precision", type=float, default=1.0)
    parser.add_argument("--out")
    parser.add_argument("--plot", help="PNG of the reliability diagram of p_correct on loops not used to fit it")
    args = parser.parse_args(argv)

    traverses = {
        loop.name: route_traverse(loop.data, loop.conditions, f"{loop.start}:{loop.end}", loop.tolerance)
        for loop in args.loop
    }
    loops = {loop.name: loop for loop in args.loop}
    results = {"argv": sys.argv[1:], "loops": {}, "transfer": [], "reliability": {}}
    reliability = {}
    for name, method, options in args.descriptor:
        descriptor = create(method, **options)
        decisions, calibrations = {}, {}
        for loop_name, traverse in traverses.items():
            t0 = time.perf_counter()
            cache = describe(descriptor, list(traverse.paths))
            detector = decide_loop(descriptor, cache, traverse)
            truth = traverse.ground_truth()
            decisions[loop_name] = (detector.decisions, truth)
            ev = evaluate_decisions(detector.decisions, truth, math.inf, detector.spec.name)
            m = ev["metrics"]
            back = np.asarray(detector.excluded_back)
            calibrations[loop_name] = calibrate_decisions(detector.decisions, truth, detector, args.target_precision)
            c = calibrations[loop_name]
            row = {
                "R@100P": m["recall_at_100_precision"],
                "R@99P": m["recall_at_99_precision"],
                "AUC-PR": m["auc_pr"],
                "R@1": m["recall_at_n"]["1"],
                "revisits": ev["frames_with_revisit"],
                "recall_ceiling": ev["reachable"]["recall_ceiling"],
                "revisits_gated": ev["reachable"]["gated"],
                "threshold": c.threshold,
                "calibration_recall": c.recall,
                "calibration_accepted": c.accepted,
                "excluded_back_median": float(np.median(back)),
                "excluded_back_p90": float(np.percentile(back, 90)),
                "excluded_back_max": int(back.max()),
            }
            results["loops"].setdefault(name, {})[loop_name] = row
            print(
                f"{name:16s} {loop_name:8s} R@100P {row['R@100P']:.3f} R@99P {row['R@99P']:.3f} AUC-PR "
                f"{row['AUC-PR']:.3f} R@1 {row['R@1']:.3f} ({row['revisits']} revisits; recall ceiling "
                f"{row['recall_ceiling']:.3f}, gated {row['revisits_gated']}); recent past excluded: "
                f"median {row['excluded_back_median']:.0f}, p90 {row['excluded_back_p90']:.0f}, max "
                f"{row['excluded_back_max']} frames; threshold for precision {args.target_precision:g}: "
                f"{c.threshold:.4g} ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
        for source, calibration in calibrations.items():
            for target, (target_decisions, truth) in decisions.items():
                if target == source or loops[source].overlaps(loops[target]):
                    continue
                at = evaluate_decisions(target_decisions, truth, calibration.threshold, DEFAULT_RULE)["at_threshold"]
                scores, right, _ = frame_outcomes(target_decisions, truth)
                p = calibration.p_correct(scores)
                finite = np.isfinite(scores) & np.isfinite(p)
                sure = finite & (p >= 0.99)
                reliability.setdefault(name, []).append((p[finite], right[finite]))
                row = {
                    "descriptor": name,
                    "calibrated_on": source,
                    "applied_to": target,
                    "threshold": calibration.threshold,
                    "precision": at["precision"],
                    "recall": at["recall"],
                    "accepted": at["accepted"],
                    "false": at["false"],
                    "p_correct_at_least_0.99": int(sure.sum()),
                    "right_among_them": float(right[sure].mean()) if sure.any() else None,
                }
                results["transfer"].append(row)
                sure_text = (
                    f"; p_correct >= 0.99: {row['p_correct_at_least_0.99']} frames, "
                    f"{100 * row['right_among_them']:.1f} % right"
                    if sure.any()
                    else "; no frame with p_correct >= 0.99"
                )
                print(
                    f"  {name:16s} calibrated on {source:8s} -> {target:8s}: threshold {calibration.threshold:.4g}, "
                    f"precision {at['precision']:.3f}, recall {at['recall']:.3f} ({at['accepted']} accepted, "
                    f"{at['false']} false){sure_text}",
                    flush=True,
                )
    print("\np_correct on loops not used to fit it (every frame that searched a place):")
    for name, pairs in reliability.items():
        p = np.concatenate([a for a, _ in pairs])
        right = np.concatenate([b for _, b in pairs])
        table = []
        for lo, hi in zip(BINS[:-1], BINS[1:]):
            inside = (p >= lo) & ((p < hi) if hi < 1.0 else (p <= hi))
            table.append(
                {
                    "from": lo,
                    "to": hi,
                    "frames": int(inside.sum()),
                    "mean_p_correct": float(p[inside].mean()) if inside.any() else None,
                    "right": float(right[inside].mean()) if inside.any() else None,
                }
            )
        results["reliability"][name] = table
        print(
            f"  {name}: "
            + "; ".join(
                f"[{b['from']:g}, {b['to']:g}): {b['frames']} frames, p {b['mean_p_correct']:.3f}, "
                f"right {b['right']:.3f}"
                for b in table
                if b["frames"]
            )
        )
    if args.plot:
        plot_reliability(results["reliability"], args.plot)
        print(f"wrote {args.plot}")
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(results, handle, indent=1, default=float)
        print(f"wrote {args.out}")
    return 0


def plot_reliability(reliability: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(4.5, 4.5))
    axis.plot([0, 1], [0, 1], color="grey", linestyle=":", label="perfectly calibrated")
    for name, table in reliability.items():
        used = [b for b in table if b["frames"]]
        axis.plot([b["mean_p_correct"] for b in used], [b["right"] for b in used], marker="o", label=name)
        for b in used:
            axis.annotate(
                str(b["frames"]),
                (b["mean_p_correct"], b["right"]),
                fontsize=6,
                textcoords="offset points",
                xytext=(3, -8),
            )
    axis.set_xlabel("p_correct (fitted on another loop)")
    axis.set_ylabel("share of those frames whose match is right")
    axis.set_title("loop closure: p_correct on loops it was not fitted on", fontsize=9)
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    sys.exit(main())
