"""Extension points, found through the installed package's metadata (entry points), so that cosim
names none of the packages that extend it.

* ``se3sync.commands``: modules with ``register(subparsers)`` that add sub-commands to `se3sync`;
* ``se3sync.tables``: scenario tables owned by another package, ``NAME = "module:parse"`` with
  ``parse(table: dict, n_agents: int) -> object`` raising `controller.errors.ConfigError` with key
  paths inside the table; the parsed object is ``Scenario.tables[NAME]``. When that object has
  ``check_graph(graph)``, the loader calls it once the graph is parsed (the same ConfigError), so
  a table that refers to agents and edges is checked against them by every command.

Both lists are declared in pyproject.toml. The modules are imported only when used.
"""
from __future__ import annotations

import importlib
from functools import lru_cache

__all__ = ["command_modules", "table_names", "table_parser"]


@lru_cache(maxsize=None)
def _group(name: str) -> dict:
    # imported here: 12 ms that a script loading a scenario without plugin tables never needs
    from importlib.metadata import PackageNotFoundError, distribution, entry_points
    # Our own distribution's entry points only: scanning every installed distribution costs
    # ~70 ms at start-up in a test environment, more than the rest of `se3sync --help`.
    try:
        eps = distribution("se3sync").entry_points
    except PackageNotFoundError:  # pragma: no cover - running from an uninstalled tree
        eps = entry_points()
    return {ep.name: ep.value for ep in eps if ep.group == name}


def command_modules() -> list[str]:
    """Module names providing sub-commands, in the order of their entry-point names."""
    g = _group("se3sync.commands")
    return [g[k] for k in sorted(g)]


def table_names() -> frozenset:
    return frozenset(_group("se3sync.tables"))


def table_parser(name: str):
    """The parse function registered for scenario table ``name``."""
    mod, _, attr = _group("se3sync.tables")[name].partition(":")
    return getattr(importlib.import_module(mod), attr)
