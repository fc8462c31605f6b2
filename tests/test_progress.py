"""Progress bars: drawn on a terminal, never with --quiet or into a file or pipe."""
import io

from startrack.progress import ProgressBar


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_bar_on_a_terminal_counts_to_the_total():
    term = _Terminal()
    bar = ProgressBar("render", stream=term)
    for done in range(1, 6):
        bar(done, 5)
    text = term.getvalue()
    assert "render" in text and "5/5" in text


def test_no_bar_when_quiet_or_not_a_terminal():
    term = _Terminal()
    ProgressBar("render", quiet=True, stream=term)(1, 1)
    pipe = io.StringIO()
    ProgressBar("render", stream=pipe)(1, 1)
    assert term.getvalue() == "" and pipe.getvalue() == ""
