"""Settings replaced on the command line of the benchmark scripts (``KEY=VALUE``)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable

from snds.policy import PolicyConfig

__all__ = ["parse_value", "parse_pairs", "split_overrides"]


def parse_value(text: str) -> object:
    """A value as JSON where it parses (``0.1``, ``[64, 64]``, ``true``), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_pairs(pairs: Iterable[str]) -> dict[str, object]:
    """``["KEY=VALUE", ...]`` -> ``{key: value}`` (values by :func:`parse_value`).

    Raises:
        SystemExit: For an item without ``=`` or without a key.
    """
    overrides: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"{pair!r} is not KEY=VALUE")
        overrides[key] = parse_value(value)
    return overrides


def split_overrides(overrides: dict[str, object]) -> tuple[dict[str, object], dict[str, object]]:
    """(the fields of :class:`~snds.policy.PolicyConfig`, the rest: the training's)."""
    policy_fields = {field.name for field in dataclasses.fields(PolicyConfig)}
    policy = {k: v for k, v in overrides.items() if k in policy_fields}
    return policy, {k: v for k, v in overrides.items() if k not in policy_fields}
