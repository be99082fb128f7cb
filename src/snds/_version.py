"""The library's version (as in pyproject.toml), a leaf that model files can record."""

__all__ = ["__version__"]

__version__ = "0.2.0"
