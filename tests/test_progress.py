"""Progress reports (appendix 00b): a bar in a sized terminal, plain lines in a log or a terminal of
0 columns, and nothing stale after an interruption. The terminals here are real pseudo-terminals."""
import fcntl
import io
import os
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from pemamoe.core import Progress

ROOT = Path(__file__).resolve().parents[1]


def _run_in_terminal(code: str, columns: int) -> str:
    """Run `code` in a fresh Python whose stderr is a pseudo-terminal `columns` wide; return what it drew."""
    leader, follower = os.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    env = {**os.environ, "COLUMNS": "", "LINES": ""}
    env.pop("COLUMNS"), env.pop("LINES")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdin=subprocess.DEVNULL, stdout=follower,
                            stderr=follower, env=env)
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 65536)
        except OSError:  # the terminal closed with the process
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=60)
    os.close(leader)
    assert proc.returncode == 0, b"".join(chunks).decode(errors="replace")
    return b"".join(chunks).decode(errors="replace")


_COUNT = """
from pemamoe.core import Progress
with Progress(5, label="demo", unit="it", every=0.0) as bar:  # enabled=None: stderr is a terminal here
    for _ in range(5):
        bar.set_postfix(phase=1)
        bar.update()
"""


def test_a_terminal_of_zero_columns_gets_plain_lines():
    out = _run_in_terminal(_COUNT, columns=0)
    lines = [line for line in out.replace("\r\n", "\n").split("\n") if line.strip()]
    assert lines and all("\r" not in line for line in lines), repr(out)
    assert "demo: 0/5 it" in lines[0] and "demo: 5/5 it" in lines[-1] and "phase=1" in lines[-1]


def test_a_sized_terminal_gets_a_bar_that_stays_at_the_end():
    out = _run_in_terminal(_COUNT, columns=100).replace("\r\n", "\n")  # the terminal's newline
    assert "\r" in out  # redrawn in place
    assert "5/5" in out.rsplit("\r", 1)[-1]


_INTERRUPTED = """
import sys
from pemamoe.core import Progress
try:
    with Progress(5, label="demo", unit="it") as bar:
        bar.update()
        raise KeyboardInterrupt
except KeyboardInterrupt:
    print("INTERRUPTED", file=sys.stderr, flush=True)
"""


def test_an_interrupted_bar_is_cleared_and_not_drawn_again_after_the_message():
    out = _run_in_terminal(_INTERRUPTED, columns=100).replace("\r\n", "\n")
    before, after = out.split("INTERRUPTED", 1)
    assert "/5" in before and after.strip() == "", repr(out)  # the bar was drawn, and nothing after
    assert before.rsplit("\r", 1)[-1].strip(" \x1b[A") == ""  # the bar's line was blanked before the message


def test_the_trainer_clears_its_bar_when_interrupted(monkeypatch):
    import pemamoe.bookkeeping as bookkeeping
    from pemamoe import mappo

    log = io.StringIO()
    made = []

    class Recording(Progress):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **{**kwargs, "stream": log, "every": 0.0})
            made.append(self)

    calls = {"n": 0}
    record = bookkeeping.IterationLogger.record

    def record_then_stop(self, *args, **kwargs):
        record(self, *args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(bookkeeping, "Progress", Recording)
    monkeypatch.setattr(bookkeeping.IterationLogger, "record", record_then_stop)
    with pytest.raises(KeyboardInterrupt):
        mappo.train(mappo.TrainConfig.for_scale("ci", iterations=4), progress=True)
    lines = log.getvalue().splitlines()
    assert len(made) == 1 and made[0].enabled is False  # closed
    assert "2/4" in lines[-1] and all("4/4" not in line for line in lines)  # no final line after the stop


def test_progress_off_prints_nothing_and_bad_streams_count_as_logs():
    log = io.StringIO()
    with Progress(3, label="x", enabled=False, stream=log) as bar:
        bar.update(3)
    assert log.getvalue() == ""

    class Closed(io.StringIO):
        def isatty(self):
            raise ValueError("I/O operation on closed file")

    with Progress(2, label="x", stream=Closed()) as bar:  # enabled=None and no terminal: off
        bar.update(2)
    assert bar.enabled is False
