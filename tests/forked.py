"""`python FILE ARGS...` run as a fork of the tests' fork server (tests/forkserver.py), with this process's folder,
environment and standard streams: the same run, without importing torch again. Signals sent to this process go to the
run; this process ends as the run did (its exit status, or killed by the same signal). Imports nothing but the standard
library, so it starts in milliseconds.

    python tests/forked.py SOCKET FILE [ARGS...]
"""

import json
import os
import signal
import socket
import struct
import sys


def read(connection: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = connection.recv(size - len(data))
        if not chunk:
            raise SystemExit(f"forked.py: the fork server closed the connection ({len(data)} of {size} bytes)")
        data += chunk
    return data


def main() -> None:
    path, *argv = sys.argv[1:]
    pending, run = [], []  # signals that come before the run's pid is known are sent as soon as it is

    def forward(number, frame):
        if run:
            os.kill(run[0], number)
        else:
            pending.append(number)

    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(number, forward)
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    connection.connect(path)
    request = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ)}).encode()
    socket.send_fds(connection, [struct.pack("!I", len(request))], [0, 1, 2])
    connection.sendall(request)
    run.append(struct.unpack("!i", read(connection, 4))[0])
    for number in pending:
        os.kill(run[0], number)
    (status,) = struct.unpack("!i", read(connection, 4))
    if os.WIFSIGNALED(status):
        number = os.WTERMSIG(status)
        if number not in (signal.SIGKILL, signal.SIGSTOP):  # the only two that cannot be handled
            signal.signal(number, signal.SIG_DFL)
        os.kill(os.getpid(), number)
    sys.exit(os.waitstatus_to_exitcode(status))


if __name__ == "__main__":
    main()
