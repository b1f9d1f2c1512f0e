"""Choose the trunk's backbone and block on a validation pair, by the rule FDNet's block is chosen.

The rule (:func:`pick_best`): the highest R@1 on the validation pair; a tie goes to the higher
AUC-PR, a tie in both to the earlier candidate in the list. This is the rule FDNet's training
applies to ``model.backbone_block_candidates`` and to ``best/``, so an FDNet run and the
untrained trunk it is compared with are chosen alike, on validation frames only (never on the
test frames).

Each candidate is ``trunk`` (or, ``whitened``, ``trunk-whitened``) at one backbone and block,
evaluated on the pair exactly as ``fdnet evaluate`` evaluates it. The result can be written as a
YAML file (:func:`write_choice`) that both trunk methods read with their ``choice=FILE`` setting
(``--method-set trunk:choice=FILE``): the chosen backbone and block become their defaults.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Sequence

from fdnet.errors import ConfigError

#: the candidates when none are given: the mid-to-late blocks of each shipped backbone (stride
#: 16 and 32; the earlier stride-8 maps are larger and, measured in docs/trunk.md, weaker)
DEFAULT_CANDIDATES = (
    "efficientnet-lite0:7,efficientnet-lite0:8,efficientnet-lite0:10,efficientnet-lite0:11,efficientnet-lite0:14,"
    "efficientnet-lite1:10,efficientnet-lite1:12,efficientnet-lite1:14,efficientnet-lite1:17,"
    "efficientnet-lite2:10,efficientnet-lite2:12,efficientnet-lite2:14,efficientnet-lite2:17"
)
RULE = "highest validation R@1; ties to the higher AUC-PR, then to the earlier candidate"
CHOICE_FORMAT = "fdnet-trunk-choice-1"


@dataclasses.dataclass(frozen=True)
class Candidate:
    backbone: str
    block: int

    def __str__(self) -> str:
        return f"{self.backbone}:{self.block}"


def parse_candidates(text: str | Sequence[str]) -> list[Candidate]:
    """``"efficientnet-lite0:7,lite2:12"`` (``lite0``..``lite2`` short for the full names) ->
    candidates, checked against each backbone's blocks. ConfigError naming a bad entry."""
    from fdnet.backbones import check_backbone, check_block

    entries = [e.strip() for e in (text.split(",") if isinstance(text, str) else text) if str(e).strip()]
    if not entries:
        raise ConfigError("--candidates: no candidates given (expected BACKBONE:BLOCK,...)")
    out: list[Candidate] = []
    for entry in entries:
        backbone, sep, block = str(entry).rpartition(":")
        if not sep or not backbone or not block.strip().lstrip("-").isdigit():
            raise ConfigError(f"--candidates {entry!r}: expected BACKBONE:BLOCK, e.g. efficientnet-lite2:12")
        backbone = backbone.strip().lower()
        if backbone.startswith("lite"):
            backbone = f"efficientnet-{backbone}"
        backbone = check_backbone(backbone, where=f"--candidates {entry!r}:")
        candidate = Candidate(backbone, check_block(int(block), backbone))
        if candidate not in out:
            out.append(candidate)
    return out


def pick_best(scores: Sequence[dict]) -> int:
    """Index of the best of ``scores`` (dicts with ``recall_at_1`` and ``auc_pr``) by :data:`RULE`.
    Pure; comparisons are exact, as FDNet's (R@1 is a count over the same queries)."""
    if not scores:
        raise ConfigError("no candidates to choose from")
    best = 0
    for index, score in enumerate(scores):
        if (score["recall_at_1"], score["auc_pr"]) > (scores[best]["recall_at_1"], scores[best]["auc_pr"]):
            best = index
    return best


@dataclasses.dataclass
class TrunkChoice:
    method: str
    chosen: Candidate
    scores: list[dict]
    input_size: tuple[int, int]
    validation: str
    options: dict

    def to_dict(self) -> dict:
        return {
            "format": CHOICE_FORMAT,
            "method": self.method,
            "rule": RULE,
            "backbone": self.chosen.backbone,
            "block": self.chosen.block,
            "input_size": [int(s) for s in self.input_size],
            "validation": self.validation,
            "options": self.options,
            "scores": self.scores,
        }


def choose_trunk(
    split,
    candidates: Sequence[Candidate],
    input_size=(128, 256),
    whitened: bool = False,
    options: dict | None = None,
    pipeline=None,
    log: Callable[[str], None] | None = None,
    create: Callable | None = None,
) -> TrunkChoice:
    """Evaluate every candidate on ``split`` (an :class:`~fdnet.data.split.EvaluationSplit`, the
    validation pair) and choose by :data:`RULE`. ``options`` go to every candidate's method
    (``device``, and for ``trunk-whitened`` ``dim``, ``power``, ``fit``, ``fit_frames``: without
    ``fit`` it learns from the split's reference images). ``pipeline``: how images are decoded
    and described (default: batches of 64; every candidate shows a progress bar). ``create``
    builds a method (default :func:`fdnet.descriptors.create`)."""
    from fdnet.descriptors.pipeline import PipelineSettings
    from fdnet.evaluation.experiment import evaluate_method

    if create is None:
        from fdnet.descriptors import create
    say = log or (lambda message: None)
    method = "trunk-whitened" if whitened else "trunk"
    options = {k: v for k, v in dict(options or {}).items() if v is not None}
    for reserved in ("backbone", "block", "input_size", "choice", "checkpoint"):
        if reserved in options:
            raise ConfigError(
                f"choose-trunk: {reserved} is what is being chosen or fixed by the command; "
                "not a method setting here"
            )
    from fdnet.progress import progress_bar

    pipeline = pipeline or PipelineSettings()
    describing = PipelineSettings(pipeline.batch_size, pipeline.workers, progress=True)
    scores = []
    # every candidate describes the whole pair: bars per candidate and over them, with the time left
    bar = progress_bar(total=len(candidates), desc="choosing the trunk", unit="candidate")
    for candidate in candidates:
        descriptor = create(
            method, backbone=candidate.backbone, block=candidate.block, input_size=list(input_size), **options
        )
        result = evaluate_method(descriptor, split, pipeline=describing)
        bar.update(1)
        m = result.to_dict(include_curve=False)
        score = {
            "backbone": candidate.backbone,
            "block": candidate.block,
            "dim": int(descriptor.dim),
            "recall_at_1": float(m["recall_at_n"]["1"]),
            "recall_at_5": float(m["recall_at_n"]["5"]),
            "recall_at_100_precision": float(m["recall_at_100_precision"]),
            "auc_pr": float(m["auc_pr"]),
        }
        if "fitted_on" in result.settings:
            score["fitted_on"] = result.settings["fitted_on"]
        scores.append(score)
        say(
            f"{method} {candidate}: R@1 {score['recall_at_1']:.3f}, AUC-PR {score['auc_pr']:.3f} " f"({score['dim']}-d)"
        )
    bar.close()
    chosen = candidates[pick_best(scores)]
    recorded = {k: (str(v) if isinstance(v, Path) else v) for k, v in options.items() if k not in ("device",)}
    return TrunkChoice(method, chosen, scores, tuple(int(s) for s in input_size), split.description, recorded)


def write_choice(path, choice: TrunkChoice) -> None:
    """The choice as YAML (crash-safe), for the trunk methods' ``choice=FILE`` setting."""
    import yaml

    from fdnet.io import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(choice.to_dict(), sort_keys=False))


def read_choice(path) -> dict:
    """``backbone``, ``block`` and ``input_size`` from a file :func:`write_choice` wrote."""
    from fdnet.config import read_yaml_file

    path = Path(path)
    try:
        data = read_yaml_file(path, "trunk choice file")
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: trunk choice file not found (write one with `fdnet choose-trunk`)") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: not a readable trunk choice file ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != CHOICE_FORMAT:
        raise ConfigError(
            f"{path}: not a trunk choice file from `fdnet choose-trunk` (format {CHOICE_FORMAT} " "missing)"
        )
    try:
        size = data["input_size"]
        chosen = {
            "backbone": str(data["backbone"]),
            "block": int(data["block"]),
            "input_size": (int(size[0]), int(size[1])),
        }
    except (KeyError, TypeError, ValueError, IndexError, OverflowError) as exc:
        raise ConfigError(f"{path}: trunk choice file lacks a valid backbone, block or input_size ({exc})") from exc
    from fdnet.data.images import check_image_size

    check_image_size(chosen["input_size"], f"{path}: input_size")
    return chosen
