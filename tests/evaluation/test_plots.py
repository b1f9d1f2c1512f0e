"""Plots write real PNG files (atomically) for PR curves, similarity matrices and example matches."""

from __future__ import annotations

import numpy as np
from PIL import Image

from fdnet.data.groundtruth import GroundTruth
from fdnet.evaluation import plots
from fdnet.metrics import evaluate_similarity


def _is_png(path, min_size=(100, 100)):
    with Image.open(path) as img:
        return img.format == "PNG" and img.size[0] >= min_size[0] and img.size[1] >= min_size[1]


def test_all_plots(tmp_path, rng):
    s = rng.random((20, 20)) + np.eye(20)
    gt = GroundTruth.aligned(20, 20, 1)
    m = evaluate_similarity(s, gt)
    pr = plots.plot_pr_curves({"a": (m.curve, m.auc_pr), "b": m.curve}, tmp_path / "pr.png", title="t")
    sim = plots.plot_similarity_matrix(s, tmp_path / "sim.png", gt, best=s.argmax(axis=1))
    paths = []
    for i in range(4):
        paths.append(tmp_path / f"{i}.png")
        Image.fromarray((rng.random((12, 16, 3)) * 255).astype(np.uint8)).save(paths[-1])
    ex = plots.plot_example_matches(
        paths, paths, np.array([1, 0, 2, 3]), np.array([0, 0, 1, 1]), tmp_path / "ex.png", count=4
    )
    assert all(_is_png(p) for p in (pr, sim, ex))
    assert not list(tmp_path.glob(".*.tmp"))
