"""The longest functions of a package folder, by lines of code (the docstring left out)
and in all::

    python benchmarks/function_lengths.py mi_tetvr/recon --top 10
    python benchmarks/checkout_cli.py BASE benchmarks/function_lengths.py BASE/mi_tetvr/recon

Prints one row per function (code lines, all lines, file:name) and how many have more
than ``--limit`` lines of code and in all.
"""
from __future__ import annotations

import argparse
import ast
from pathlib import Path


def lengths(folder):
    """``[(code lines, all lines, "file:function")]`` of every function and method in the
    ``.py`` files of ``folder``, longest first."""
    rows = []
    for path in sorted(Path(folder).glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            body, start = node.body, node.body[0].lineno
            if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                start = body[1].lineno if len(body) > 1 else body[0].end_lineno
            rows.append((node.end_lineno - start + 1, node.end_lineno - node.lineno + 1,
                         f"{path.name}:{node.name}"))
    return sorted(rows, reverse=True)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder")
    p.add_argument("--top", type=int, default=10)
    p.add_argument("--limit", type=int, default=60)
    a = p.parse_args()
    rows = lengths(a.folder)
    print(f"{'code':>5} {'all':>5}  function")
    for code, total, name in rows[:a.top]:
        print(f"{code:5d} {total:5d}  {name}")
    print(f"{len(rows)} functions; above {a.limit} lines: "
          f"{sum(r[0] > a.limit for r in rows)} of code, {sum(r[1] > a.limit for r in rows)} "
          f"in all")


if __name__ == "__main__":
    main()
