"""The streaming image pipeline: decode and resize in DataLoader workers while the model runs,
hand out descriptors in chunks, never hold a folder.

For a folder of any size (10^6 images), memory stays bounded by a few batches: worker processes
(``torch.utils.data.DataLoader``) decode and resize images while the descriptor describes the
previous batch, at most ``workers * prefetch`` batches wait in between, and the vectors come out
batch by batch (:func:`describe_stream`) for the caller to write where they go (an ``.npz``
written in chunks by ``fdnet extract``, a spool file that ``fdnet database`` inserts in one
transaction). :func:`fdnet.descriptors.base.describe_paths` collects them into one array for
callers that need all vectors at once (matching, evaluation).

Descriptors that declare ``accepts_uint8`` (the torch ones) get uint8 images: a quarter of the
bytes of float32 in the queues and on the way to the device, converted and normalised there
(:func:`fdnet.backbones.images_to_device`). Others get float32 in [0, 1], as always. For a CUDA
device the batches are put in pinned memory so the copy overlaps.

Errors: an image that cannot be read stops the stream with the :class:`~fdnet.errors.DataError`
naming it, raised in the main process (not a worker's traceback).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from fdnet.errors import ConfigError, DataError

try:
    import fcntl
except ImportError:  # Windows: stale spools are not swept (see remove_stale_spools)
    fcntl = None

log = logging.getLogger(__name__)

#: batches each worker prepares ahead of the model (DataLoader's prefetch_factor)
PREFETCH = 2


def default_workers() -> int:
    """Decoding processes when the caller does not say: one per spare core, at least 1, at most 8
    (a 2-core machine: 1 worker decodes while torch runs on the cores)."""
    return max(1, min(8, (os.cpu_count() or 2) - 1))


@dataclass(frozen=True)
class PipelineSettings:
    """How images are decoded and described, passed whole: ``batch_size`` images per forward
    pass, ``workers`` decoding processes (None: :func:`default_workers`; 0: in the calling
    process), ``progress``: a progress bar on standard error."""

    batch_size: int = 64
    workers: int | None = None
    progress: bool = False

    def __post_init__(self):
        for flag, value in (("--batch-size", self.batch_size), ("--workers", self.workers)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))):
                raise ConfigError(f"{flag} must be a whole number, got {value!r}")
        check_pipeline_settings(self.batch_size, self.workers)  # the one range check, naming the flags


def check_pipeline_settings(batch_size: int | None = 64, workers: int | None = None) -> None:
    """Refuse a batch size under 1 and a negative worker count (None: the default), naming the
    command-line flags that set them."""
    from fdnet.errors import ConfigError

    if batch_size is not None and batch_size < 1:
        raise ConfigError(f"--batch-size must be >= 1, got {batch_size}")
    if workers is not None and workers < 0:
        raise ConfigError(f"--workers must be >= 0, got {workers}")


class _Images:
    """Dataset of image paths -> (index, image or None, error message or None). Errors travel as
    values so the main process raises the DataError itself, with its one-line message."""

    def __init__(self, paths: Sequence[Path], size: tuple[int, int], uint8: bool):
        self.paths = list(paths)
        self.size = (int(size[0]), int(size[1]))
        self.uint8 = bool(uint8)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int):
        from fdnet.data.images import load_image, load_image_uint8

        try:
            image = (load_image_uint8 if self.uint8 else load_image)(self.paths[i], self.size)
        except DataError as exc:
            return i, None, str(exc)
        return i, image, None


#: prctl's option that sends the calling process a signal when its parent dies (linux/prctl.h)
PR_SET_PDEATHSIG = 1
#: seconds between a worker's checks that its parent lives, where prctl is not there
PARENT_CHECK_S = 1.0


def die_with_parent(parent: int) -> None:
    """Make this (worker) process end when process ``parent`` does, whatever ends it (kill -9
    included): on Linux the kernel sends it SIGKILL (``prctl(PR_SET_PDEATHSIG)``); elsewhere a
    daemon thread checks every :data:`PARENT_CHECK_S` seconds that its parent is still
    ``parent``. A parent already gone ends it at once. Without this a worker blocked writing a
    batch nobody reads outlived a killed command for good."""
    import signal
    import sys

    armed = False
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    if not armed:
        import threading

        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(PARENT_CHECK_S)
            os._exit(1)

        threading.Thread(target=watch, name="fdnet-parent-watch", daemon=True).start()


class _DieWithParent:
    """DataLoader's ``worker_init_fn`` (picklable, for any start method): :func:`die_with_parent`
    of the process that made the loader."""

    def __init__(self) -> None:
        self.parent = os.getpid()

    def __call__(self, worker_id: int) -> None:
        die_with_parent(self.parent)


def _collate(items, as_tensor: bool = True):
    for _, image, error in items:
        if error is not None:
            return items[0][0], None, error
    batch = np.stack([image for _, image, _ in items])
    if not as_tensor:
        return items[0][0], batch, None
    import torch

    return items[0][0], torch.from_numpy(batch), None


def _collate_arrays(items):
    """A worker's batch as a numpy array: it reaches the main process pickled through the pipe,
    not as a torch tensor in shared memory (/dev/shm), whose failure (a small /dev/shm, a file
    size limit) left the worker's error unseen and the main process waiting forever."""
    return _collate(items, as_tensor=False)


def iter_image_batches(
    paths: Sequence[str | os.PathLike],
    size: tuple[int, int],
    batch_size: int = 64,
    uint8: bool = False,
    workers: int | None = None,
    pin_memory: bool = False,
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(start, images)`` for consecutive batches of ``paths`` in order: images (n, H, W, 3)
    at ``size`` (height, width), uint8 or float32 in [0, 1]. ``workers``: decoding processes
    (None = :func:`default_workers`; 0 = decode in this process, no overlap). At most
    ``workers * PREFETCH`` decoded batches exist besides the one yielded."""
    from fdnet.data.images import check_image_size

    paths = [Path(p) for p in paths]
    size = check_image_size(size, "images")
    if batch_size < 1:
        raise DataError(f"batch size must be at least 1, got {batch_size}")
    if not paths:
        return
    workers = default_workers() if workers is None else max(0, int(workers))
    if len(paths) <= batch_size:
        workers = 0  # one batch: a worker process would only add its start-up time
    import multiprocessing

    if multiprocessing.current_process().daemon:
        workers = 0  # a daemonic process may not start worker processes
    if workers == 0:
        dataset = _Images(paths, size, uint8)
        for start in range(0, len(paths), batch_size):
            _, batch, error = _collate(
                [dataset[i] for i in range(start, min(start + batch_size, len(paths)))], as_tensor=False
            )
            if error is not None:
                raise DataError(error)
            yield start, batch
        return
    from torch.utils.data import DataLoader

    # pinned memory (a GPU) needs tensors; otherwise batches travel as arrays (see _collate_arrays)
    loader = DataLoader(
        _Images(paths, size, uint8),
        batch_size=batch_size,
        shuffle=False,
        num_workers=workers,
        collate_fn=_collate if pin_memory else _collate_arrays,
        prefetch_factor=PREFETCH,
        pin_memory=pin_memory,
        persistent_workers=False,
        worker_init_fn=_DieWithParent(),
    )
    iterator = iter(loader)
    try:
        while True:
            try:
                start, batch, error = next(iterator)
            except StopIteration:
                break
            except RuntimeError as exc:  # a worker killed (out of memory, a signal): one line, not a hang
                if "DataLoader worker" not in str(exc):
                    raise
                raise DataError(
                    f"an image-decoding worker process failed ({' '.join(str(exc).split())}); "
                    "with little memory, give --workers 0 to decode in this process"
                ) from exc
            if error is not None:
                raise DataError(error)
            # .numpy() shares the (possibly pinned) memory: no copy
            yield int(start), batch.numpy() if hasattr(batch, "numpy") else batch
    finally:
        # Stop the worker processes now (an error, or a consumer that stops early), not at exit.
        shutdown = getattr(iterator, "_shutdown_workers", None)
        if shutdown is not None:
            shutdown()


@dataclass(frozen=True)
class DescribeJob:
    """What is done with each batch of images: ``describe(images)`` instead of the descriptor's
    own ``describe`` (e.g. content and appearance vectors at once); ``what``: the progress bar's
    label; ``reads_pixels``: whether that ``describe`` reads the pixels (None: it does when there
    is one; a descriptor ``keyed_by_image`` alone decodes no image)."""

    describe: Callable[[np.ndarray], object] | None = None
    what: str | None = None
    reads_pixels: bool | None = None


def describe_stream(
    descriptor,
    paths: Sequence[str | os.PathLike],
    pipeline: PipelineSettings | None = None,
    job: DescribeJob | None = None,
    timing: dict | None = None,
) -> Iterator[tuple[int, object]]:
    """Yield ``(start, vectors)`` per batch of ``paths``: ``descriptor.describe`` of the images
    (or ``job.describe(images)``), in order, decoded and described as ``pipeline`` says (default:
    batches of 64, no progress bar).

    A descriptor ``keyed_by_image`` (vectors computed elsewhere,
    :class:`fdnet.descriptors.precomputed.PrecomputedDescriptor`) is told each batch's paths
    while it describes; when nothing else reads the pixels (:class:`DescribeJob`) no image is
    decoded at all.

    The progress bar counts images with images/s (:mod:`fdnet.progress`). ``timing`` (a dict)
    receives ``seconds_describe`` (model time only: decoding overlaps with it in the workers and
    is excluded), ``seconds_wall`` and ``num_images``.
    """
    pipeline = pipeline or PipelineSettings()
    job = job or DescribeJob()
    batch_size, workers, progress = pipeline.batch_size, pipeline.workers, pipeline.progress
    describe, what, reads_pixels = job.describe, job.what, job.reads_pixels
    paths = list(paths)
    keyed = descriptor.keyed_by_image
    if reads_pixels is None:
        reads_pixels = describe is not None
    describe = describe or descriptor.describe
    pin = getattr(descriptor.device, "type", None) == "cuda"
    uint8 = descriptor.accepts_uint8
    bar = None
    if progress:
        from fdnet.progress import progress_bar

        bar = progress_bar(
            total=len(paths), desc=what or f"describe [{descriptor.name}]", unit="img", leave=False, smoothing=0.1
        )
    if keyed and not reads_pixels:
        batches = (
            (start, np.empty((len(paths[start : start + batch_size]), 0, 0, 3), np.float32))
            for start in range(0, len(paths), batch_size)
        )
    else:
        batches = iter_image_batches(
            paths, descriptor.input_size, batch_size, uint8=uint8, workers=workers, pin_memory=pin
        )
    spent = 0.0
    t_start = time.perf_counter()
    try:
        for start, images in batches:
            t0 = time.perf_counter()
            with descriptor.images_of(paths[start : start + len(images)]):
                out = describe(images)
            spent += time.perf_counter() - t0
            if bar is not None:
                bar.update(len(images))
            yield start, out
    finally:
        if bar is not None:
            bar.close()
        if timing is not None:
            timing["seconds_describe"] = spent
            timing["seconds_wall"] = time.perf_counter() - t_start
            timing["num_images"] = len(paths)


class NpzChunkWriter:
    """An ``.npz`` written chunk by chunk, never whole in memory, and atomically.

    Each large array has a shape known in advance (e.g. (N, L) vectors for N images); its rows
    are appended in order (:meth:`write`) to a plain ``.npy`` file in a temporary folder beside
    the target. :meth:`close` checks every array is complete, packs the ``.npy`` files
    (uncompressed, ZIP64, so any size) plus small extra arrays into a temporary ``.npz`` beside
    the target, syncs it and renames it over the target (:func:`fdnet.io.atomic_path`). A crash
    or an error leaves the target as it was and no temporary folder; after kill -9 a hidden
    ``.NAME.parts.*`` folder stays beside it until the next writer of the same target removes it
    (its writer holds a lock on it while alive, as :class:`VectorSpool` does). The result is an
    ordinary ``.npz``: ``np.load(path)`` reads it without pickle.
    """

    def __init__(self, path, arrays: dict[str, tuple[tuple[int, ...], object]]):
        import tempfile

        from numpy.lib import format as npy_format

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._folder = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.parts.", dir=self.path.parent))
        self._lock = None
        self._files: dict = {}
        self._rows: dict[str, int] = {}
        self._shapes: dict[str, tuple[int, ...]] = {}
        self._dtypes: dict = {}
        try:
            self._lock = lock_folder(self._folder)
            remove_stale_parts(self.path)
            for name, (shape, dtype) in arrays.items():
                dtype = np.dtype(dtype)
                shape = tuple(int(v) for v in shape)
                handle = open(self._folder / f"{name}.npy", "wb")
                self._files[name] = handle
                header = {"descr": npy_format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
                npy_format.write_array_header_2_0(handle, header)
                self._rows[name], self._shapes[name], self._dtypes[name] = 0, shape, dtype
        except BaseException:
            self.discard()
            raise

    def write(self, name: str, rows: np.ndarray) -> None:
        """Append ``rows`` (the next rows of array ``name``, in order)."""
        rows = np.ascontiguousarray(rows, dtype=self._dtypes[name])
        shape = self._shapes[name]
        if rows.shape[1:] != shape[1:]:
            raise ValueError(f"{name}: rows of shape {rows.shape[1:]}, expected {shape[1:]}")
        if self._rows[name] + len(rows) > shape[0]:
            raise ValueError(f"{name}: more than the {shape[0]} rows announced")
        self._files[name].write(rows.tobytes())
        self._rows[name] += len(rows)

    def close(self, extra: dict[str, np.ndarray] | None = None) -> None:
        """Pack everything into the target, atomically (see the class docstring)."""
        import io
        import zipfile

        from fdnet.io import atomic_path

        try:
            for name, handle in self._files.items():
                handle.close()
                if self._rows[name] != self._shapes[name][0]:
                    raise ValueError(f"{name}: {self._rows[name]} rows written of {self._shapes[name][0]}")
            with atomic_path(self.path) as tmp:
                with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
                    for name in self._files:
                        archive.write(self._folder / f"{name}.npy", arcname=f"{name}.npy")
                    for name, value in (extra or {}).items():
                        buffer = io.BytesIO()
                        np.save(buffer, np.asarray(value), allow_pickle=False)
                        archive.writestr(f"{name}.npy", buffer.getvalue())
        finally:
            self.discard()

    def discard(self) -> None:
        """Drop the temporary parts (the target is untouched)."""
        import shutil

        for handle in self._files.values():
            if not handle.closed:
                handle.close()
        shutil.rmtree(self._folder, ignore_errors=True)
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def __enter__(self) -> "NpzChunkWriter":
        return self

    def __exit__(self, exc_type, *rest) -> None:
        if exc_type is not None:
            self.discard()


SPOOL_PREFIX, SPOOL_SUFFIX = ".fdnet-spool.", ".f32"


class VectorSpool:
    """Vectors written to a temporary file as they are made, read back in chunks: a place
    database stores a folder of any size in one transaction without holding its vectors, and
    without holding its write lock while images are described. The file lives in ``folder``
    (hidden, removed by :meth:`close` or when the ``with`` block ends).

    A process killed with -9 cannot remove its spool: each spool is locked (``flock``) by the
    process writing it, which the kernel releases when that process ends, and every new spool
    first removes the spools in its folder that no live process holds
    (:func:`remove_stale_spools`), so they never pile up beside a database."""

    def __init__(self, folder, dim: int):
        import tempfile

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale_spools(folder)
        fd, name = tempfile.mkstemp(prefix=SPOOL_PREFIX, suffix=SPOOL_SUFFIX, dir=folder)
        if fcntl is not None:
            # A sweeping writer may hold it for a moment (and even unlink it: this process then
            # writes to its open file all the same and finds nothing to unlink at close).
            fcntl.flock(fd, fcntl.LOCK_EX)
        self.path = Path(name)
        self._handle = os.fdopen(fd, "w+b")
        self.dim = int(dim)
        self.rows = 0

    def write(self, rows: np.ndarray) -> None:
        rows = np.ascontiguousarray(rows, dtype="<f4")
        if rows.ndim != 2 or rows.shape[1] != self.dim:
            raise ValueError(f"spool holds {self.dim}-d vectors, got {rows.shape}")
        try:
            self._handle.write(rows.tobytes())
        except OSError as exc:  # a full disk: say which file (a write() error names none)
            raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
        self.rows += len(rows)

    def chunks(self, rows_per_chunk: int = 65536) -> Iterator[tuple[int, np.ndarray]]:
        """``(start, rows)`` in the order written."""
        self._handle.flush()
        self._handle.seek(0)
        width = 4 * self.dim
        for start in range(0, self.rows, rows_per_chunk):
            n = min(rows_per_chunk, self.rows - start)
            data = self._handle.read(n * width)
            if len(data) != n * width:
                raise DataError(f"{self.path}: spool file truncated (disk full?)")
            yield start, np.frombuffer(data, dtype="<f4").reshape(n, self.dim).astype(np.float32)

    def close(self) -> None:
        try:
            self.path.unlink()  # while still locked: no other process takes it for stale
        except FileNotFoundError:
            pass
        if not self._handle.closed:
            self._handle.close()

    def __enter__(self) -> "VectorSpool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_PARTS_LOCK = ".lock"


def lock_folder(folder: Path) -> int | None:
    """Hold a lock on ``folder`` for as long as this process lives (or until the returned
    descriptor is closed): ``folder/.lock``, created under another name and renamed once locked,
    so a sweeping writer never finds it unlocked while its owner is alive."""
    if fcntl is None:
        return None
    staging = folder / f"{_PARTS_LOCK}.new"
    fd = os.open(staging, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.replace(staging, folder / _PARTS_LOCK)
    return fd


def remove_stale_parts(target: Path) -> None:
    """Remove the ``.NAME.parts.*`` folders beside ``target`` whose writer has died (kill -9):
    those whose lock no live process holds. A folder without its lock file is left alone (being
    set up right now, or written by an older fdnet)."""
    import shutil

    if fcntl is None:
        return
    for folder in target.parent.glob(f".{target.name}.parts.*"):
        try:
            fd = os.open(folder / _PARTS_LOCK, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # its writer is alive
            os.close(fd)
            continue
        try:
            shutil.rmtree(folder, ignore_errors=True)
            log.info("removed %s, left by a killed writer of %s", folder, target)
        finally:
            os.close(fd)


def remove_stale_spools(folder) -> list[Path]:
    """Remove the spool files in ``folder`` whose writer has died (kill -9, a power cut): the
    ones no process holds a lock on. Returns what was removed. Without ``fcntl`` (Windows)
    nothing is removed, since a live writer could not be told from a dead one."""
    removed = []
    if fcntl is None:
        return removed
    for path in Path(folder).glob(f"{SPOOL_PREFIX}*{SPOOL_SUFFIX}"):
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        except OSError:  # gone already (its writer finished), or not ours to open
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # held: a writer is still describing into it
            os.close(fd)
            continue
        try:
            # Locked by us now, so no writer holds it; it may have been unlinked (and a new file
            # made under the same name is impossible: mkstemp names are unique) since the glob.
            if os.path.exists(path) and os.stat(path).st_ino == os.fstat(fd).st_ino:
                os.unlink(path)
                removed.append(path)
        except OSError:
            pass
        finally:
            os.close(fd)
    if removed:
        log.info("removed %d stale spool file(s) in %s left by killed writers", len(removed), folder)
    return removed
