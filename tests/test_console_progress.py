"""pelvislab run's progress where stderr is a log file, not a terminal."""

from __future__ import annotations

import io

from pelvislab.acquisition.runner import Progress
from pelvislab.app.commands.run import ConsoleProgress


def test_a_log_file_gets_a_line_at_every_tenth_of_the_plan():
    # before: nothing between "setup k/N" lines in a nohup or service log
    stream = io.StringIO()
    console = ConsoleProgress(runner=None, stream=stream)
    for done in range(0, 309):
        console(Progress(0.1 * done, done, 308, 0.1 * done, 0.1 * (308 - done)))
    lines = stream.getvalue().splitlines()
    assert len(lines) == 9 and lines[0].startswith("progress: 31/308 steps (10 %)")
    assert lines[-1].startswith("progress: 278/308 steps (90 %)")
