"""Run a script as `python SCRIPT FLAGS...` would, and send its own process SIGNAL right after it prints the first line
matching PATTERN: a stop (SIGTERM, SIGINT) or a kill (SIGKILL) at an exact point of the run, however fast the machine.
With `hold` for SIGNAL, the run waits at that line instead until a stop signal comes from outside (SIGINT, SIGTERM,
SIGUSR1 or SIGUSR2, e.g. from a launcher), then hands it to the script's own handler and goes on: it cannot end before
the signal arrives, however long the sender takes.

    python tests/signal_at_line.py SIGNAL|hold PATTERN SCRIPT [FLAGS...]

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
import time

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)


def hold() -> None:
    """Wait for a stop signal, then give it to the handler the script had installed for it."""
    handlers, arrived = {number: signal.getsignal(number) for number in STOP_SIGNALS}, []
    for number in STOP_SIGNALS:
        signal.signal(number, lambda number, frame: arrived.append((number, frame)))
    while not arrived:
        time.sleep(0.05)
    for number, handler in handlers.items():
        signal.signal(number, handler)
    number, frame = arrived[0]
    if callable(handlers[number]):
        handlers[number](number, frame)
    else:
        os.kill(os.getpid(), number)


def main() -> None:
    name, pattern, script, *flags = sys.argv[1:]
    number, regex = None if name == "hold" else getattr(signal, name), re.compile(pattern, re.MULTILINE)
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
            if number is None:
                hold()
                return
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
