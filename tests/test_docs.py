"""The README and the documentation site: the README's Python runs as written from
a directory outside the checkout, every block of the site marked runnable runs,
the site builds with warnings as errors, its plugin reference shows every parameter
of the plugins' docstrings, its table of derivatives names tests that exercise each
parameter, and its pages load in a real browser with their pictures.

The site is built once here (``python -m sphinx -W``), or read from
``MI_TETVR_DOCS_HTML`` (a build ``.ci/run`` made). ``MI_TETVR_DOCS_SCREENSHOTS=DIR``
keeps the browser's screenshots of the index and of the ``tetmesh`` reference there
(``docs/images/`` holds the committed ones).
"""
import html
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import ROOT, VARIANT, start_browser

README = ROOT / "README.md"
DOCS = ROOT / "docs"
PLUGINS = ("tetmesh", "tetvr", "tetproj", "tetpath")


def fenced(text, language):
    """The bodies of the ```language fenced blocks of a Markdown text, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", text, re.S | re.M)


def runnable(text):
    """The bodies of the MyST ``{code-block} python`` blocks whose ``:class:`` says
    ``runnable``, in order."""
    found = []
    # (an option line ends at its newline: ``.`` matches newlines here)
    for m in re.finditer(r"^```\{code-block\} python\n((?::[\w-]+:[^\n]*\n)*)\n?(.*?)^```",
                         text, re.S | re.M):
        if re.search(r"^:class:.*\brunnable\b", m.group(1), re.M):
            found.append(m.group(2))
    return found


def run_python(code, cwd):
    """Run code in a fresh interpreter in ``cwd`` on the suite's variant; its output."""
    code = code.replace('mi.set_variant("llvm_ad_rgb")', f'mi.set_variant("{VARIANT}")')
    r = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    return r.stdout


def read_png(path):
    from PIL import Image
    return np.asarray(Image.open(path).convert("RGB"), np.float64) / 255


def test_readme_is_a_first_screen():
    """At most 20,000 bytes, and it names where the rest is."""
    assert README.stat().st_size <= 20_000, README.stat().st_size
    text = README.read_text()
    for page in ("docs/guide/rendering.md", "docs/reference/plugins.md", "docs/limitations.md",
                 "docs/benchmarks/index.md", "docs/architecture.md"):
        assert f"]({page}" in text, page
        assert (ROOT / page).is_file(), page


RECORD = ROOT / "benchmarks" / "README.md"
#: A number as the pages write it (bold or not), and a range of two.
_NUM = r"\**(\d+(?:\.\d+)?)\**"
_RANGE = _NUM + "–" + _NUM
#: The headline quantities the pages quote, each as a pattern that finds its value in any
#: page's wording (its groups: the numbers).
QUANTITIES = {
    "the walk against a plain Dr.Jit walk, 1.57M tets":
        _RANGE + r"×\** (?:the|a) plain Dr\.Jit walk",
    "a render and dr.backward against a render": _RANGE + r"×\** a (?:primal )?render\b",
    "the default fit, 10 min: engine CT / C60 / head MR / Lego":
        r"engine CT / C60 / head MR / Lego[^|\n]*\| " + " / ".join([_NUM] * 4) + " dB",
    "monstree without poses, 10 min": r"`monstree`, 23 photos[^|\n]*\|[^|\n]*?" + _NUM + " dB",
    "against VTK's volume mapper": r"VTK's volume mapper \| " + _RANGE + r"× faster",
    "100.7M tets on 4 Ray workers, a frame":
        r"100\.7M tets on 4 Ray workers[^|\n]*\|[^|\n]*?" + _RANGE + r" s a frame",
    "adjoint memory at 103 tets a ray": r"(\d+) MB, (?:as|the same) at 4 tets",
    "setup.sh's one-minute fit": _RANGE + r" dB\** held out(?: on a 2-core CPU, idle or busy|"
                                   r", idle or with one| \(the 8 views' mean\)| \(eight runs)",
}


def at_a_glance(record_text):
    """The record's headline table (between its ``at-a-glance`` markers)."""
    return record_text.split("<!-- at-a-glance: start -->")[1].split(
        "<!-- at-a-glance: end -->")[0]


def quoted_otherwise(source, pages):
    """``[(page, quantity, quoted, source's)]``: each quote in ``pages`` (``{name: text}``)
    of a :data:`QUANTITIES` value that is not ``source``'s (the headline table's text) as
    written or rounded to the quote's decimals."""
    out = []
    source = " ".join(source.split())          # (a quote may wrap across lines)
    pages = {page: " ".join(text.split()) for page, text in pages.items()}
    for name, pattern in QUANTITIES.items():
        truth = re.search(pattern, source)
        assert truth, f"the headline table does not state {name!r}"
        for page, text in pages.items():
            for m in re.finditer(pattern, text):
                for quoted, value in zip(m.groups(), truth.groups()):
                    decimals = len(quoted.partition(".")[2])
                    if abs(float(quoted) - float(value)) > 0.5 * 10.0 ** -decimals + 1e-9:
                        out.append((page, name, m.group(0), truth.group(0)))
    return out


def test_each_headline_figure_is_quoted_as_the_record_has_it():
    """The benchmark record's *At a glance* table is the one source of the headline figures
    (the documentation's *Benchmarks* page includes it). The README and every page quote
    each of them as it states it, or rounded; the record's own history (older runs) is not
    a quote."""
    source = at_a_glance(RECORD.read_text())
    pages = {"README.md": README.read_text()}
    pages.update({str(p.relative_to(ROOT)): p.read_text() for p in DOCS.rglob("*.md")})
    assert not quoted_otherwise(source, pages)
    # the check itself: a figure quoted with another value is found, a rounded one is not
    found = quoted_otherwise(source, {"x": "it costs 1.9–3.4× a render", "y": "70 MB, as at "
                                      "4 tets", "z": "| 1.9–2.4 s a frame", "w": "1.92–3.2× a "
                                      "primal render"})
    assert [(page, name) for page, name, _, _ in found] == [
        ("x", "a render and dr.backward against a render")]


def test_readme_python_runs_as_written_from_elsewhere(tmp_path):
    """The README's Python blocks, in order, in an empty directory outside the checkout,
    then its ``mi-tetvr render`` of the XML file they wrote: the dict scene, the XML file
    and the command render the same picture, and the gradient loop fits the colors (from
    gray, a loss of 1.5e-3, to 2.9e-5 measured; a wrong gradient stays near the start)."""
    text = README.read_text()
    blocks = fenced(text, "python")
    assert len(blocks) == 3, len(blocks)
    out = run_python("\n".join(blocks), tmp_path)
    loss = float(re.search(r"loss after 30 steps: (\S+)", out).group(1))
    assert loss < 2e-4, out
    line = next(x for b in fenced(text, "bash") for x in b.splitlines()
                if x.startswith("mi-tetvr render blob.xml"))
    args = line.split("#")[0].split()[1:]
    r = subprocess.run([sys.executable, "-m", "mi_tetvr.cli", *args, "--variant", VARIANT],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    dict_png, cli_png = read_png(tmp_path / "blob.png"), read_png(tmp_path / "blob_cli.png")
    assert dict_png.shape == cli_png.shape == (256, 256, 3)
    assert dict_png.max() > 0.3                      # the blobs are there
    assert np.abs(dict_png - cli_png).mean() < 2e-3, np.abs(dict_png - cli_png).mean()
    assert (tmp_path / "blob_xml.exr").stat().st_size > 0


def doc_pages():
    return sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)


@pytest.mark.parametrize("page", [p.relative_to(DOCS).as_posix() for p in doc_pages()
                                  if runnable(p.read_text())])
def test_runnable_blocks_of_the_site_run(page, tmp_path):
    """Every block marked runnable, a page's blocks in order, in an empty directory."""
    run_python("\n".join(runnable((DOCS / page).read_text())), tmp_path)


def test_some_blocks_are_runnable():
    """The runnable blocks the test above runs exist (a page that loses its marks
    would silently leave them untested)."""
    blocks = [b for p in doc_pages() for b in runnable(p.read_text())]
    assert len(blocks) >= 2 and all("import" in b for b in blocks), blocks


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The built site's folder: ``MI_TETVR_DOCS_HTML`` where given, else built here
    with warnings as errors."""
    given = os.environ.get("MI_TETVR_DOCS_HTML")
    if given:
        assert (Path(given) / "index.html").is_file(), given
        return Path(given)
    for module in ("sphinx", "myst_parser", "furo", "sphinxarg"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (pip install -e '.[docs]' installs it)")
    out = tmp_path_factory.mktemp("site") / "html"
    r = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b",
                        "html", str(DOCS), str(out)], capture_output=True, text=True,
                       timeout=1200)
    assert r.returncode == 0, (r.stdout + r.stderr)[-6000:]
    return out


def test_every_page_is_built(site):
    """One HTML page per source page (the guide, references, tutorials, benchmarks)."""
    pages = [p.relative_to(DOCS).with_suffix(".html") for p in doc_pages()]
    missing = [str(p) for p in pages if not (site / p).is_file()]
    assert not missing, missing
    assert len(pages) >= 30, len(pages)


def docstring_parameters(name):
    """``[(names, type, description)]`` of a plugin's ``pluginparameters`` list, read
    from its source (``* - name`` / ``- type`` / ``- description`` items)."""
    import ast
    path = ROOT / "mi_tetvr" / "plugins" / f"{name}.py"
    doc = ast.get_docstring(ast.parse(path.read_text()))
    lines = []
    for line in doc.split(".. pluginparameters::", 1)[1].splitlines()[1:]:
        if line.strip() and not line.startswith(" "):
            break                                    # the directive's block ends
        lines.append(line)
    block = "\n".join(lines)
    rows = []
    for item in re.split(r"^ \* - ", block, flags=re.M)[1:]:
        fields = re.split(r"^   - ", item, flags=re.M)
        rows.append(tuple(" ".join(f.split()) for f in fields[:3]))
    return rows


def cell_text(cell):
    """A table cell's text without markup, the site's typographic quotes as ASCII."""
    text = html.unescape(re.sub(r"<[^>]+>", " ", cell))
    return " ".join(text.translate(str.maketrans("‘’“”", "''\"\"")).split())


def test_plugin_reference_shows_every_parameter(site):
    """Each plugin's section of the reference has a row per parameter of its
    docstring, with its name(s), its type, its default (``(Default: X)`` in the
    docstring) and its description."""
    page = (site / "reference" / "plugins.html").read_text()
    for name in PLUGINS:
        start = page.index(f'id="{name}"')
        ends = [page.find(f'id="{other}"', start + 1) for other in PLUGINS if other != name]
        section = page[start:min([e for e in ends if e > 0] or [len(page)])]
        rows = re.findall(r'<tr class="plugin-parameter[^"]*">(.*?)</tr>', section, re.S)
        cells = [[cell_text(c) for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]
                 for r in rows]
        expected = docstring_parameters(name)
        assert len(cells) == len(expected), (name, len(cells), len(expected))
        for (names, kind, description), (c_names, c_kind, c_default, c_text) in zip(
                expected, cells):
            for n in names.split(","):
                assert n.strip() in c_names, (name, n, c_names)
            types = re.findall(r"\|(\w+)\|", kind)
            assert types and all(t in c_kind for t in types), (name, names, kind, c_kind)
            default = re.search(r"\(Default: (.*)\)\s*\.?$", description)
            if default:
                value = cell_text(default.group(1).replace("``", ""))
                assert value in c_default, (name, names, value, c_default)
            else:
                assert c_default == "—", (name, names, c_default)
            words = re.sub(r"[^\w\s]", " ", c_text).split()
            said = re.sub(r"[^\w\s]", " ", cell_text(description)).split()
            assert words[:4] == said[:4], (name, names, words[:4], said[:4])


def test_derivative_table_names_tests_that_exercise_each_parameter():
    """Each ``<id>.NAME`` row of *What is differentiable* cites test files that exist
    and differentiate that parameter by name."""
    text = (DOCS / "guide" / "derivatives.md").read_text()
    table = text.split("## What is differentiable", 1)[1].split("\n\n")[2]
    checked = 0
    for row in table.splitlines()[2:]:
        cells = [c.strip() for c in row.strip("|").split("|")]
        keys = re.findall(r"`<id>\.(\w+)`", cells[0])
        for cell in cells[1:]:
            if not cell.startswith(("yes", "`tf_color`", "overlay")):
                continue
            for test in re.findall(r"`(\w+/test_\w+\.py)`", cell):
                source = (ROOT / "tests" / test).read_text()
                assert any(k in source for k in keys) or not keys, (keys, test)
                checked += 1
    assert checked >= 12, checked


def test_site_in_a_real_browser(site):
    """Headless Chromium opens every page: it loads (a title), every picture shows
    (``naturalWidth > 0``), the plugin reference lists each plugin; screenshots of the
    index and of the ``tetmesh`` reference are not blank."""
    from PIL import Image
    import io
    keep = os.environ.get("MI_TETVR_DOCS_SCREENSHOTS")
    browser = start_browser(1280, 900)
    try:
        pages = sorted(p for p in site.rglob("*.html")
                       if p.name not in ("search.html", "genindex.html")
                       and "_static" not in p.parts and "_sources" not in p.parts)
        broken, images = [], 0
        for page in pages:
            browser.get(page.as_uri())
            assert "mi_tetvr" in browser.title, (page, browser.title)
            browser.execute_script("document.querySelectorAll('img').forEach("
                                   "i => i.loading = 'eager'); window.scrollTo(0, 1e9);")
            browser.execute_async_script(
                "const done = arguments[arguments.length - 1];"
                "Promise.all(Array.from(document.images).map(i => i.complete ? null :"
                " new Promise(r => { i.onload = r; i.onerror = r; }))).then(done);")
            state = browser.execute_script(
                "return Array.from(document.images).map(i => [i.src, i.naturalWidth]);")
            images += len(state)
            broken += [(page.name, src) for src, width in state if width == 0]
        assert not broken, broken
        assert images >= 10, images
        shots = {}
        for label, page in (("site_index", "index.html"),
                            ("site_tetmesh", "reference/plugins.html#tetmesh")):
            browser.get((site / page.split("#")[0]).as_uri() + (
                "#" + page.split("#")[1] if "#" in page else ""))
            if label == "site_tetmesh":
                listed = browser.execute_script(
                    "return ['tetmesh', 'tetvr', 'tetproj', 'tetpath'].filter("
                    "n => document.getElementById(n) !== null);")
                assert listed == list(PLUGINS), listed
            shots[label] = browser.get_screenshot_as_png()
    finally:
        browser.quit()
    for label, png in shots.items():
        picture = np.asarray(Image.open(io.BytesIO(png)).convert("L"), np.float64)
        assert picture.std() > 10, (label, picture.std())     # text and pictures, not blank
        if keep:
            Path(keep).mkdir(parents=True, exist_ok=True)
            (Path(keep) / f"{label}.png").write_bytes(png)
