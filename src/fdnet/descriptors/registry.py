"""Method name -> descriptor class, imported lazily so light methods never import torch."""

from __future__ import annotations

import importlib
import inspect

from fdnet.errors import ConfigError

# name: (module, class, one-line summary)
_METHODS: dict[str, tuple[str, str, str]] = {
    "raw": ("fdnet.descriptors.classic", "RawThumbnail", "downsampled grey thumbnail, cosine"),
    "sad": ("fdnet.descriptors.classic", "SeqSLAMFrontEnd", "SeqSLAM front end: patch-normalised thumbnail, sum of absolute differences"),
    "hog": ("fdnet.descriptors.classic", "HOGDescriptor", "histogram of oriented gradients (OpenCV, VPR-Bench settings), cosine"),
    "fdnet": ("fdnet.methods.fdnet.descriptor", "FDNetDescriptor", "FDNet content vector (needs --checkpoint RUN_DIR)"),
    "gist": ("fdnet.descriptors.gist", "GistDescriptor", "Gist: Gabor energies on a 4x4 grid (512-d)"),
    "dbow": ("fdnet.descriptors.dbow", "DBoWDescriptor", "ORB bag of words, vocabulary tree, TF-IDF, L1 score"),
    "trunk": ("fdnet.methods.fdnet.trunk_alone", "TrunkDescriptor", "the frozen trunk FDNet reads, alone (the number to beat; --checkpoint takes an FDNet run's block and size)"),
    "trunk-whitened": ("fdnet.methods.fdnet.trunk_alone", "TrunkWhitenedDescriptor", "the trunk's map PCA-whitened to dim=L (default 512), learnt from --fit DIR or the reference images"),
    "conv3": ("fdnet.descriptors.conv3", "Conv3Descriptor", "pretrained CNN mid-level map + Gaussian random projection"),
    "netvlad": ("fdnet.methods.netvlad.descriptor", "NetVLADDescriptor", "NetVLAD on the pretrained backbone (needs --checkpoint)"),
    "calc": ("fdnet.methods.calc.descriptor", "CALCDescriptor", "CALC: auto-encoder reconstructing HOG (needs --checkpoint)"),
    "landmarks": ("fdnet.descriptors.landmarks", "LandmarksDescriptor", "region proposals + CNN features, mutual NN matching"),
    "hybridnet": ("fdnet.descriptors.hybridnet", "HybridNetDescriptor", "HybridNet conv4 (needs converted --weights)"),
}


def available_methods() -> dict[str, str]:
    """Method name -> one-line summary."""
    return {name: summary for name, (_, _, summary) in _METHODS.items()}


def descriptor_class(name: str):
    try:
        module_name, class_name, _ = _METHODS[name]
    except KeyError:
        raise ConfigError(f"unknown method {name!r}; available: {', '.join(_METHODS)}") from None
    module = importlib.import_module(module_name)
    return getattr(module, class_name)


def takes_device(name: str) -> bool:
    """Whether method ``name`` runs on a torch device (has a ``device`` setting)."""
    return "device" in inspect.signature(descriptor_class(name).__init__).parameters


def create(name: str, **options):
    """Build descriptor ``name``; ``options`` are its constructor's keyword settings
    (e.g. ``checkpoint=``, ``weights=``, ``vocabulary=``, ``dim=``, ``device=``). ``None`` values
    are dropped so command-line defaults do not override a method's own.

    ``device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``) goes to the methods that run on torch
    (fdnet, conv3, trunk, netvlad, calc, hybridnet); the others (numpy/OpenCV: raw, sad, hog,
    gist, dbow, landmarks) run on the CPU whatever it says, so ``--method fdnet,sad --device
    cuda`` works. It is checked for every method, so a malformed one is always an error."""
    cls = descriptor_class(name)
    options = {k: v for k, v in options.items() if v is not None}
    params = inspect.signature(cls.__init__).parameters
    if "device" in options and "device" not in params:
        from fdnet.backbones import check_device_spec

        check_device_spec(options.pop("device"), where=f"{name}: device")
    accepts_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    if not accepts_any:
        valid = [p for p in params if p != "self"]
        unknown = sorted(set(options) - set(valid))
        if unknown:
            raise ConfigError(
                f"method {name!r} has no setting(s) {', '.join(unknown)}; its settings: {', '.join(valid) or 'none'}"
            )
    return cls(**options)
