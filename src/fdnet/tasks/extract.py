"""Every method's vectors for a list of images, streamed into one ``.npz`` (``fdnet extract``),
or into hloc's global-features ``.h5`` (``--format h5``, :func:`extract_h5`).

Images are decoded in worker processes while the descriptor runs
(:func:`fdnet.descriptors.pipeline.describe_stream`), and the vectors are written batch by batch
to temporary ``.npy`` parts, packed into the ``.npz`` at the end and renamed over the output
(:class:`fdnet.descriptors.pipeline.NpzChunkWriter`): a folder of any size needs only a few
batches of memory, and a crash never leaves half a file.

Arrays: ``descriptors`` (N, D), what the method compares (``--method``'s vectors); a descriptor
that also describes appearance (``describes_appearance``: FDNet) writes ``content`` (its place
descriptor) and ``appearance`` instead. Always: ``names``, ``sources``, ``timestamps`` (see
:func:`frame_arrays`), ``method`` and ``settings`` (JSON of the descriptor's settings).

hloc's ``.h5`` holds the place descriptor alone (``descriptors``, or FDNet's ``content``) as each
image's ``global_descriptor`` (float32), the image named by its path relative to a root folder
(hloc's ``image_dir``), written group by group as batches come
(:class:`fdnet.descriptors.hloc_formats.GlobalFeaturesWriter`), atomically too.

Under ``torchrun`` (:mod:`fdnet.descriptors.sharding`) every process describes its block of the
images and rank 0 writes the one file from its own vectors and the others' (the same file one
process writes, up to floating-point reduction order); ``settings`` records ``world_size``, the
number of processes that made it (1 for one process).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time

import numpy as np

from fdnet.descriptors.base import check_vectors

logger = logging.getLogger(__name__)


def frame_arrays(paths) -> dict:
    """``sources`` (N,): the video, bag or folder each image came from; ``timestamps`` (N,) seconds
    (a video's from its first frame, a bag's recording time since the epoch; NaN for image files);
    ``sizes`` and ``mtimes_ns`` (N,): the size and modification time of each image's file (a
    frame's video or bag), so ``--method precomputed`` can tell these images from others of the
    same names (:mod:`fdnet.data.identity`)."""
    from fdnet.data.frame_records import frame_records
    from fdnet.data.identity import image_facts

    records = frame_records(paths)
    facts = [image_facts(p) for p in paths]
    return {
        "sources": np.array([r.source for r in records]),
        "timestamps": np.array([np.nan if r.timestamp is None else r.timestamp for r in records], dtype=np.float64),
        "sizes": np.array([-1 if f is None else f[1] for f in facts], dtype=np.int64),
        "mtimes_ns": np.array([-1 if f is None else f[2] for f in facts], dtype=np.int64),
    }


def described_arrays(descriptor):
    """The array names a descriptor's extraction writes, and the function giving them per batch."""
    if descriptor.describes_appearance:
        return ("content", "appearance"), descriptor.describe_both
    return ("descriptors",), lambda images: (descriptor.describe(images),)


def _fit_if_needed(descriptor, paths) -> str | None:
    """Let a descriptor that learns from images and was given none learn from ``paths``; what it
    learnt from (for the summary), or None."""
    if not descriptor.needs_fit:
        return None
    logger.info(f"{descriptor.name}: learning from the {len(paths)} images being described (none supplied)")
    descriptor.fit(paths)
    return f"the {len(paths)} extracted images"


def _settings(descriptor, world_size: int) -> str:
    """The descriptor's settings as JSON, with the number of processes that described the images."""
    return json.dumps({**descriptor.settings(), "world_size": int(world_size)}, default=str, sort_keys=True)


def _seconds(shards, timing: dict, started: float) -> float:
    """The describing's wall time: the stream's own for one process; under torchrun, until rank 0
    held every process's vectors."""
    if shards.enabled:
        return time.perf_counter() - started
    return timing.get("seconds_wall", time.perf_counter() - started)


def _checked(descriptor, paths, start: int, array) -> np.ndarray:
    """A batch of vectors as written: NaN or infinity (a damaged checkpoint's weights) is refused
    naming the first image, never written for a later command to stumble on."""
    settings = descriptor.settings()
    made_by = settings.get("checkpoint") or settings.get("weights")
    source = f"{descriptor.name} vectors" + (f" of {made_by}" if made_by else "")
    return check_vectors(array, source, lambda i: f"{paths[start + i]}", directions=False)


def _summary(paths, arrays, descriptor, seconds: float, fitted) -> dict:
    return {
        "images": len(paths),
        "arrays": arrays,
        "dim": descriptor.dim,
        "seconds": seconds,
        "images_per_second": len(paths) / max(seconds, 1e-9),
        "fitted_on": fitted,
    }


def extract(descriptor, paths, out, batch_size: int = 64, workers: int | None = None, progress: bool = True) -> dict:
    """Describe ``paths`` with ``descriptor`` into the ``.npz`` file ``out`` (written atomically).

    A descriptor that learns from images and was given none (``needs_fit``: dbow without a
    vocabulary, trunk-whitened without ``fit``) learns from ``paths`` first, and its settings say
    so. Under torchrun (:func:`fdnet.descriptors.sharding.launch`) each process describes its
    block and rank 0 writes ``out``; a method that learns does so on rank 0, which shares the
    result. Returns a summary: images, arrays, dim, seconds, images_per_second, fitted_on (in
    every process; seconds from the start of describing until rank 0 holds every vector)."""
    from fdnet.descriptors.pipeline import DescribeJob, NpzChunkWriter, PipelineSettings
    from fdnet.descriptors.sharding import BlockOutput, current, describe_blocks, share_fitted

    shards = current()
    paths = list(paths)
    fitted = share_fitted(shards, descriptor, paths, _fit_if_needed)
    names, describe = described_arrays(descriptor)
    shape = (len(paths), descriptor.dim)
    timing: dict = {}
    started = time.perf_counter()
    writer = shards.collectively(
        lambda: NpzChunkWriter(out, {name: (shape, np.float32) for name in names}) if shards.is_main else None
    )

    def write(start, arrays):
        for name, array in zip(names, arrays):
            writer.write(name, _checked(descriptor, paths, start, array))

    with writer if writer is not None else contextlib.nullcontext():
        describe_blocks(
            shards,
            descriptor,
            paths,
            BlockOutput([descriptor.dim] * len(names), write),
            PipelineSettings(batch_size, workers, progress),
            DescribeJob(describe, what=f"extract [{descriptor.name}]", reads_pixels=False),
            timing,
        )
        if writer is not None:
            writer.close(
                {
                    "names": np.array([p.name for p in paths]),
                    **frame_arrays(paths),
                    "method": np.array(descriptor.name),
                    "fingerprint": np.array(descriptor.fingerprint()),
                    "settings": np.array(_settings(descriptor, shards.world_size)),
                }
            )
    seconds = _seconds(shards, timing, started)
    return _summary(paths, names, descriptor, seconds, fitted)


def extract_h5(
    descriptor, paths, out, root, batch_size: int = 64, workers: int | None = None, progress: bool = True
) -> dict:
    """Describe ``paths`` into hloc's global-features file ``out`` (written atomically): each
    image's place descriptor (what :func:`described_arrays` calls ``descriptors``, FDNet's
    ``content``) as the ``global_descriptor`` of the group named by its path relative to
    ``root`` (:func:`fdnet.descriptors.hloc_formats.relative_names`; hloc's ``image_dir``).
    The names are checked before any image is described. Under torchrun, as :func:`extract`.
    Returns the summary of :func:`extract`, with ``array`` (what was written) and ``root``."""
    from fdnet.data.identity import image_facts
    from fdnet.descriptors.hloc_formats import GlobalFeaturesWriter, check_image_name, relative_names
    from fdnet.descriptors.pipeline import DescribeJob, PipelineSettings
    from fdnet.descriptors.sharding import BlockOutput, current, describe_blocks, share_fitted

    shards = current()
    paths = list(paths)
    names = [check_image_name(n, out) for n in relative_names(paths, root)]
    fitted = share_fitted(shards, descriptor, paths, _fit_if_needed)
    array = described_arrays(descriptor)[0][0]  # "content" for FDNet, else "descriptors"
    timing: dict = {}
    started = time.perf_counter()
    # "root": the folder the names are relative to (hloc ignores it; --method precomputed reads the
    # names below it, so day/0001.png's vector never serves dusk/0001.png)
    attrs = {
        "method": descriptor.name,
        "fingerprint": descriptor.fingerprint(),
        "array": array,
        "settings": _settings(descriptor, shards.world_size),
        "root": os.path.abspath(os.fspath(root)),
    }
    writer = shards.collectively(lambda: GlobalFeaturesWriter(out, attrs=attrs) if shards.is_main else None)

    def write(start, arrays):
        end = start + len(arrays[0])
        writer.write(
            names[start:end],
            _checked(descriptor, paths, start, arrays[0]),
            facts=[None if f is None else f[1:] for f in map(image_facts, paths[start:end])],
        )

    with writer if writer is not None else contextlib.nullcontext():
        describe_blocks(
            shards,
            descriptor,
            paths,
            BlockOutput([descriptor.dim], write),
            PipelineSettings(batch_size, workers, progress),
            DescribeJob(what=f"extract [{descriptor.name}]"),
            timing,
        )
        if writer is not None and writer.count != len(paths):
            raise RuntimeError(f"{out}: {writer.count} vectors for {len(paths)} images")
    seconds = _seconds(shards, timing, started)
    return {**_summary(paths, ("global_descriptor",), descriptor, seconds, fitted), "array": array, "root": str(root)}
