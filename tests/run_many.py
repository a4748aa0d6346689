"""Run a script several times in one process, each time as `python SCRIPT FLAGS...` would, and print what each run
returned: many refusals of bad input tested for the cost of one start of Python and torch.

    python tests/run_many.py SCRIPT < cases.json      # cases: [{"cwd": folder, "argv": [flag, ...]}, ...]

Each case runs the script afresh as __main__ (runpy) in its own folder, with its own sys.argv. What it ends with is
recorded as a process would end (forkserver.run_as_main): the code of SystemExit (a message given instead of a code goes
to stderr, status 1), 1 with the traceback on stderr for an uncaught exception, 0 for a normal end. Printed last, on
stdout: one JSON list of {"returncode", "stdout", "stderr"}. Meant for runs that end before any training: a case that
trains runs to its end."""

import contextlib
import io
import json
import os
import signal
import sys

from forkserver import run_as_main  # tests/forkserver.py: how a forked run ends, the same way


def run_case(script: str, argv: list[str]) -> dict:
    out, err = io.StringIO(), io.StringIO()
    sys.argv = [script, *argv]
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = run_as_main(script)
    return {"returncode": code, "stdout": out.getvalue(), "stderr": err.getvalue()}


def main() -> None:
    script, results = os.path.abspath(sys.argv[1]), []
    defaults = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)}
    for case in json.load(sys.stdin):
        os.chdir(case["cwd"])
        results.append(run_case(script, case["argv"]))
        for number, handler in defaults.items():  # as a fresh process would start the next case
            signal.signal(number, handler)
    json.dump(results, sys.stdout)


if __name__ == "__main__":
    main()
