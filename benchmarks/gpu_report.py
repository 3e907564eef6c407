"""The markdown report of ``benchmarks/gpu_check.sh``: what each step did (exit status,
seconds), the tests by file (passed, failed, skipped) and the benchmarks' headline
figures, from the folder the check wrote (``steps.txt``, ``tests.xml``, the JSON files).

Usage::

    python benchmarks/gpu_report.py out/gpu_check > out/gpu_check/gpu_check.md
"""
from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path


def _json(folder, name):
    path = folder / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def tests_table(path):
    """Markdown rows of the tests by file, from pytest's JUnit XML, and the failures."""
    if not path.is_file():
        return ["(no test results: the tests did not run to the end)"], []
    counts = defaultdict(lambda: [0, 0, 0, 0.0])
    failures = []
    for case in ET.parse(path).getroot().iter("testcase"):
        file = case.get("classname", "").replace(".", "/") + ".py"
        row = counts[file]
        row[3] += float(case.get("time", 0))
        if case.find("failure") is not None or case.find("error") is not None:
            row[1] += 1
            bad = case.find("failure") if case.find("failure") is not None else case.find("error")
            failures.append(f"{file}::{case.get('name')}: {(bad.get('message') or '')[:300]}")
        elif case.find("skipped") is not None:
            row[2] += 1
        else:
            row[0] += 1
    rows = ["| tests | passed | failed | skipped | seconds |", "|---|---|---|---|---|"]
    for file, (p, f, s, t) in sorted(counts.items()):
        rows.append(f"| {file} | {p} | {f} | {s} | {t:.1f} |")
    total = [sum(c[i] for c in counts.values()) for i in range(4)]
    rows.append(f"| **all** | {total[0]} | {total[1]} | {total[2]} | {total[3]:.1f} |")
    return rows, failures


def render_rows(result, label):
    """Rows of one bench_render result: tetvr's times and the plain walk's ratio."""
    r = result["results"]
    mesh, image = r["mesh"], r["image"]
    methods = {m["method"]: m for m in r["methods"]}
    tv = methods.get("tetvr mi.render")
    rays = image["rays"] / tv["median_s"] / 1e6 if tv else float("nan")
    return [f"| {label} | {mesh['tets']:,} tets, {image['res']}² | "
            f"{tv['median_s'] * 1e3:.1f} ms ({rays:.1f} Mrays/s, "
            f"{tv['msteps_per_s']:.0f} M tet steps/s; first run {tv['first_s']:.1f} s) | "
            f"plain walk / tetvr {r['plain_over_tetvr']['same_integral']:.2f}x |"]


def main(folder):
    folder = Path(folder)
    steps = [line.split() for line in (folder / "steps.txt").read_text().splitlines()
             if line.strip()] if (folder / "steps.txt").is_file() else []
    header = next((d["header"] for d in (_json(folder, n) for n in
                                         ("render", "backward", "memory", "render_10m")) if d),
                  {})
    print("# mi_tetvr GPU check\n")
    print(f"- device: {header.get('device', '?')}; variant {header.get('variant', '?')}; "
          f"Mitsuba {header.get('mitsuba')}, Dr.Jit {header.get('drjit')}, "
          f"mi_tetvr {header.get('mi_tetvr')}; {header.get('date', '')}")
    print("- steps: " + ", ".join(f"{n} {'ok' if rc == '0' else f'FAILED ({rc})'} in {s} s"
                                  for n, rc, s in steps))
    print()
    rows, failures = tests_table(folder / "tests.xml")
    print("\n".join(rows))
    if failures:
        print("\nFailures:\n")
        print("\n".join(f"- {f}" for f in failures))
    print("\n| benchmark | size | result | against |\n|---|---|---|---|")
    for name, label in (("render", "render"), ("render_10m", "render, large")):
        d = _json(folder, name)
        if d:
            print("\n".join(render_rows(d, label)))
    d = _json(folder, "backward")
    if d:
        r = d["results"]
        print(f"| render + backward | {r['mesh']['tets']:,} tets, {r['image']['res']}² | "
              f"{r['render_backward_over_primal']:.2f}x the primal render "
              f"(reduce_mode {r['best_reduce_mode']}) | colors, opacities, positions |")
    d = _json(folder, "memory")
    if d:
        r = d["results"]
        cases = {c["case"]: c for c in r["cases"]}
        t, o = cases.get("transparent"), cases.get("opaque")
        print(f"| adjoint memory | {r['mesh']['tets']:,} tets, {r['image']['res']}² | "
              f"transparent - opaque: {r['adjoint_transparent_minus_opaque_mb']:+.1f} MB "
              f"({t['tets_per_ray_mean']:.0f} vs {o['tets_per_ray_mean']:.1f} tets per ray) | "
              f"recorded loop: {r['recorded_transparent_over_opaque']:.1f}x transparent / "
              f"opaque |")
    d = _json(folder, "rays")
    if d:
        r = d["results"]
        ratios = {c["case"]: sorted(c["ratios"])[len(c["ratios"]) // 2] for c in r["cases"]}
        print(f"| render_rays | {r['tets']:,} tets, {r['rays']:,} rays | "
              + ", ".join(f"{k} {v:.2f}x" for k, v in ratios.items())
              + f" mi.render's time; max diff {r['max_diff']:.1e} | mi.render, same rays |")
    return 0 if all(rc == "0" for _, rc, _ in steps) and not failures else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "out/gpu_check"))
