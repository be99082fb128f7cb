"""Exceptions the library raises for bad input.

Every error a user can cause is one of these, so the CLI can print a one-line message and
exit with code 2 instead of a traceback.
"""

from __future__ import annotations


class SNDSError(Exception):
    """Base class of the errors caused by what a user hands the library."""


class DataError(SNDSError, ValueError):
    """Demonstrations that cannot be used: missing, malformed, wrong shapes, non-finite."""


class ModelFileError(SNDSError, ValueError):
    """A model directory or file that is missing, corrupted, or from an unknown version."""


class ConfigError(SNDSError, ValueError):
    """Settings that cannot be used: a count or rate out of range, an unknown choice."""


class CheckpointError(SNDSError, ValueError):
    """A training checkpoint that is corrupted or was made with other settings or data."""
