"""Progress bars: tqdm's on a terminal, whole lines at most every LOG_SECONDS in a file."""
import io

import mi_tetvr.progress as progress


class Clock:
    """tqdm's clock, simulated: ``t`` seconds."""
    t = 0.0

    def __call__(self):
        return self.t


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_file_gets_a_line_every_few_seconds(monkeypatch):
    clock = Clock()
    import tqdm.std
    monkeypatch.setattr(tqdm.std, "time", clock)
    log = io.StringIO()
    with progress.progress_bar(total=100, file=log, desc="fit") as bar:
        for i in range(100):             # 100 updates over 30 simulated seconds
            clock.t += 0.3
            bar.update(1)
            bar.set_postfix(step=i)        # (as the fit does after every step)
    text = log.getvalue()
    assert "\r" not in text
    lines = [line for line in text.splitlines() if line.strip()]
    # the first line, one per LOG_SECONDS (30 s / 5 s) and the last, each a whole status
    assert 5 <= len(lines) <= 30 / progress.LOG_SECONDS + 3, lines
    assert all(line.startswith("fit:") for line in lines)
    assert "100/100" in lines[-1]


def test_a_terminal_gets_tqdms_bar():
    term = Terminal()
    with progress.progress_bar(total=3, file=term, desc="x", mininterval=0) as bar:
        for _ in range(3):
            bar.update(1)
    assert "\r" in term.getvalue() and "3/3" in term.getvalue()
    quiet = io.StringIO()
    with progress.progress_bar(total=3, file=quiet, disable=True) as bar:
        bar.update(3)
    assert quiet.getvalue() == ""
