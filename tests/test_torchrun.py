"""fdnet.torchrun: what a training's and a map description's torchrun processes share."""

from __future__ import annotations

import pytest

from fdnet.errors import ConfigError
from fdnet.torchrun import environment_int, require_rendezvous


def test_environment_integers_are_read_defaulted_or_refused_with_how_to_start():
    assert environment_int({"RANK": "3"}, "RANK") == 3
    assert environment_int({}, "LOCAL_RANK", 0) == 0
    with pytest.raises(ConfigError, match="RANK is not: start distributed training with torchrun"):
        environment_int({}, "RANK", start="start distributed training")
    with pytest.raises(ConfigError, match=r"RANK='x' is not an integer"):
        environment_int({"RANK": "x"}, "RANK")


def test_the_rendezvous_address_is_required_and_what_is_missing_is_named():
    require_rendezvous({"MASTER_ADDR": "h", "MASTER_PORT": "1"}, 2)
    with pytest.raises(
        ConfigError,
        match=r"^WORLD_SIZE=2 is set but MASTER_ADDR and MASTER_PORT not: " r"start several processes with torchrun$",
    ):
        require_rendezvous({}, 2)
    with pytest.raises(ConfigError, match=r"but MASTER_PORT not: start distributed training with torchrun$"):
        require_rendezvous({"MASTER_ADDR": "h"}, 4, start="start distributed training")
