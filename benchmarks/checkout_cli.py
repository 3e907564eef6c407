"""Run the ``mi-tetvr`` command, or a script, with another checkout's code::

    python benchmarks/checkout_cli.py DIR fit DATA --out OUT ...
    python benchmarks/checkout_cli.py DIR DIR/benchmarks/bench_render.py --res 384

``mi_tetvr`` is imported from ``DIR`` (first on ``sys.path``). The benchmarks
that compare two versions (``--code DIR``) run it.

Revisions from before the plugins moved into the package kept them in
``DIR/plugins``, which their ``pyproject.toml`` mapped to ``mi_tetvr.plugins``;
for those alone a finder imports ``mi_tetvr.plugins`` from there (this
checkout's package has its own).
"""
from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path


class _Plugins(importlib.machinery.PathFinder):
    """Finds ``mi_tetvr.plugins`` (and its modules) in ``DIR/plugins`` (older revisions)."""
    root = None

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name == "mi_tetvr.plugins":
            folder = cls.root / "plugins"
            return importlib.util.spec_from_file_location(
                name, folder / "__init__.py", submodule_search_locations=[str(folder)])
        return None


def command(code):
    """The argv prefix that runs the command of the checkout ``code``."""
    return [sys.executable, str(Path(__file__).resolve()), str(Path(code).resolve())]


def main():
    code = Path(sys.argv.pop(1)).resolve()
    sys.path.insert(0, str(code))
    if (code / "plugins" / "__init__.py").is_file():
        _Plugins.root = code
        sys.meta_path.insert(0, _Plugins)
    if sys.argv[1:] and sys.argv[1].endswith(".py"):
        import runpy
        script = Path(sys.argv.pop(1)).resolve()
        sys.argv[0] = str(script)
        sys.path.insert(0, str(script.parent))
        runpy.run_path(str(script), run_name="__main__")
        return 0
    from mi_tetvr.cli import main as cli
    sys.argv[0] = "mi-tetvr"
    return cli()


if __name__ == "__main__":
    sys.exit(main())
