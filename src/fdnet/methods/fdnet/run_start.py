"""What an FDNet run starts on and what it keeps when resumed, from its config alone: the starts a
run with a validation pair chooses among (trunk block x synthetic conditions), the choice a
resumed run made when it started, the ablation switches it keeps, and what those switches remove
(log columns, and in words). :mod:`fdnet.methods.fdnet.training` scores the starts."""

from __future__ import annotations

import logging

from fdnet.config import replace_dotted
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import ABLATION_SWITCHES, FDNetRunConfig, synthetic_option, synthetic_option_text
from fdnet.methods.fdnet.model import TRUNK_HEADS

log = logging.getLogger(__name__)


#: log.csv's columns that belong to each ablation switch's part
ABLATED_COLUMNS = {
    "adversarial": ("encoder_adversarial", "structure", "critic", "wasserstein"),
    "appearance_triplet": ("appearance",),
    "reconstruction": ("reconstruction",),
}


def removed_columns(config: FDNetRunConfig) -> set[str]:
    """The loss columns a run with ``config``'s ablation switches never logs."""
    return {column for name in config.ablated() for column in ABLATED_COLUMNS[name]}


def ablation_text(config: FDNetRunConfig) -> str:
    """What the ablation switches remove from this run, in words (empty for the full method)."""
    trunk_head = config.model.content_head in TRUNK_HEADS
    parts = {
        "adversarial": "no critic D_a and no L_e^adv (D_a stays as initialised, the critic stage is skipped"
        + ("; the content head, which only L_e^adv moves, stays at its start)" if trunk_head else ")"),
        "appearance_triplet": "no L_a ("
        + ("E_a learns only through the decoder's L_r)" if config.loss.reconstruction else "E_a is never updated)"),
        "reconstruction": "no L_r (the decoder is never updated"
        + (")" if trunk_head else "; E_c learns from L_e^adv alone)"),
    }
    return "; ".join(f"loss.{name}=false: {parts[name]}" for name in config.ablated())


def start_candidates(config: FDNetRunConfig) -> list[tuple[tuple[str, ...], int]]:
    """The (synthetic conditions, trunk block) starts a run with a validation pair chooses from,
    synthetic settings outer: ``data.synthetic_conditions_candidates`` (or the one
    ``data.synthetic_conditions``) x ``model.backbone_block_candidates`` (or the one block)."""
    options = [synthetic_option(t) for t in config.data.synthetic_conditions_candidates] or [
        tuple(config.data.synthetic_conditions)
    ]
    blocks = [int(b) for b in config.model.backbone_block_candidates] or [int(config.model.backbone_block)]
    return [(option, block) for option in options for block in blocks]


def start_label(config: FDNetRunConfig, option: tuple[str, ...], block: int) -> str:
    """``block_selection``'s key: the block, plus the synthetic setting when that is chosen too."""
    if not config.data.synthetic_conditions_candidates:
        return str(block)
    return f"{block}, synthetic {synthetic_option_text(option)}"


def chosen_when_started(config: FDNetRunConfig, run_dir) -> FDNetRunConfig:
    """``config`` with the trunk block and synthetic conditions the run chose when it started
    (a resumed run does not choose again: its weights are for that choice)."""
    from fdnet import runs

    saved = runs.load_config(run_dir, FDNetRunConfig)
    block, option = saved.model.backbone_block, tuple(saved.data.synthetic_conditions)
    if (option, block) not in start_candidates(config):
        return config
    if block != config.model.backbone_block or option != tuple(config.data.synthetic_conditions):
        log.info(
            f"continuing on trunk block {start_label(config, option, block)}, chosen when the run "
            f"started (its weights are for that choice; model.backbone_block = {config.model.backbone_block} "
            "applies to new runs)"
        )
    return replace_dotted(config, {"model.backbone_block": block, "data.synthetic_conditions": list(option)})


def check_same_ablation(config: FDNetRunConfig, run_dir) -> None:
    """A resumed run keeps the ablation switches it started with (even with ``--override``): a
    switch changes the stages and the losses logged, so the run would be neither variant."""
    from fdnet import runs
    from fdnet.training import distributed

    if not distributed.current().is_main or not runs.is_run(run_dir):
        return  # rank 0 alone reads the run directory; the loop says what is wrong with resuming it
    saved = runs.load_config(run_dir, FDNetRunConfig)
    changed = [
        f"loss.{name}: saved {str(getattr(saved.loss, name)).lower()}, requested "
        f"{str(getattr(config.loss, name)).lower()}"
        for name in ABLATION_SWITCHES
        if getattr(saved.loss, name) != getattr(config.loss, name)
    ]
    if changed:
        raise ConfigError(
            f"{run_dir}: a run keeps the ablation switches it started with ({'; '.join(changed)}); "
            "train the other variant into a new run directory"
        )
