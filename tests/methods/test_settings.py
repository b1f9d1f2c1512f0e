"""Settings every trained method shares: the validation pair."""

import pytest

from fdnet.errors import ConfigError
from fdnet.methods.settings import ValidationConfig, check_validation_pair


@pytest.mark.parametrize("reference, query, match", [
    ("day", "", "give both a reference and a query"),
    ("", "night", "give both a reference and a query"),
    ("day", "day", r"the same condition \('day'\).*choose two conditions"),
])
def test_a_validation_pair_needs_two_different_conditions(reference, query, match):
    with pytest.raises(ConfigError, match=match):
        check_validation_pair(ValidationConfig(reference=reference, query=query))


def test_two_conditions_or_none_are_a_validation_pair():
    check_validation_pair(ValidationConfig(reference="day", query="night"))
    check_validation_pair(ValidationConfig())
