"""Decisions after matching: how confident is each query's best match, and is it accepted?

The stage between matching (:mod:`fdnet.matching`: each query's ranked candidates) and evaluation
or a robot acting on the match. ``acceptance`` turns ranked candidates into one acceptance score
per query under a named rule (``raw``, ``margin``, ``ratio``, gates such as ``floor`` or a
verification registered by another module); ``calibration`` picks the threshold on that score
that reaches a target precision on a validation pair and stores it with the model's fingerprint.
Everything here works on any method's candidates and never looks at a method's name.
"""

from fdnet.decisions.acceptance import (
    AcceptanceSpec,
    Candidates,
    Decision,
    Rule,
    decide,
    get_rule,
    parse_acceptance,
    parse_acceptance_list,
    register_rule,
    rule_names,
)

__all__ = [
    "AcceptanceSpec",
    "Candidates",
    "Decision",
    "Rule",
    "decide",
    "get_rule",
    "parse_acceptance",
    "parse_acceptance_list",
    "register_rule",
    "rule_names",
]
