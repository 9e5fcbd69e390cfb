"""Progress bars drawn for a terminal or for a log file."""
from __future__ import annotations

import io

from dagr_lite.progress import LOG_INTERVAL_S, progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_in_a_log_file_redraws_at_the_log_interval_and_a_passing_bar_inside_another_is_not_drawn():
    log = io.StringIO()
    outer = progress_bar(total=100, desc="training", file=log)
    assert (outer.mininterval, outer.maxinterval, outer.disable) == (LOG_INTERVAL_S, LOG_INTERVAL_S, False)
    inner = progress_bar(range(50), desc="validating", leave=False, file=log)
    assert inner.disable
    assert list(inner) == list(range(50))  # a bar not drawn still yields every item
    for _ in range(100):
        outer.update(1)
        outer.set_postfix(loss="1.0", refresh=False)
    outer.close()
    assert log.getvalue().count("training") <= 3  # the first draw, the last, and at most one between
    alone = progress_bar(range(3), desc="evaluating", leave=False, file=io.StringIO())
    assert not alone.disable  # a passing bar with none around it is drawn
    alone.close()


def test_a_bar_on_a_terminal_keeps_tqdms_defaults():
    screen = Terminal()
    outer = progress_bar(total=10, desc="training", file=screen)
    inner = progress_bar(range(5), leave=False, file=screen)
    assert outer.mininterval == 0.1 and not inner.disable
    inner.close()
    outer.close()


def test_a_message_while_a_bar_is_drawn_is_a_line_of_its_own(capsys):
    """The bar on stderr (captured: not a terminal) is cleared before the message and drawn again after it."""
    import sys

    from dagr_lite.progress import say

    def run(message: str | None) -> tuple[str, str]:
        bar = progress_bar(total=10, desc="training", file=sys.stderr)
        bar.update(3)
        if message:
            say(message)
        bar.close()
        return capsys.readouterr()

    quiet, told = run(None), run("step 3: the graph joins")
    assert told.out == "step 3: the graph joins\n" and quiet.out == ""
    assert told.err.count("training") == quiet.err.count("training") + 1  # drawn again after the message
    assert told.err.count("\r") > quiet.err.count("\r")  # and cleared before it
