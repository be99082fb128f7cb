"""Obstacle specs: ``--obstacle`` and ``--workspace`` strings and their dictionary form."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from snds.errors import ConfigError
from snds.obstacles.shapes import SHAPES, WORKSPACES, Obstacle

__all__ = ["obstacle_from_dict", "parse_obstacle", "parse_workspace"]


#: Spec options: name -> (constructor field, parser). Vectors are separated by "/".
_OPTIONS: dict[str, tuple[str, Callable[[str], Any]]] = {
    "margin": ("margin", float),
    "influence": ("influence", float),
    "angle": ("angles", lambda s: (float(s),)),
    "angles": ("angles", lambda s: tuple(float(p) for p in s.split("/"))),
    "velocity": ("velocity", lambda s: tuple(float(p) for p in s.split("/"))),
}


def _parse(text: str, registry: dict[str, type[Obstacle]], flag: str) -> Obstacle:
    name, colon, body = text.partition(":")
    if name not in registry or not colon:
        raise ConfigError(
            f"{flag} {text!r}: expected SHAPE:NUMBERS with SHAPE one of {', '.join(registry)}"
        )
    numbers: list[float] = []
    options: dict[str, Any] = {}
    for part in body.split(","):
        part = part.strip()
        key, equals, value = part.partition("=")
        if equals and key not in _OPTIONS:
            raise ConfigError(
                f"{flag} {text!r}: unknown option {key!r} (options: {', '.join(_OPTIONS)})"
            )
        if not equals and options:
            raise ConfigError(f"{flag} {text!r}: numbers must come before key=value options")
        try:
            if equals:
                target, convert = _OPTIONS[key]
                options[target] = convert(value)
            else:
                numbers.append(float(part))
        except ValueError:
            raise ConfigError(f"{flag} {text!r}: {part!r} is not a number") from None
    try:
        return registry[name].from_numbers(numbers, **options)
    except ConfigError as error:
        raise ConfigError(f"{flag} {text!r}: {error}") from None


def parse_obstacle(text: str) -> Obstacle:
    """An obstacle from a spec ``SHAPE:NUMBERS[,key=value...]`` (docs/obstacles.md).

    ``sphere:CX,CY[,CZ],R``; ``ellipsoid:CX,CY[,CZ],A1,A2[,A3]`` (semi-axes); ``box:CX,CY[,CZ],
    H1,H2[,H3]`` (half-widths); options ``margin=M``, ``influence=D``, ``angle=DEG`` (2-D),
    ``angles=A/B/C`` (3-D, x-y-z Euler, degrees), ``velocity=V1/V2[/V3]``.

    Raises:
        ConfigError: naming the spec and its problem.
    """
    return _parse(text, SHAPES, "--obstacle")


def parse_workspace(text: str) -> Obstacle:
    """A workspace from ``box:CX,CY[,CZ],H1,H2[,H3][,margin=M,...]``: the box to stay in."""
    return _parse(text, WORKSPACES, "--workspace")


def obstacle_from_dict(entry: Any, registry: dict[str, type[Obstacle]], where: str) -> Obstacle:
    """An obstacle of ``registry`` from a spec string or a :meth:`Obstacle.to_dict` form."""
    if isinstance(entry, str):
        return _parse(entry, registry, where)
    if not isinstance(entry, dict) or entry.get("shape") not in registry:
        raise ConfigError(
            f'{where}: expected a spec string or an object with "shape" one of '
            f"{', '.join(registry)}, got {entry!r}"
        )
    cls = registry[entry["shape"]]
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(entry) - fields - {"shape"})
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {unknown[0]!r} (keys: {', '.join(sorted(fields))})"
        )
    try:
        return cls(**{k: v for k, v in entry.items() if k != "shape"})
    except TypeError as error:
        raise ConfigError(f"{where}: {error}") from None
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None
