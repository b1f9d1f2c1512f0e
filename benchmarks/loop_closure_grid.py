"""Loop closure on a real route driven twice: every (descriptor, rule, sequence length, gates)
setting measured on one loop, and a threshold calibrated on one loop applied to another.

Each descriptor describes the frames once (vectors and the gates' pixel signals, as
``fdnet loop-closure`` computes them); every setting then runs the same
:class:`fdnet.decisions.loop_closure.LoopClosureDetector` over the vectors, frame by frame, and
is evaluated with the same functions as the command (so a row equals what
``fdnet loop-closure --data ... --conditions ...`` prints for that setting). Usage (the numbers
in docs/loop-closure.md):

    python benchmarks/loop_closure_grid.py --data ../shared/data/nordland_trimmed \\
        --conditions summer,winter --frames 1576:2576 --tolerance 0 \\
        --calibrate-frames 1576:2076 --test-frames 2076:2576 \\
        --method fdnet --checkpoint runs/nordland/best --out loop-grid-nordland.json

Prints one line per setting: R@100P, R@99P, AUC-PR on the whole loop, and the calibrated
transfer (threshold for precision 1.0 on the calibration loop; precision and recall it reaches
on the test loop).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time

import numpy as np

from fdnet.cli.common import add_method_arguments, create_descriptor
from fdnet.decisions.loop_closure import LoopClosureDetector
from fdnet.decisions.loop_evaluation import calibrate_decisions, evaluate_decisions
from fdnet.decisions.loop_gates import LoopGates, frame_signals
from fdnet.decisions.loop_traverse import route_traverse
from fdnet.descriptors.pipeline import DescribeJob, PipelineSettings, describe_stream

#: gate settings compared (name -> LoopGates); "none" switches every gate off
GATES = {
    "none": LoopGates(min_brightness=None, min_contrast=None, still_difference=None, similar_past=False),
    "uninformative": LoopGates(still_difference=None, similar_past=False),
    "uninformative+still": LoopGates(similar_past=False),
    "uninformative+still+past": LoopGates(),
    "uninformative+still+past+k3": LoopGates(consistency=3),
}


def describe(descriptor, paths, batch_size: int = 32):
    """{path: (vector, signals)} for every path, in one pass."""
    out = {}
    for start, (vectors, signals) in describe_stream(
        descriptor,
        paths,
        PipelineSettings(batch_size),
        DescribeJob(lambda images: (descriptor.describe(images), frame_signals(images))),
    ):
        for i, vector in enumerate(np.asarray(vectors, np.float32)):
            out[paths[start + i]] = (vector, signals[i])
    return out


def run(descriptor, cache, traverse, exclude_last, rule, length, gates, threshold=math.inf):
    detector = LoopClosureDetector(
        descriptor, None, exclude_last=exclude_last, rule=rule, threshold=threshold, sequence_length=length, gates=gates
    )
    starts = set(np.flatnonzero(np.diff(traverse.condition_of)) + 1)  # each condition is a new recording
    with detector:
        for i, path in enumerate(traverse.paths):
            vector, signals = cache[path]
            detector.process_vector(vector, name=str(path), signals=signals, new_segment=i in starts)
        return detector, list(detector.decisions), dict(detector.gate_counts)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--conditions", required=True)
    parser.add_argument("--frames", required=True)
    parser.add_argument("--tolerance", type=int, default=0)
    parser.add_argument("--exclude-last", type=int, default=0)
    parser.add_argument("--calibrate-frames")
    parser.add_argument("--test-frames")
    parser.add_argument("--rules", default="raw,margin")
    parser.add_argument("--lengths", default="1,5,10")
    parser.add_argument("--gates", default=",".join(GATES))
    parser.add_argument("--target-precision", type=float, default=1.0)
    parser.add_argument("--out")
    add_method_arguments(parser)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)

    conditions = args.conditions.split(",")
    whole = route_traverse(args.data, conditions, args.frames, args.tolerance)
    loops = {"whole": whole}
    if args.calibrate_frames and args.test_frames:
        loops["calibrate"] = route_traverse(args.data, conditions, args.calibrate_frames, args.tolerance)
        loops["test"] = route_traverse(args.data, conditions, args.test_frames, args.tolerance)
    paths = sorted({p for t in loops.values() for p in t.paths})
    results = []
    for method in args.method.split(","):
        descriptor = create_descriptor(method, args)
        t0 = time.perf_counter()
        cache = describe(descriptor, paths)
        print(f"# {method}: described {len(paths)} frames in {time.perf_counter() - t0:.1f} s", flush=True)
        for rule, length, gate_name in itertools.product(
            args.rules.split(","), [int(v) for v in args.lengths.split(",")], args.gates.split(",")
        ):
            gates = GATES[gate_name]
            detector, decisions, counts = run(descriptor, cache, whole, args.exclude_last, rule, length, gates)
            ev = evaluate_decisions(decisions, whole.ground_truth(), math.inf, detector.spec.name)
            m = ev["metrics"]
            row = {
                "method": method,
                "rule": rule,
                "sequence_length": length,
                "gates": gate_name,
                "R@100P": m["recall_at_100_precision"],
                "R@99P": m["recall_at_99_precision"],
                "AUC-PR": m["auc_pr"],
                "R@1": m["recall_at_n"]["1"],
                "gate_counts": counts,
            }
            if "calibrate" in loops:
                cal_detector, cal_decisions, _ = run(
                    descriptor, cache, loops["calibrate"], args.exclude_last, rule, length, gates
                )
                calibration = calibrate_decisions(
                    cal_decisions, loops["calibrate"].ground_truth(), cal_detector, args.target_precision
                )
                _, test_decisions, _ = run(
                    descriptor,
                    cache,
                    loops["test"],
                    args.exclude_last,
                    rule,
                    length,
                    gates,
                    threshold=calibration.threshold,
                )
                at = evaluate_decisions(test_decisions, loops["test"].ground_truth(), calibration.threshold, rule)[
                    "at_threshold"
                ]
                row.update(
                    {
                        "threshold": calibration.threshold,
                        "calibration_recall": calibration.recall,
                        "test_precision": at["precision"],
                        "test_recall": at["recall"],
                        "test_accepted": at["accepted"],
                        "test_false": at["false"],
                    }
                )
            results.append(row)
            transfer = ""
            if "threshold" in row:
                transfer = (
                    f" | calibrated {row['threshold']:.4g} (recall {row['calibration_recall']:.3f}) -> test "
                    f"precision {row['test_precision']:.3f} recall {row['test_recall']:.3f} "
                    f"({row['test_accepted']} accepted, {row['test_false']} false)"
                )
            print(
                f"{method:15s} {rule:7s} L={length:<3d} {gate_name:24s} R@100P {row['R@100P']:.3f} "
                f"R@99P {row['R@99P']:.3f} AUC {row['AUC-PR']:.3f} R@1 {row['R@1']:.3f}{transfer}",
                flush=True,
            )
    if args.out:
        with open(args.out, "w") as handle:
            json.dump({"argv": sys.argv[1:], "results": results}, handle, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
