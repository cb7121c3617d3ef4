"""The one progress bar of the entry points (tqdm): a bar on a terminal, plain lines in a log."""

import io

from linereg.bench import report
from linereg.cli.progress import Progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_on_a_terminal_a_tqdm_bar_with_the_note():
    stream = Terminal()
    with Progress(10, "localize", stream=stream) as progress:
        progress.update(3, "img_3.png: ok")
        progress.note("a line above the bar")
    text = stream.getvalue()
    assert "localize" in text and "3/10" in text and "img_3.png: ok" in text and "\r" in text
    assert "a line above the bar\n" in text


def test_in_a_log_one_line_per_step_or_none():
    stream = io.StringIO()
    with Progress(2, "map build", stream=stream, log_steps=True) as progress:
        progress.update(0, "read")
        progress.update(1, "normals")
        progress.update(1)  # no note: no line
    lines = stream.getvalue().splitlines()
    assert [line.split()[:3] for line in lines] == [["map", "build", "0/2"], ["map", "build", "1/2"]]
    assert lines[0].endswith(" read") and lines[1].endswith(" normals") and "\r" not in stream.getvalue()
    quiet = io.StringIO()
    Progress(2, "bench", stream=quiet).update(1, "trial")
    assert quiet.getvalue() == ""


def test_the_benchmarks_use_the_same_bar():
    assert report.Progress is Progress
    stream = Terminal()
    progress = report.Progress(4, stream=stream)
    progress.advance("seed 0 image 1")
    progress.close()
    assert "1/4" in stream.getvalue() and "seed 0 image 1" in stream.getvalue()
