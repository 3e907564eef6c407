"""The plugin reference: each plugin's docstring as Mitsuba's documentation shows it.

``.. mitsuba-plugin:: NAME`` inserts the docstring of ``mi_tetvr.plugins.NAME``
(reStructuredText). Its ``.. pluginparameters::`` list (Mitsuba's own directive: one
item per parameter, with its name, type and description, the default at the end of
the description as ``(Default: ...)``) becomes a table of the parameter, its type, its
default and its description.
"""
import importlib
import inspect
import re

from docutils import nodes
from docutils.parsers.rst import Directive, directives
from docutils.statemachine import StringList

DEFAULT = re.compile(r"\s*\(Default:\s*(.*)\)\s*\.?\s*$", re.S)
# Mitsuba's type names (``|float|``, its documentation's substitutions), shown in italics
TYPE = re.compile(r"\|(\w+)\|")


def parameter_rows(lines):
    """The rows of a ``pluginparameters`` block: ``(name, type, description)`` as the
    text of each of its three fields, from the block's lines."""
    rows = []
    for line in lines:
        stripped = line.strip()
        if stripped.startswith("* - "):
            rows.append([stripped[4:]])
        elif stripped.startswith("- ") and rows:
            rows[-1].append(stripped[2:])
        elif stripped and rows:
            rows[-1][-1] += " " + stripped
    for row in rows:
        if len(row) != 3:
            raise ValueError(f"a plugin parameter needs a name, a type and a description: {row}")
    return [tuple(row) for row in rows]


def split_default(description):
    """``(description, default)`` of a description that ends in ``(Default: ...)``
    (``default`` None when it does not)."""
    m = DEFAULT.search(description)
    if not m:
        return description, None
    return description[:m.start()].rstrip(), m.group(1).strip()


class PluginParameters(Directive):
    """Mitsuba's ``pluginparameters``: a table of a plugin's parameters."""
    has_content = True

    def cell(self, text):
        entry = nodes.entry()
        paragraph = StringList([text], source="pluginparameters")
        self.state.nested_parse(paragraph, self.content_offset, entry)
        return entry

    def run(self):
        rows = parameter_rows(self.content)
        table = nodes.table(classes=["pluginparameters"])
        group = nodes.tgroup(cols=4)
        table += group
        for width in (18, 12, 14, 56):
            group += nodes.colspec(colwidth=width)
        head = nodes.thead()
        header = nodes.row()
        for title in ("Parameter", "Type", "Default", "Description"):
            header += nodes.entry("", nodes.paragraph(text=title))
        head += header
        group += head
        body = nodes.tbody()
        for name, kind, description in rows:
            text, default = split_default(description)
            row = nodes.row(classes=["plugin-parameter"])
            names = ", ".join(f"``{n.strip()}``" for n in name.split(","))
            row += self.cell(f"{names}")
            row += self.cell(TYPE.sub(r"*\1*", kind))
            row += self.cell(default if default is not None else "—")
            row += self.cell(text)
            body += row
        group += body
        return [table]


class MitsubaPlugin(Directive):
    """The docstring of ``mi_tetvr.plugins.NAME``, parsed in place."""
    required_arguments = 1
    option_spec = {"module": directives.unchanged}

    def run(self):
        name = self.arguments[0]
        module = importlib.import_module(self.options.get("module", f"mi_tetvr.plugins.{name}"))
        doc = inspect.cleandoc(module.__doc__ or "")
        if not doc:
            raise self.error(f"plugin {name} has no docstring")
        container = nodes.container(classes=["mitsuba-plugin", f"plugin-{name}"])
        self.state.nested_parse(StringList(doc.splitlines(), source=module.__file__),
                                self.content_offset, container)
        return [container]


def setup(app):
    app.add_directive("pluginparameters", PluginParameters)
    app.add_directive("mitsuba-plugin", MitsubaPlugin)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
