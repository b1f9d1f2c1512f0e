"""Every place-recognition method, declared once: one :class:`MethodSpec` line per method.

The line names the method's descriptor (what ``--method NAME`` builds), what it supports (a torch
device, learning from ``--fit`` images, ONNX export, ``fdnet reproduce``'s default list) and, for
a trained method, its run config class, its presets and its trainer. Everything that lists
methods is generated from :data:`_METHODS`: ``--method``'s help and ``fdnet methods``,
``fdnet train``'s method and preset choices, ``fdnet reproduce``'s method list
(:func:`reproduce_methods`), the torch methods named by ``--device``'s help, and the table in
docs/methods.md (:func:`methods_markdown`, checked by a test).

Modules and classes are named as text and imported on use, so listing methods (``fdnet --help``)
never imports torch. Adding a method is its own package plus one line here (docs/methods.md,
"Adding a method").
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from fdnet.errors import ConfigError


@dataclass(frozen=True)
class MethodSpec:
    """One method. ``descriptor``, ``config`` and ``trainer`` are ``"module:attribute"`` text."""

    name: str
    #: one line for ``fdnet methods`` and the docs' table
    summary: str
    #: the :class:`fdnet.descriptors.base.Descriptor` class ``--method NAME`` builds
    descriptor: str
    #: runs on a device (takes ``--device``: a torch device, or onnxruntime's CUDA provider for
    #: ``onnx``); the others run on the CPU whatever it says
    torch: bool = False
    #: learns from images before describing (``--fit DIR``, default the reference images)
    fit: bool = False
    #: ``fdnet export`` writes it as ONNX
    export: bool = False
    #: in ``fdnet reproduce``'s default method list
    reproduce: bool = True
    #: trained methods: the run config dataclass (its module holds ``PRESETS``: name -> factory)
    config: str | None = None
    #: trained methods: ``train(config, run_dir, resume, override, max_minutes, progress, command)``
    trainer: str | None = None
    #: trained methods: preset names (the keys of the config module's ``PRESETS``), and the default
    presets: tuple[str, ...] = ()
    default_preset: str = ""

    @property
    def trained(self) -> bool:
        return self.trainer is not None

    @property
    def package(self) -> str | None:
        """A trained method's package (``fdnet.methods.NAME``), from its config module."""
        return self.config.split(":")[0].rsplit(".", 1)[0] if self.config else None

    @property
    def devices(self) -> str:
        return "cpu, cuda" if self.torch else "cpu"

    def descriptor_class(self):
        return _load(self.descriptor)

    def config_class(self):
        self._need_training("a run config")
        return _load(self.config)

    def config_module(self):
        self._need_training("presets")
        return importlib.import_module(self.config.split(":")[0])

    def preset(self, name: str | None = None):
        """A fresh run config of preset ``name`` (default :attr:`default_preset`)."""
        self._need_training("presets")
        name = name or self.default_preset
        if name not in self.presets:
            raise ConfigError(f"unknown preset {name!r} for {self.name}; available: {', '.join(self.presets)}")
        return self.config_module().PRESETS[name]()

    def train_function(self):
        self._need_training("training")
        return _load(self.trainer)

    def _need_training(self, what: str) -> None:
        if not self.trained:
            raise ConfigError(
                f"{self.name} is not a trained method, so it has no {what}; trained methods: "
                f"{', '.join(trained_methods())}"
            )


def _load(target: str):
    module_name, _, attribute = target.partition(":")
    return getattr(importlib.import_module(module_name), attribute)


_M = MethodSpec
# Order = order in `fdnet methods`, the docs' table and `fdnet reproduce` (FDNet, the trunk alone, then
# the baselines).
_METHODS: dict[str, MethodSpec] = {
    spec.name: spec
    for spec in (
        _M(
            "fdnet",
            "FDNet content vector (needs --checkpoint RUN_DIR)",
            "fdnet.methods.fdnet.descriptor:FDNetDescriptor",
            torch=True,
            export=True,
            config="fdnet.methods.fdnet.config:FDNetRunConfig",
            trainer="fdnet.methods.fdnet.training:train",
            presets=("paper", "paper-native", "cpu", "cpu-scratch", "tiny"),
            default_preset="cpu",
        ),
        _M(
            "trunk",
            "the frozen trunk FDNet reads, alone (the number to beat; --checkpoint takes an FDNet run's block "
            "and size)",
            "fdnet.methods.fdnet.trunk_alone:TrunkDescriptor",
            torch=True,
        ),
        _M(
            "trunk-whitened",
            "the trunk's map PCA-whitened to dim=L (default 512), learnt from --fit DIR or the " "reference images",
            "fdnet.methods.fdnet.trunk_alone:TrunkWhitenedDescriptor",
            torch=True,
            fit=True,
        ),
        _M("raw", "downsampled grey thumbnail, cosine", "fdnet.descriptors.classic:RawThumbnail", reproduce=False),
        _M(
            "sad",
            "SeqSLAM front end: patch-normalised thumbnail, sum of absolute differences",
            "fdnet.descriptors.classic:SeqSLAMFrontEnd",
        ),
        _M(
            "hog",
            "histogram of oriented gradients (OpenCV, VPR-Bench settings), cosine",
            "fdnet.descriptors.classic:HOGDescriptor",
        ),
        _M("gist", "Gist: Gabor energies on a 4x4 grid (512-d)", "fdnet.descriptors.gist:GistDescriptor"),
        _M(
            "dbow",
            "ORB bag of words, vocabulary tree, TF-IDF, L1 score",
            "fdnet.descriptors.dbow:DBoWDescriptor",
            fit=True,
        ),
        _M(
            "conv3",
            "pretrained CNN mid-level map + Gaussian random projection",
            "fdnet.descriptors.conv3:Conv3Descriptor",
            torch=True,
        ),
        _M(
            "landmarks",
            "region proposals + CNN features, mutual NN matching",
            "fdnet.descriptors.landmarks:LandmarksDescriptor",
        ),
        _M(
            "netvlad",
            "NetVLAD on the pretrained backbone (needs --checkpoint)",
            "fdnet.methods.netvlad.descriptor:NetVLADDescriptor",
            torch=True,
            config="fdnet.methods.netvlad.config:NetVLADRunConfig",
            trainer="fdnet.methods.netvlad.training:train",
            presets=("default", "tiny"),
            default_preset="default",
        ),
        _M(
            "calc",
            "CALC: auto-encoder reconstructing HOG (needs --checkpoint)",
            "fdnet.methods.calc.descriptor:CALCDescriptor",
            torch=True,
            config="fdnet.methods.calc.config:CALCRunConfig",
            trainer="fdnet.methods.calc.training:train",
            presets=("default", "small", "tiny"),
            default_preset="default",
        ),
        _M(
            "hybridnet",
            "HybridNet conv4 (needs converted --weights)",
            "fdnet.descriptors.hybridnet:HybridNetDescriptor",
            torch=True,
        ),
        _M(
            "onnx",
            "any ONNX model mapping images (N, 3, H, W) to vectors (N, D), through onnxruntime (needs --weights "
            "MODEL.onnx; preprocessing from --method-set or the model's metadata)",
            "fdnet.descriptors.onnx_model:ONNXDescriptor",
            torch=True,
            reproduce=False,
        ),
        _M(
            "precomputed",
            "vectors computed elsewhere, looked up by image (needs --vectors FILE: fdnet extract's .npz, "
            ".npy + names, hloc's .h5)",
            "fdnet.descriptors.precomputed:PrecomputedDescriptor",
            reproduce=False,
        ),
    )
}


def spec(name: str) -> MethodSpec:
    try:
        return _METHODS[name]
    except KeyError as exc:
        raise ConfigError(f"unknown method {name!r}; available: {', '.join(_METHODS)}") from exc


def all_specs() -> list[MethodSpec]:
    return list(_METHODS.values())


#: what a row label may be made of (``--method LABEL=METHOD``)
LABEL_PATTERN = r"[A-Za-z0-9_.+-]+"


def parse_method_entry(item: str) -> tuple[str, str]:
    """``(label, method)`` of one ``--method`` entry: ``METHOD`` is its own label,
    ``LABEL=METHOD`` names the row (nothing is checked here: :func:`method_entries` does)."""
    label, sep, method = item.strip().partition("=")
    return (label.strip(), method.strip()) if sep else (label.strip(), label.strip())


def method_entries(text: str | None) -> list[tuple[str, str]]:
    """``(label, method)`` of each entry of a comma-separated ``--method`` list: ``METHOD`` (its
    label is its name) or ``LABEL=METHOD``, a name of one's own for a row, so that two models of one
    method compare side by side (``--method a=onnx,b=onnx --weights a:A.onnx --weights b:B.onnx``,
    ``--method old=fdnet,new=fdnet --checkpoint old:RUN1 --checkpoint new:RUN2``). A label is a
    method's key for its options (``--weights LABEL:FILE``, ``--method-set LABEL:KEY=VALUE``).
    Unknown methods, bad labels and a label given twice are refused."""
    import re

    entries, seen = [], set()
    for item in (text or "").split(","):
        item = item.strip()
        if not item:
            continue
        label, method = parse_method_entry(item)
        named = "=" in item
        if not re.fullmatch(LABEL_PATTERN, label):
            raise ConfigError(f"--method {item!r}: a label is letters, digits and _ . + - (LABEL=METHOD)")
        if method not in _METHODS:
            raise ConfigError(f"unknown method {method!r}; available: {', '.join(_METHODS)}")
        if named and label in _METHODS and label != method:
            raise ConfigError(f"--method {item!r}: the label {label!r} is another method's name; choose another")
        if label in seen:
            raise ConfigError(
                f"--method names {label} more than once: its rows would be one method under one name "
                "with one set of options, not told apart; give each its own label "
                "(--method a=onnx,b=onnx --weights a:A.onnx --weights b:B.onnx)"
            )
        seen.add(label)
        entries.append((label, method))
    return entries


def available_methods() -> dict[str, str]:
    """Method name -> one-line summary."""
    return {name: s.summary for name, s in _METHODS.items()}


def trained_methods() -> list[str]:
    """The methods ``fdnet train METHOD`` trains (FDNet first)."""
    return [name for name, s in _METHODS.items() if s.trained]


def torch_methods() -> list[str]:
    """The methods that run on a torch device (``--device`` applies to them)."""
    return [name for name, s in _METHODS.items() if s.torch]


def fitting_methods() -> list[str]:
    """The methods that learn from images before describing (``--fit``)."""
    return [name for name, s in _METHODS.items() if s.fit]


def reproduce_methods() -> tuple[str, ...]:
    """``fdnet reproduce``'s default methods: FDNet, the trunk alone and every baseline."""
    return tuple(name for name, s in _METHODS.items() if s.reproduce)


def descriptor_class(name: str):
    return spec(name).descriptor_class()


def settings_class(name: str):
    """Method ``name``'s settings dataclass (its descriptor's ``Settings``)."""
    return descriptor_class(name).Settings


def setting_names(name: str) -> tuple[str, ...]:
    """The settings method ``name`` takes: its settings dataclass's fields (what ``create`` and
    the command line's method options accept)."""
    return settings_class(name).declared()


def takes_device(name: str) -> bool:
    """Whether method ``name`` has a ``device`` setting (what ``torch=`` declares; a test holds
    the two together)."""
    return "device" in setting_names(name)


def methods_markdown() -> str:
    """The method table of docs/methods.md (a test checks that the file holds this text)."""
    rows = [
        "| method | what it is | trained (`fdnet train METHOD`; presets, default first) | devices | learns from "
        "`--fit` | ONNX export | in `fdnet reproduce` |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in _METHODS.values():
        presets = ", ".join([s.default_preset, *(p for p in s.presets if p != s.default_preset)])
        rows.append(
            f"| `{s.name}` | {s.summary.replace('|', '/')} | {f'yes ({presets})' if s.trained else 'no'} "
            f"| {s.devices} | {'yes' if s.fit else 'no'} | {'yes' if s.export else 'no'} "
            f"| {'yes' if s.reproduce else 'no'} |"
        )
    return "\n".join(rows) + "\n"


def _check_run_method(name: str, checkpoint) -> None:
    """A trained method given another method's run (``--method fdnet --checkpoint CALC_RUN``) is
    refused naming the method the run records, instead of failing on its config's keys: the one
    place every command's descriptor goes through."""
    if not checkpoint or "checkpoint" not in setting_names(name):
        return
    from fdnet.runs import recorded_method

    reads = name if name in trained_methods() else "fdnet"  # trunk, trunk-whitened: an FDNet run's trunk
    recorded = recorded_method(checkpoint)
    if recorded and recorded != reads:
        if reads == name:
            raise ConfigError(
                f"{checkpoint}: a run of `fdnet train {recorded}`, not of {name}: give --method " f"{recorded}"
            )
        raise ConfigError(
            f"{checkpoint}: a run of `fdnet train {recorded}`, but --method {name} takes a run of "
            f"`fdnet train {reads}`: give --method {recorded} for this run, or a {reads} run"
        )


def create(name: str, **options):
    """Build descriptor ``name``; ``options`` are fields of its settings dataclass
    (:func:`setting_names`: e.g. ``checkpoint=``, ``weights=``, ``vocabulary=``, ``dim=``,
    ``device=``). ``None`` values are dropped so command-line defaults do not override a
    method's own.

    ``device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``) goes to the methods that run on torch
    (:func:`torch_methods`); the others (numpy/OpenCV) run on the CPU whatever it says, so
    ``--method fdnet,sad --device cuda`` works. It is checked for every method, so a malformed
    one is always an error."""
    cls = descriptor_class(name)
    options = {k: v for k, v in options.items() if v is not None}
    _check_run_method(name, options.get("checkpoint"))
    valid = setting_names(name)
    if "device" in options and "device" not in valid:
        from fdnet.backbones import check_device_spec

        check_device_spec(options.pop("device"), where=f"{name}: device")
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise ConfigError(
            f"method {name!r} has no setting(s) {', '.join(unknown)}; its settings: {', '.join(valid) or 'none'}"
        )
    return cls(**options)
