"""fdnet: appearance-invariant visual place recognition.

FDNet (Qin et al., "Appearance-invariant place recognition by adversarially learning
disentangled representation") plus the paper's baselines, matching and evaluation.

Quick use::

    import fdnet
    model = fdnet.load("runs/my-run")          # a run directory written by `fdnet train`
    vectors = model.describe(images)           # (N, H, W, C) float32 in [0, 1] -> (N, L)
"""

from fdnet.version import __version__

__all__ = ["load", "__version__"]


def load(run_dir, device: str = "auto"):
    """Load a trained FDNet run directory (or its ``best/``) and return its descriptor
    (``.describe(images)``); ``device`` "auto" takes a GPU when there is one. Built as every
    command builds it (:func:`fdnet.descriptors.create`), so another method's run is refused
    naming the method it records."""
    # Imported lazily so `import fdnet` stays cheap (no torch) for metrics-only users.
    from fdnet.descriptors import create

    return create("fdnet", checkpoint=str(run_dir), device=device)
