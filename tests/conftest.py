"""Shared test fixtures.

Tests that need the real data in ``../shared/data`` use the ``shared_data`` fixture (or
``require_shared``), which skips with a clear reason when the folder is absent, so a fresh clone
elsewhere still passes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FDNET_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def require_shared(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with a clear reason if it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not available: {path} is absent (set FDNET_SHARED_DATA to its folder)")
    return path


@pytest.fixture
def shared_data() -> Path:
    return require_shared()


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory):
    """fdnet's caches ($FDNET_CACHE: frame filters, reproduce's vectors) under this test session's
    own folder, never the user's ~/.cache, and never shared between test runs."""
    old = os.environ.get("FDNET_CACHE")
    os.environ["FDNET_CACHE"] = str(tmp_path_factory.mktemp("fdnet-cache"))
    yield
    if old is None:
        os.environ.pop("FDNET_CACHE", None)
    else:
        os.environ["FDNET_CACHE"] = old


@pytest.fixture(autouse=True)
def _few_threads():
    # CI has 2 cores; keep torch (when a test uses it) from oversubscribing them.
    try:
        import torch
    except ImportError:  # pragma: no cover
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(min(2, previous))
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def write_day_night_route(root: Path, places: int) -> Path:
    """``root/route/{day,night}/NNN.png``: ``places`` random 32x64 images, the night copy of each
    darker (x0.6) with a little noise; frame i is the same place in both conditions."""
    from PIL import Image

    rng = np.random.default_rng(0)
    images = rng.random((places, 32, 64, 3))
    for k, condition in enumerate(("day", "night")):
        (root / "route" / condition).mkdir(parents=True)
        for i, place in enumerate(images):
            image = np.clip(place * (1.0 - 0.4 * k) + 0.05 * rng.random(place.shape), 0, 1)
            Image.fromarray((image * 255).astype(np.uint8)).save(root / "route" / condition / f"{i:03d}.png")
    return root / "route"


def write_random_places(folder: Path, n: int, seed: int = 0, brightness: float = 1.0) -> Path:
    """``folder/frame_NNN.png``: n distinct random-texture 24x32 places (the same seed gives the
    same places), scaled by ``brightness``."""
    from PIL import Image

    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        img = rng.integers(0, 256, size=(24, 32, 3)).astype(np.float32) * brightness
        Image.fromarray(np.clip(img, 0, 255).astype(np.uint8)).save(folder / f"frame_{i:03d}.png")
    return folder


def read_csv_rows(path) -> list[dict]:
    import csv

    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write_day_dusk_route(root: Path, rng: np.random.Generator, places: int = 10) -> Path:
    """``root/{day,dusk}/NNN.png``: random-texture 16x16 places, the dusk copy darker and noisier."""
    from PIL import Image

    for cond in ("day", "dusk"):
        (root / cond).mkdir(parents=True, exist_ok=True)
    for i in range(places):
        pattern = rng.random((16, 16))
        dusk = np.clip(0.5 * pattern + 0.03 * rng.standard_normal(pattern.shape), 0, 1)
        Image.fromarray((pattern * 255).astype(np.uint8)).save(root / "day" / f"{i:03d}.png")
        Image.fromarray((dusk * 255).astype(np.uint8)).save(root / "dusk" / f"{i:03d}.png")
    return root


def write_day_night_set(root: Path, n: int = 8, prefix: str = "") -> Path:
    """``root/{day,night}/PREFIXNNN.png``: n random 20x40 grey images per condition, night darker."""
    from PIL import Image

    rng = np.random.default_rng(1)
    for k, name in enumerate(("day", "night")):
        (root / name).mkdir(parents=True)
        for i in range(n):
            Image.fromarray((rng.random((20, 40)) * (255 - 120 * k)).astype(np.uint8)).save(
                root / name / f"{prefix}{i:03d}.png"
            )
    return root


# ------------------------------------------------------------------ full disks and read-only media
# Real file systems where the test can mount one (root, or a container allowing mount), skipped
# with the reason otherwise; file_size_limit makes the kernel refuse writes on any machine.


def _mount(*arguments: str) -> None:
    import subprocess

    try:
        done = subprocess.run(["mount", *arguments], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"cannot mount a test file system here ({exc})")
    if done.returncode != 0:
        pytest.skip(
            f"cannot mount a test file system here (mount {' '.join(arguments)}: "
            f"{done.stderr.strip() or done.returncode})"
        )


def _unmount(folder: Path) -> None:
    import subprocess

    subprocess.run(["umount", "-l", str(folder)], capture_output=True, timeout=30)


class SmallDisk:
    """A real 1 MiB tmpfs mounted at ``path``; :meth:`fill` leaves only ``free`` bytes of it."""

    def __init__(self, path: Path):
        self.path = path

    def fill(self, free: int = 4096) -> Path:
        """Fill the disk but for ``free`` bytes (default one 4 KiB page: a command's check that it
        can write passes, an output of more than a page does not fit: ENOSPC mid-write)."""
        stats = os.statvfs(self.path)
        available = stats.f_bavail * stats.f_frsize
        with open(self.path / ".filler", "ab") as handle:
            handle.write(b"\0" * max(0, available - free))
        return self.path

    def files(self) -> list[str]:
        """Everything on the disk but the filler, as paths relative to it."""
        return sorted(str(p.relative_to(self.path)) for p in self.path.rglob("*") if p.name != ".filler")


@pytest.fixture
def small_disk(tmp_path):
    """A :class:`SmallDisk` at ``tmp_path/disk``; skipped when this machine does not let the test
    mount a file system (needs root or a container that allows mount)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    _mount("-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk))
    try:
        yield SmallDisk(disk)
    finally:
        _unmount(disk)


@pytest.fixture
def make_read_only():
    """``make_read_only(folder)``: bind-mount ``folder`` over itself read-only (EROFS for every
    write, root included). Skipped when this machine does not let the test mount."""
    mounted = []

    def make(folder: Path) -> Path:
        _mount("--bind", str(folder), str(folder))
        mounted.append(folder)
        _mount("-o", "remount,bind,ro", str(folder))
        return folder

    yield make
    for folder in reversed(mounted):
        _unmount(folder)


@pytest.fixture
def file_size_limit():
    """``with file_size_limit(n):`` the kernel refuses (EFBIG) any write that would make a file
    longer than ``n`` bytes, on any POSIX machine and without privileges (RLIMIT_FSIZE, with
    SIGXFSZ ignored so the write fails instead of the process being killed)."""
    import contextlib
    import signal

    resource = pytest.importorskip("resource", reason="RLIMIT_FSIZE needs a POSIX system")

    @contextlib.contextmanager
    def limit(size: int):
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, hard))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            signal.signal(signal.SIGXFSZ, handler)

    return limit


# ---------------------------------------------------------------------------- make test-fast
# `make test-fast` runs `pytest -m "not slow"`: the unit tests (3.3 minutes measured on 2 loaded cores).
# Marked slow here, by path (no test file needs to say it): the modules that train a model or run
# a whole command end to end, and the single tests measured over 2 s on a loaded 2-core machine.
# `make test` runs everything.

#: test modules that train models or run whole pipelines (demo, reproduce, torchrun trainings)
SLOW_MODULES = (
    "tests/training/test_crash_resume.py",
    "tests/training/test_distributed.py",
    "tests/training/test_loop.py",
    "tests/methods/calc/",
    "tests/methods/netvlad/",
    "tests/methods/fdnet/test_ablation.py",
    "tests/methods/fdnet/test_beats_trunk.py",
    "tests/methods/fdnet/test_paper_native.py",
    "tests/methods/fdnet/test_training.py",
    "tests/methods/fdnet/test_trunk_alone.py",
    "tests/cli/test_reproduce.py",
    "tests/cli/test_demo.py",
    "tests/cli/test_train_baselines.py",
    "tests/reproduce/test_ablation.py",
    "tests/data/test_appearance.py",
)
#: single tests measured over 2 s (torchrun groups, benchmarks, kill-at-any-moment loops, real data)
SLOW_TESTS = (
    "tests/cli/test_benchmark.py::test_quick_benchmark_reports_figures_and_ratios",
    "tests/cli/test_benchmark.py::test_sweep_measures_one_built_index_at_several_search_settings",
    "tests/cli/test_benchmark.py::test_scale_on_real_vectors_from_an_extract_file",
    "tests/test_devices.py::test_bf16_is_as_accurate_as_fp32_for_retrieval",
    "tests/test_devices.py::test_compiled_content_pads_short_batches_and_matches_eager",
    "tests/cli/test_calibrate.py::test_one_rule_for_a_calibration_stored_in_the_run",
    "tests/cli/test_calibrate.py::test_calibration_stored_in_an_fdnet_run_directory",
    "tests/cli/test_calibrate.py::test_a_calibration_from_another_model_is_refused",
    "tests/cli/test_database_command.py::test_torchrun_",
    "tests/cli/test_extract.py::test_torchrun_",
    "tests/cli/test_extract.py::test_a_runs_recorded_method_is_used_or_named",
    "tests/descriptors/test_sharding.py::test_torchrun_",
    "tests/descriptors/test_pipeline.py::test_a_folder_streams_in_memory_far_below_its_decoded_size",
    "tests/descriptors/test_pipeline.py::test_decoding_workers_die_with_their_parent_whatever_kills_it",
    "tests/descriptors/test_classic.py::test_real_",
    "tests/descriptors/test_landmarks.py::test_recognises_gardens_point_across_viewpoint",
    "tests/test_runs.py::test_sigkill_during_saves_always_leaves_a_complete_checkpoint",
    "tests/matching/test_database.py::test_a_writer_killed_at_any_moment_leaves_whole_batches",
    "tests/cli/test_common.py::test_fit_folder_and_frames_are_recorded_in_the_output",
    "tests/cli/test_common.py::test_a_database_rebuilds_the_whitening_from_its_fit_folder",
    "tests/test_export.py::test_projection_head_gives_its_length_to_extract_export_and_the_database",
    "tests/test_provenance.py::test_benchmark_json_records_it",
    "tests/data/test_sources.py::test_evaluate_on_videos_matches_evaluate_on_the_frames_as_folders",
    "tests/test_logs.py::test_train_into_a_log_file_writes_lines_not_redraws",
    "tests/methods/fdnet/test_trunk_choice.py::test_choice_is_the_best_candidate_and_trunk_methods_read_it",
    "tests/methods/fdnet/test_trunk.py::test_condition_means_init_removes_the_direction_between_the_conditions",
)


def is_slow(nodeid: str) -> bool:
    """Whether ``make test-fast`` leaves the test ``nodeid`` out (SLOW_MODULES, SLOW_TESTS)."""
    return nodeid.startswith(SLOW_MODULES) or nodeid.split("[")[0].startswith(SLOW_TESTS)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if is_slow(item.nodeid):
            item.add_marker(pytest.mark.slow)
