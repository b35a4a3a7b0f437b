"""The package's version, written once: setuptools reads it from here (``pyproject.toml``),
``flyvpr.__version__`` re-exports it, and the modules that record it import it from here."""

__version__ = "0.1.0"
