"""The version of cascal, in one place (also read by pyproject through the package)."""

__version__ = "0.6.1"
