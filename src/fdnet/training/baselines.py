"""Training loops of the trained baselines, CALC and NetVLAD.

Both write a run directory with :mod:`fdnet.training.checkpoint` (``model.safetensors`` +
``config.yaml`` + ``training_state.pt``) that ``CALCDescriptor(checkpoint=...)`` /
``NetVLADDescriptor(checkpoint=...)`` load, and both resume exactly from their last checkpoint
(weights, optimiser, step, random-number states). Stopping is by a step count or a wall-clock
budget (``max_minutes``), whichever comes first; the model is saved either way.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from fdnet.data.dataset import RouteDataset, parse_frame_range
from fdnet.data.images import load_images
from fdnet.errors import ConfigError, DataError
from fdnet.io import atomic_write_text

Log = Callable[[str], None]

HISTORY_FILE = "history.csv"


# ----------------------------------------------------------------------------- shared helpers
@dataclass
class TrainingDataConfig:
    """Which images a baseline was trained on (recorded in the run; reused by ``--resume``)."""

    root: str = ""
    #: condition sub-folders used (empty = all)
    conditions: list[str] = field(default_factory=list)
    #: "START:END" slice of every condition (empty = all frames)
    frames: str = ""
    #: frame tolerance of the ground truth (NetVLAD's positives; CALC ignores it)
    tolerance: int = 0


def load_method_config(run_dir, cls, method: str):
    """Read a baseline run's config into ``cls``, first checking that the run directory holds a run
    of ``method`` (a CALC run given to NetVLAD is an error that says so)."""
    import yaml

    from fdnet.training.checkpoint import CONFIG_FILE as config_file, load_config

    run_dir = Path(run_dir)
    path = run_dir / config_file
    if run_dir.is_dir() and path.is_file():
        try:
            saved_method = (yaml.safe_load(path.read_text()) or {}).get("method")
        except (yaml.YAMLError, AttributeError):
            saved_method = None
        if saved_method != method:
            what = f"a {saved_method!r} run" if saved_method else "not a baseline run (no 'method' setting)"
            raise ConfigError(f"{path}: is {what}, not a {method} run; give --checkpoint the --out folder "
                              f"of `fdnet train-baseline {method}`")
    return load_config(run_dir, cls)


def training_dataset(data) -> RouteDataset:
    """The route (conditions, frame slice) a :class:`TrainingDataConfig` names."""
    if not data.root:
        raise ConfigError("no training data given (--data DIR, a folder with one sub-folder per condition)")
    dataset = RouteDataset.from_folder(data.root, list(data.conditions) or None)
    start, end = parse_frame_range(data.frames or None)
    dataset = dataset.frames(start, end)
    for name, traverse in dataset.traverses.items():
        if len(traverse) == 0:
            raise DataError(f"{Path(data.root) / name}: frame range {data.frames!r} selects no images")
    return dataset


def load_in_chunks(paths: list[Path], size: tuple[int, int], convert: Callable[[np.ndarray], np.ndarray],
                   chunk: int = 256) -> np.ndarray:
    """Load images at ``size`` and ``convert`` them chunk by chunk (bounded memory)."""
    parts = [convert(load_images(paths[i:i + chunk], size)) for i in range(0, len(paths), chunk)]
    return np.concatenate(parts, axis=0)


def _rng_state(rng: np.random.Generator) -> str:
    # numpy's PCG64 state holds 128-bit integers; JSON keeps them exact and is a plain string.
    return json.dumps(rng.bit_generator.state)


def _set_rng_state(rng: np.random.Generator, text: str) -> None:
    rng.bit_generator.state = json.loads(text)


class _Stopper:
    """Step budget and wall-clock budget, whichever runs out first."""

    def __init__(self, steps: int, max_minutes: float | None):
        self.steps = int(steps)
        self.deadline = None if not max_minutes else time.monotonic() + 60.0 * float(max_minutes)

    def done(self, step: int) -> bool:
        return step >= self.steps or (self.deadline is not None and time.monotonic() >= self.deadline)


def _write_history(run_dir: Path, history: list[dict]) -> None:
    if not history:
        return
    keys = list(history[0])
    lines = [",".join(keys)] + [",".join(f"{row[k]:.6g}" if isinstance(row[k], float) else str(row[k])
                                          for k in keys) for row in history]
    atomic_write_text(run_dir / HISTORY_FILE, "\n".join(lines) + "\n")


def _resume(run_dir, name: str, network, optimizer, rng, log) -> tuple[int, list, float]:
    """Restore weights, optimiser and both RNG streams of run ``name``; return (step, history,
    seconds trained so far), so the run continues exactly where it stopped."""
    import torch

    from fdnet.training.checkpoint import load_training_state, load_weights

    load_weights(run_dir, {name: network})
    state = load_training_state(run_dir, {name: optimizer})
    step, seconds = int(state["step"]), float(state.get("seconds", 0.0))
    _set_rng_state(rng, state["numpy_rng"])
    torch.set_rng_state(state["torch_rng"])
    log(f"resuming {name} from step {step}")
    return step, _read_history(run_dir), seconds


def _read_history(run_dir: Path) -> list[dict]:
    path = run_dir / HISTORY_FILE
    if not path.is_file():
        return []
    lines = path.read_text().splitlines()
    keys = lines[0].split(",")
    rows = []
    for line in lines[1:]:
        values = line.split(",")
        rows.append({k: (int(v) if k == "step" else float(v)) for k, v in zip(keys, values)})
    return rows


def _refuse_existing_run(run_dir: Path) -> None:
    from fdnet.training.checkpoint import WEIGHTS_FILE

    if (run_dir / WEIGHTS_FILE).exists():
        raise ConfigError(f"{run_dir}: already holds a training run; use --resume to continue it, "
                          "or pick another --out")


def _check_resumable(run_dir: Path, saved, requested) -> None:
    """A resumed run must keep the model and data it was started with; only the training budget
    (steps, checkpoint/log cadence) may change."""
    from fdnet.training.checkpoint import check_config, config_differences

    keys = [d.split(":")[0] for d in config_differences(saved, requested)]
    allowed = {"train.steps", "train.checkpoint_every", "train.log_every"}
    check_config(run_dir, saved, requested, [k for k in keys if k not in allowed])


def _make_optimizer(params, train):
    import torch

    if train.optimizer == "adam":
        return torch.optim.Adam(params, lr=train.lr)
    if train.optimizer == "sgd":
        return torch.optim.SGD(params, lr=train.lr, momentum=train.momentum, weight_decay=train.weight_decay)
    raise ConfigError(f"train.optimizer: {train.optimizer!r} is not one of adam, sgd")


# ----------------------------------------------------------------------------- CALC
def train_calc(config, run_dir: str | Path, resume: bool = False, max_minutes: float | None = None,
               log: Log = print) -> dict:
    """Train CALC (unsupervised: no place labels) on every image of the configured conditions and
    frames. Returns a summary (steps, final loss, seconds)."""
    import torch

    from fdnet.descriptors import calc
    from fdnet.descriptors.backbone import bf16_supported
    from fdnet.training.checkpoint import save_run

    run_dir = Path(run_dir)
    train = config.train
    if train.batch_size < 1 or train.steps < 0:
        raise ConfigError("train.batch_size must be >= 1 and train.steps >= 0")
    if not 0.0 <= train.swap_probability <= 1.0:
        raise ConfigError(f"train.swap_probability must be in [0, 1], got {train.swap_probability}")
    if resume:
        saved = calc.load_run_config(run_dir)
        _check_resumable(run_dir, saved, config)
    else:
        _refuse_existing_run(run_dir)

    dataset = training_dataset(config.data)
    paths = [p for t in dataset.traverses.values() for p in t.paths]
    if len(paths) < train.batch_size:
        raise DataError(f"{config.data.root}: {len(paths)} training images, fewer than one batch "
                        f"({train.batch_size}); add images or lower train.batch_size")

    model_cfg = config.model
    rng = np.random.default_rng(train.seed)
    torch.manual_seed(train.seed)  # before building: the initial weights come from it
    network = calc.build_network(model_cfg)
    optimizer = _make_optimizer(network.parameters(), train)
    step, history, seconds_before = 0, [], 0.0
    if resume:
        step, history, seconds_before = _resume(run_dir, "calc", network, optimizer, rng, log)

    t_load = time.perf_counter()
    images = load_in_chunks(paths, tuple(model_cfg.input_size), calc.to_grey_u8)
    hog = calc.hog_descriptor(model_cfg.hog)
    targets = calc.compute_hog(images, model_cfg.hog, hog)
    log(f"CALC: {len(paths)} training images from {', '.join(dataset.conditions)} at "
        f"{model_cfg.input_size[0]}x{model_cfg.input_size[1]}, HOG targets {targets.shape[1]}-d, "
        f"descriptor {network.descriptor_dim}-d ({time.perf_counter() - t_load:.1f} s to prepare)")

    if not resume and train.init_output_bias:
        # Start the decoder at the mean HOG (sigmoid^-1 of it) instead of 0.5 everywhere: the large
        # first-step error otherwise drives most bottleneck ReLUs dead before anything is learnt.
        mean = np.clip(targets.mean(axis=0), 1e-3, 1 - 1e-3)
        with torch.no_grad():
            network.decoder[-2].bias.copy_(torch.from_numpy(np.log(mean / (1 - mean)).astype(np.float32)))

    use_bf16 = bool(train.bf16) and bf16_supported()
    stopper = _Stopper(train.steps, max_minutes)
    height, width = model_cfg.input_size
    t_start = time.perf_counter()
    running, running_active = [], []

    def save() -> None:
        elapsed = seconds_before + time.perf_counter() - t_start
        _write_history(run_dir, history)
        save_run(run_dir, {"calc": network}, config, optimizers={"calc": optimizer},
                 state={"step": step, "seconds": elapsed, "numpy_rng": _rng_state(rng),
                        "torch_rng": torch.get_rng_state()})

    network.to(memory_format=torch.channels_last).train()
    while not stopper.done(step):
        batch = rng.integers(0, len(images), size=train.batch_size)
        inputs = np.empty((train.batch_size, height, width), np.uint8)
        target = np.empty((train.batch_size, targets.shape[1]), np.float32)
        for row, index in enumerate(batch):
            warped = calc.random_perspective_warp(images[index], rng)
            if rng.random() < train.swap_probability:
                # original in, HOG of the warp out
                inputs[row] = images[index]
                target[row] = calc.compute_hog(warped[None], model_cfg.hog, hog)[0]
            else:
                inputs[row] = warped
                target[row] = targets[index]
        # channels_last: oneDNN's convolutions run about twice as fast in it on CPU (measured)
        x = torch.from_numpy(inputs.astype(np.float32) / 255.0)[:, None].contiguous(memory_format=torch.channels_last)
        y = torch.from_numpy(target)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=use_bf16):
            code = network.encode(x)
            prediction = network.decoder(code)
        loss = calc.euclidean_loss(prediction.float(), y)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"CALC loss became {loss.item()} at step {step}; lower train.lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        running.append(float(loss.item()))
        # share of bottleneck values above zero: 0 means every ReLU died and descriptors are all-zero
        running_active.append(float((code.detach() > 0).float().mean()))
        if step % train.log_every == 0 or stopper.done(step):
            elapsed = seconds_before + time.perf_counter() - t_start
            history.append({"step": step, "loss": float(np.mean(running)),
                            "active_units": float(np.mean(running_active)), "seconds": elapsed})
            log(f"step {step}/{train.steps} loss {np.mean(running):.4f} active bottleneck units "
                f"{np.mean(running_active):.2f} ({elapsed:.0f} s)")
            if np.mean(running_active) == 0.0:
                log("warning: every CALC bottleneck unit is zero (dead ReLUs); descriptors carry no "
                    "information. Lower train.lr or restart with model.init=he")
            running, running_active = [], []
        if step % train.checkpoint_every == 0:
            save()
    save()
    network.eval()
    total = seconds_before + time.perf_counter() - t_start
    final = history[-1]["loss"] if history else float("nan")
    log(f"CALC saved to {run_dir} after {step} steps ({total:.0f} s training)")
    return {"steps": step, "loss": final, "seconds": total, "run_dir": str(run_dir)}


# ----------------------------------------------------------------------------- NetVLAD
def _aligned_conditions(dataset: RouteDataset, root: str) -> np.ndarray:
    """Frame ids shared by every condition (frame-aligned ground truth needs identical ones)."""
    traverses = list(dataset.traverses.values())
    if len(traverses) < 2:
        raise DataError(f"{root}: NetVLAD trains on query/reference pairs from different conditions; "
                        f"give at least two (got {', '.join(dataset.conditions) or 'none'})")
    frame_ids = traverses[0].frame_ids
    for traverse in traverses[1:]:
        if len(traverse) != len(frame_ids) or not np.array_equal(traverse.frame_ids, frame_ids):
            raise DataError(f"{Path(root) / traverse.name} has {len(traverse)} frames but "
                            f"{Path(root) / traverses[0].name} has {len(frame_ids)}: frame-aligned "
                            "ground truth needs the same frames in every training condition")
    return frame_ids


def _triplet_candidates(frame_ids: np.ndarray, tolerance: int, negative_distance: int):
    """Per frame: indices of its positives (|d| <= tolerance) and negatives (|d| > negative_distance)."""
    gap = np.abs(frame_ids[:, None] - frame_ids[None, :])
    positives = [np.flatnonzero(row <= tolerance) for row in gap]
    negatives = [np.flatnonzero(row > negative_distance) for row in gap]
    return positives, negatives


def _frozen_maps(extractor, paths: list[Path], size: tuple[int, int], chunk: int = 64):
    """The frozen trunk's maps of every image, computed once (float32 (N, C, h, w) tensor)."""
    import torch

    parts = [extractor.features_tensor(load_images(paths[i:i + chunk], size)) for i in range(0, len(paths), chunk)]
    return torch.cat(parts, dim=0)


def _describe_maps(network, maps, bf16: bool, chunk: int = 128):
    """No-gradient descriptors of cached maps (for mining, k-means and PCA)."""
    import torch

    out = []
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        for i in range(0, len(maps), chunk):
            out.append(network.vlad_vectors(maps[i:i + chunk]).float())
    return torch.cat(out).numpy()


def _kmeans_init(network, maps, train, rng: np.random.Generator, log: Log) -> None:
    """Cluster centres by k-means on L2-normalised local features of the last fine-tuned block."""
    import faiss
    import torch

    model_clusters = network.vlad.centroids.shape[0]
    order = rng.permutation(len(maps))[: min(len(maps), 512)]
    with torch.no_grad():
        local = torch.cat([network.local_features(maps[order[i:i + 64]]) for i in range(0, len(order), 64)])
    local = local.permute(0, 2, 3, 1).reshape(-1, local.shape[1]).numpy().astype(np.float32)
    local /= np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-12)
    if len(local) < model_clusters:
        raise DataError(f"only {len(local)} local features for {model_clusters} NetVLAD clusters; "
                        "use more images, a larger input_size or fewer model.clusters")
    local = local[rng.permutation(len(local))[: train.kmeans_samples]]
    kmeans = faiss.Kmeans(local.shape[1], model_clusters, niter=25, seed=int(train.seed), verbose=False)
    kmeans.train(local)
    alpha = network.vlad.initialise(kmeans.centroids.astype(np.float32), local)
    log(f"NetVLAD: {model_clusters} clusters from k-means on {len(local)} local features, alpha {alpha:.1f}")


def train_netvlad(config, run_dir: str | Path, resume: bool = False, max_minutes: float | None = None,
                  log: Log = print) -> dict:
    """Train NetVLAD with the triplet loss on the training split's frame-aligned ground truth
    (queries and references from different conditions). Returns a summary."""
    import torch

    from fdnet.descriptors import netvlad
    from fdnet.descriptors.backbone import FeatureExtractor, bf16_supported
    from fdnet.training.checkpoint import save_run

    run_dir = Path(run_dir)
    model_cfg, train, data = config.model, config.train, config.data
    netvlad.check_model_config(model_cfg)
    if train.batch_size < 1 or train.steps < 0 or train.hard_negatives < 1 or train.negatives_sampled < 1:
        raise ConfigError("NetVLAD train.batch_size, hard_negatives and negatives_sampled must be >= 1, steps >= 0")
    if data.tolerance < 0 or train.negative_distance < data.tolerance:
        raise ConfigError(f"NetVLAD negatives must lie farther than the positives: train.negative_distance "
                          f"({train.negative_distance}) must be >= the tolerance ({data.tolerance}) >= 0")
    if train.cache_refresh < 1:
        raise ConfigError("NetVLAD train.cache_refresh must be >= 1")
    if resume:
        _check_resumable(run_dir, netvlad.load_run_config(run_dir), config)
    else:
        _refuse_existing_run(run_dir)

    dataset = training_dataset(data)
    frame_ids = _aligned_conditions(dataset, data.root)
    positives, negatives = _triplet_candidates(frame_ids, data.tolerance, train.negative_distance)
    lonely = [int(frame_ids[i]) for i, n in enumerate(negatives) if len(n) == 0]
    if lonely:
        raise DataError(f"{data.root}: frame {lonely[0]} has no negative (no training frame is more than "
                        f"{train.negative_distance} frames away); train on more frames or lower "
                        "train.negative_distance")
    if len(frame_ids) < train.batch_size:
        raise DataError(f"{data.root}: {len(frame_ids)} training frames, fewer than one batch "
                        f"({train.batch_size}); add frames or lower train.batch_size")
    if model_cfg.pca_dim and len(frame_ids) * len(dataset.conditions) <= model_cfg.pca_dim:
        raise ConfigError(f"NetVLAD model.pca_dim {model_cfg.pca_dim} needs more training images than that "
                          f"(have {len(frame_ids) * len(dataset.conditions)}); lower it or set 0")

    use_bf16 = bool(train.bf16) and bf16_supported()
    rng = np.random.default_rng(train.seed)
    torch.manual_seed(train.seed)
    network = netvlad.build_network(model_cfg, pretrained=True)
    t_prep = time.perf_counter()
    extractor = FeatureExtractor(block=model_cfg.frozen_block, bf16=use_bf16)
    size = tuple(model_cfg.input_size)
    maps = {name: _frozen_maps(extractor, t.paths, size) for name, t in dataset.traverses.items()}
    conditions = dataset.conditions
    all_maps = torch.cat([maps[c] for c in conditions])
    log(f"NetVLAD: {len(frame_ids)} frames x {len(conditions)} conditions ({', '.join(conditions)}), "
        f"trunk maps {tuple(all_maps.shape[1:])} cached in {time.perf_counter() - t_prep:.0f} s")

    parameters = [p for p in network.parameters() if p.requires_grad]
    optimizer = _make_optimizer(parameters, train)
    step, history, seconds_before = 0, [], 0.0
    if resume:
        step, history, seconds_before = _resume(run_dir, "netvlad", network, optimizer, rng, log)
    else:
        network.eval()
        _kmeans_init(network, all_maps, train, rng, log)

    stopper = _Stopper(train.steps, max_minutes)
    t_start = time.perf_counter()
    cache: dict[str, np.ndarray] = {}
    cache_step = -1
    running_loss, running_active = [], []

    def refresh_cache() -> None:
        nonlocal cache, cache_step
        network.eval()
        cache = {c: _describe_maps(network, maps[c], use_bf16) for c in conditions}
        cache_step = step
        network.train()

    def save() -> None:
        if model_cfg.pca_dim:
            network.eval()
            network.fit_pca(_describe_maps(network, all_maps, use_bf16))
        elapsed = seconds_before + time.perf_counter() - t_start
        _write_history(run_dir, history)
        save_run(run_dir, {"netvlad": network}, config, optimizers={"netvlad": optimizer},
                 state={"step": step, "seconds": elapsed, "numpy_rng": _rng_state(rng),
                        "torch_rng": torch.get_rng_state()})
        network.train()

    network.train()
    while not stopper.done(step):
        if cache_step < 0 or step - cache_step >= train.cache_refresh:
            refresh_cache()
        q_maps, p_maps, n_maps = [], [], []
        for _ in range(train.batch_size):
            q_cond, d_cond = rng.choice(len(conditions), size=2, replace=False)
            q_cond, d_cond = conditions[q_cond], conditions[d_cond]
            i = int(rng.integers(len(frame_ids)))
            query = cache[q_cond][i]
            # best-matching potential positive (weak supervision: the nearest one in descriptor space)
            pos = positives[i][np.argmin(((cache[d_cond][positives[i]] - query) ** 2).sum(1))]
            pool = negatives[i]
            if len(pool) > train.negatives_sampled:
                pool = rng.choice(pool, size=train.negatives_sampled, replace=False)
            dist = ((cache[d_cond][pool] - query) ** 2).sum(1)
            hardest = pool[np.argsort(dist, kind="stable")[: train.hard_negatives]]
            if len(hardest) < train.hard_negatives:  # fewer negatives than asked: repeat the hardest
                hardest = np.resize(hardest, train.hard_negatives)
            q_maps.append(maps[q_cond][i])
            p_maps.append(maps[d_cond][pos])
            n_maps.extend(maps[d_cond][j] for j in hardest)
        batch = torch.stack(q_maps + p_maps + n_maps)
        vectors = network.vlad_vectors(batch).float()
        b = train.batch_size
        q, p = vectors[:b], vectors[b:2 * b]
        n = vectors[2 * b:].view(b, train.hard_negatives, -1)
        d_pos = ((q - p) ** 2).sum(1, keepdim=True)
        d_neg = ((q[:, None, :] - n) ** 2).sum(2)
        hinge = torch.relu(d_pos - d_neg + train.margin)
        loss = hinge.mean()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"NetVLAD loss became {loss.item()} at step {step}; lower train.lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        step += 1
        running_loss.append(float(loss.item()))
        running_active.append(float((hinge > 0).float().mean().item()))
        if step % train.log_every == 0 or stopper.done(step):
            elapsed = seconds_before + time.perf_counter() - t_start
            history.append({"step": step, "loss": float(np.mean(running_loss)),
                            "active_triplets": float(np.mean(running_active)), "seconds": elapsed})
            log(f"step {step}/{train.steps} loss {np.mean(running_loss):.4f} "
                f"active triplets {np.mean(running_active):.2f} ({elapsed:.0f} s)")
            running_loss, running_active = [], []
        if step % train.checkpoint_every == 0:
            save()
    save()
    network.eval()
    total = seconds_before + time.perf_counter() - t_start
    final = history[-1]["loss"] if history else float("nan")
    log(f"NetVLAD saved to {run_dir} after {step} steps ({total:.0f} s training)")
    return {"steps": step, "loss": final, "seconds": total, "run_dir": str(run_dir)}
