"""A tutorial's page: ``.. tutorial:: NAME`` shows ``tutorials/NAME.py``'s docstring,
the command that runs it, the picture it makes (``docs/images/tutorials/NAME.png``, or
the file named by ``:image:``) and the script itself.
"""
import ast
import re
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive, directives
from docutils.statemachine import StringList

ROOT = Path(__file__).resolve().parents[2]


class Tutorial(Directive):
    required_arguments = 1
    option_spec = {"image": directives.unchanged, "alt": directives.unchanged}

    def run(self):
        name = self.arguments[0]
        script = ROOT / "tutorials" / f"{name}.py"
        if not script.is_file():
            raise self.error(f"no tutorial {script}")
        doc = ast.get_docstring(ast.parse(script.read_text())) or ""
        body = doc.removeprefix("Tutorial: ")
        body = body[:1].upper() + body[1:]
        # a docstring's section titles as rubrics (a directive cannot open sections)
        body = re.sub(r"^(\S.*)\n([-=~])\2{2,}$", r".. rubric:: \1\n", body, flags=re.M)
        image = self.options.get("image", f"/images/tutorials/{name}.png")
        alt = self.options.get("alt", f"the picture tutorials/{name}.py makes")
        lines = body.splitlines() + [
            "", "Run it from a checkout (``--help`` lists its options)::", "",
            f"    python tutorials/{name}.py", "",
            f".. figure:: {image}", f"   :alt: {alt}", "   :width: 100%", "",
            f"   What ``tutorials/{name}.py`` wrote with its default settings.", "",
            ".. rubric:: The script", "",
            f".. literalinclude:: /../tutorials/{name}.py", "   :language: python", ""]
        container = nodes.container(classes=["tutorial"])
        self.state.nested_parse(StringList(lines, source=str(script)), self.content_offset,
                                container)
        return [container]


def setup(app):
    app.add_directive("tutorial", Tutorial)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
