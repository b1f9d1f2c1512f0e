"""Where a method that learns from images (``dbow``'s vocabulary, ``trunk-whitened``'s PCA) learns.

``fit=DIR`` (the CLI's ``--fit DIR``) is a dataset folder: every condition sub-folder's images
are used, no labels (a plain folder of images is taken as it is). ``fit_frames=START:END``
(``--fit-frames``) keeps the same slice of every condition, so a user can fit on training frames
only. Without ``fit`` such a method learns from the reference images it is matched against, and
its settings say so: ``fitted_on`` names what it learnt from in every output's settings.
"""

from __future__ import annotations

from pathlib import Path

from fdnet.errors import ConfigError, DataError

#: ``fitted_on`` of a method that learnt from the reference images it then matches
REFERENCE_IMAGES = "reference images"


def check_fit_frames(fit_frames, where: str) -> str | None:
    """``fit_frames`` as START:END text (or None). YAML reads ``0:1576`` given as a method setting
    as a base-60 integer, so anything but text is refused with the flag to use instead."""
    from fdnet.data.dataset import parse_frame_range

    if fit_frames is None or fit_frames == "":
        return None
    if not isinstance(fit_frames, str):
        raise ConfigError(
            f"{where}: fit_frames {fit_frames!r} is not START:END text; pass --fit-frames START:END "
            "(or quote it: fit_frames='0:1576')"
        )
    parse_frame_range(fit_frames)
    return fit_frames


def fit_image_paths(folder, fit_frames: str | None = None, where: str = "fit") -> tuple[list[Path], str]:
    """The images under ``folder`` to learn from, and a description for ``fitted_on``.

    Every condition sub-folder of ``folder`` (or ``folder`` itself when it holds the images),
    ``fit_frames`` (START:END) of each. DataError naming the folder when there is nothing to fit on.
    """
    from fdnet.data.dataset import RouteDataset, Traverse, parse_frame_range
    from fdnet.data.images import has_images
    from fdnet.data.sources import is_source

    root = Path(folder)
    if not (root.is_dir() or is_source(root)):
        raise DataError(f"{where} {folder}: folder not found")
    start, end = parse_frame_range(check_fit_frames(fit_frames, where))
    if has_images(root) or is_source(root):  # a video or ROS bag is one condition's images
        traverses = [Traverse.from_folder(root)]
    else:
        try:
            traverses = list(RouteDataset.from_folder(root).traverses.values())
        except DataError as exc:
            raise DataError(
                f"{where} {folder}: no images to fit on (neither images in the folder nor condition "
                "sub-folders with images)"
            ) from exc
    chosen = [t.frames(start, end) for t in traverses]
    paths = [p for t in chosen for p in t.paths]
    frames = f"; frames {fit_frames}" if fit_frames else ""
    if not paths:
        raise DataError(
            f"{where} {folder}{frames}: no images to fit on (the conditions "
            f"{', '.join(t.name for t in traverses)} have {', '.join(str(len(t)) for t in traverses)} "
            "images)"
        )
    names = ", ".join(f"{t.name} ({len(c)})" for t, c in zip(traverses, chosen))
    return paths, f"{root.resolve()}{frames}: {len(paths)} images of {names}"
