"""Every exception the library raises on purpose, in one place.

Each is an :class:`SNDSError`, caused by what a user hands the library (a file, a setting, a
request, a model it cannot handle), so the CLI can print a one-line message and exit with
code 2 instead of a traceback, and the page can answer with a 4xx.
"""

from __future__ import annotations

__all__ = [
    "CExportError",
    "CertificateError",
    "CheckpointError",
    "ConfigError",
    "DataError",
    "ExportError",
    "ModelFileError",
    "NotCertifiable",
    "RequestError",
    "SNDSError",
    "SimulationError",
    "TrainingError",
]


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


class TrainingError(SNDSError, RuntimeError):
    """Training diverged even after restarting from its last good state."""


class ExportError(SNDSError):
    """An export that failed, or whose outputs differ from the library's."""


class CExportError(SNDSError):
    """A policy the C export cannot write (a method or a layer it does not have, a bad
    option)."""


class SimulationError(SNDSError):
    """A simulation that cannot run: a missing optional package, a bad robot or setting."""


class NotCertifiable(SNDSError):
    """A policy that this certificate does not cover (the message says why)."""


class CertificateError(SNDSError):
    """A certificate file that is malformed or does not match its model."""


class RequestError(SNDSError):
    """A request the page's server refuses: an HTTP status (4xx) and a one-line reason.

    Arguments:
        status: The HTTP status code.
        reason: What is wrong, in one line.
    """

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = " ".join(reason.split())
