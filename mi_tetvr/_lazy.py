"""Names of a package that live in modules needing a Mitsuba variant, looked
up on first use (PEP 562), so that importing the package needs none."""
import importlib


def lazy_exports(package: str, table: dict, names_now: dict):
    """``(__getattr__, __dir__)`` for ``package``: ``table`` maps an exported
    name to its module (relative to the package); ``names_now`` is the
    package's ``globals()``."""
    def __getattr__(name):
        if name in table:
            return getattr(importlib.import_module(f"{package}.{table[name]}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return sorted(set(names_now) | set(table))

    return __getattr__, __dir__
