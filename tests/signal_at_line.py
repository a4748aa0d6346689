"""Run a script as `python SCRIPT FLAGS...` would, and send its own process SIGNAL right after it prints the first line
matching PATTERN: a stop (SIGTERM, SIGINT) or a kill (SIGKILL) at an exact point of the run, however fast the machine.

    python tests/signal_at_line.py SIGNAL PATTERN SCRIPT [FLAGS...]

A test that signals a run from outside, on reading a line, races the run: on a fast machine the run may be steps later,
or done, when the signal lands. Here the signal is sent by the printing call itself, so the run is stopped at the step
that printed the line. The script runs as __main__ (what it pickles into resume.pt loads in a plain run). Before a
SIGKILL the TensorBoard writers are flushed, so that everything logged before the kill is on disk, as the worst case of
a kill is: a resumed run must drop what was logged after its resume file. PATTERN is a regex searched in each printed
text with re.MULTILINE (`^` matches at a line's start)."""

import builtins
import os
import re
import runpy
import signal
import sys


def main() -> None:
    name, pattern, script, *flags = sys.argv[1:]
    number, regex = getattr(signal, name), re.compile(pattern, re.MULTILINE)
    writers, sent = [], []

    from torch.utils.tensorboard import SummaryWriter

    init = SummaryWriter.__init__

    def recording_init(self, *args, **kwargs):
        writers.append(self)
        init(self, *args, **kwargs)

    def print_then_signal(*values, sep=" ", **options):
        builtins.print(*values, sep=sep, **options)
        if not sent and regex.search(sep.join(map(str, values))):
            sent.append(True)
            sys.stdout.flush()
            sys.stderr.flush()
            if number == signal.SIGKILL:
                for writer in writers:
                    writer.flush()
            os.kill(os.getpid(), number)

    SummaryWriter.__init__ = recording_init
    sys.argv = [script, *flags]
    sys.path[0] = os.path.dirname(os.path.abspath(script))
    runpy.run_path(script, init_globals={"print": print_then_signal}, run_name="__main__")


if __name__ == "__main__":
    main()
