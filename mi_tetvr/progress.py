"""Progress bars that read well on a terminal and in a log file.

:func:`progress_bar` is tqdm's bar on a terminal. When its output is not a
terminal (a log file, a pipe, a CI job), tqdm's bar would rewrite one line
with carriage returns many times a second; there it writes a whole line
instead, at most every :data:`LOG_SECONDS` seconds, and one at the end. Every
long-running step of the project shows its progress through it.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

__all__ = ["progress_bar", "LOG_SECONDS"]

#: Seconds between the lines a bar writes into a file.
LOG_SECONDS = 5.0


class _LineBar(tqdm):
    """A tqdm bar that writes one line per update (for files)."""

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        # shown with the next line, not as a line of its own
        super().set_postfix(ordered_dict, refresh=False, **kwargs)

    def set_description(self, desc=None, refresh=True):
        super().set_description(desc, refresh=False)

    def display(self, msg=None, pos=None):
        # (tqdm calls it only for a bar that shows, and once more from close())
        text = (self.__str__() if msg is None else msg).strip()
        if text:
            self.fp.write(text + "\n")
            self.fp.flush()
        return True


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(iterable=None, *, file=None, disable=False, **kw):
    """A tqdm bar (same arguments) on ``file`` (default ``sys.stderr``); on
    anything but a terminal, a line at most every :data:`LOG_SECONDS` seconds."""
    stream = sys.stderr if file is None else file
    if _is_terminal(stream):
        return tqdm(iterable, file=stream, disable=disable, **kw)
    kw.update(mininterval=max(float(kw.get("mininterval", 0.0)), LOG_SECONDS),
              maxinterval=max(float(kw.get("maxinterval", 0.0)), LOG_SECONDS),
              dynamic_ncols=False, ascii=True)
    kw.setdefault("bar_format", "{l_bar}{n_fmt}/{total_fmt} [{elapsed}<{remaining}, "
                                "{rate_fmt}{postfix}]")
    kw.pop("leave", None)
    return _LineBar(iterable, file=stream, disable=disable, leave=True, **kw)
