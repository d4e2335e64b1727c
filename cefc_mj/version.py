"""The package version, in a module of its own so that low layers (`cefc_mj.provenance`) can read it
without importing the package's public entry points (`cefc_mj/__init__.py` re-exports it)."""

__version__ = "0.1.0"
