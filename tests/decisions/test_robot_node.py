"""docs/guide.md's robot node, run as printed: killed between storing a frame and handing on its
closure, the restarted node hands on exactly the closures of an uninterrupted run."""

import json
import math
import re
from pathlib import Path

import numpy as np

from fdnet.decisions.calibration import save_calibration
from fdnet.decisions.loop_evaluation import calibrate_decisions
from fdnet.performance.loop_benchmark import StoredVectors
from tests.decisions.test_loop_recency import drive, revisit_truth, slow_route

GUIDE = Path(__file__).resolve().parents[2] / "docs" / "guide.md"


def robot_node_from_the_guide():
    text = GUIDE.read_text()
    code = re.search(r"<!-- robot-node -->\n```python\n(.*?)```\n<!-- /robot-node -->", text, re.S).group(1)
    namespace: dict = {}
    exec(compile(code, str(GUIDE), "exec"), namespace)
    return namespace["robot_node"]


class VectorFrames(StoredVectors):
    """Frames that are their own vectors: (1, dim, 3) 'images' holding (v + 1) / 2."""

    name = "vector-frames"

    def __init__(self, dim):
        super().__init__(dim)
        self.input_size = (1, dim)


def test_the_guides_robot_node_loses_no_closure_when_killed_and_restarted(tmp_path, monkeypatch):
    robot_node = robot_node_from_the_guide()
    first, second = slow_route(n=80)
    calibration = calibrate_decisions(drive(first, second).decisions, revisit_truth(80), drive(first, second), 1.0)
    calibration.fingerprint = VectorFrames(64).fingerprint()  # the same vectors, fed as frames
    calibration.method = VectorFrames.name
    save_calibration(calibration, tmp_path / "cal.yaml")
    other_first, other_second = slow_route(n=80, seed=3)
    frames = [
        ((v + 1) / 2).reshape(1, 64, 1).repeat(3, axis=2).astype(np.float32)
        for v in np.concatenate([other_first, other_second])
    ]
    # the frame's 'pixels' are its vector: the detector resizes nothing at (1, 64) and reads no gate
    monkeypatch.setattr("fdnet.decisions.loop_closure.frame_signals", lambda images: None)
    monkeypatch.setattr(
        VectorFrames,
        "describe",
        lambda self, images: 2 * np.asarray(images, np.float32)[..., 0].reshape(len(images), -1) - 1,
    )

    def read(path):
        return [json.loads(line) for line in Path(path).read_text().splitlines()]

    whole = tmp_path / "whole"
    whole.mkdir()
    robot_node(
        frames,
        VectorFrames(64),
        tmp_path / "cal.yaml",
        "run1",
        map_path=whole / "map.db",
        events_path=whole / "closures.jsonl",
    )
    expected = read(whole / "closures.jsonl")
    assert len(expected) > 10 and all(0.0 < e["p_correct"] < 1.0 for e in expected)

    # killed after storing the frame of its 6th closure but before handing it on
    killed = tmp_path / "killed"
    killed.mkdir()
    stop = expected[5]["query_index"] + 1
    robot_node(
        frames[:stop],
        VectorFrames(64),
        tmp_path / "cal.yaml",
        "run1",
        map_path=killed / "map.db",
        events_path=killed / "closures.jsonl",
    )
    lines = (killed / "closures.jsonl").read_text().splitlines(keepends=True)
    assert len(lines) == 6
    (killed / "closures.jsonl").write_text("".join(lines[:5]) + lines[5][:20])  # and tore the last line
    robot_node(
        frames,
        VectorFrames(64),
        tmp_path / "cal.yaml",
        "run1",
        map_path=killed / "map.db",
        events_path=killed / "closures.jsonl",
    )
    text = (killed / "closures.jsonl").read_text()
    complete = [json.loads(line) for line in text.splitlines() if line.endswith("}")]
    assert [e["query"] for e in complete] == [e["query"] for e in expected]
    assert [e["score"] for e in complete] == [e["score"] for e in expected]
    assert not math.isnan(complete[0]["p_correct"])
