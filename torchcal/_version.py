"""The package version, stated once (pyproject.toml reads it; the package and the URDF export show it)."""

__version__ = "0.1.0"
