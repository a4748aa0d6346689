"""A fork server for the tests: Python, torch and the scripts' other libraries imported once, then a fresh fork of that
process for each script run, instead of a new interpreter that spends seconds importing torch again.

    python tests/forkserver.py SOCKET        # serves until killed; prints "ready" once it listens

A client (tests/forked.py) sends a run: argv, working directory, environment, and its own stdin/stdout/stderr. The
server forks a keeper for it, which forks the run and tells the client the run's pid, then its exit status. The run is
a plain `python FILE ARGS...` but for the imports already done: __main__ is FILE (runpy), sys.path and os.environ are
the client's, signal handlers are the defaults, stdout and stderr are buffered as PYTHONUNBUFFERED says. The libraries
imported here read nothing from the environment at import time that a run sets differently (MuJoCo, which reads
MUJOCO_GL, is left to each run)."""

import os
import signal
import socket
import struct
import sys

SERVER_PATH = [path for path in sys.path[1:] if path not in os.environ.get("PYTHONPATH", "").split(os.pathsep)]

import gymnasium  # noqa: E402, F401
import numpy  # noqa: E402, F401
import torch  # noqa: E402, F401
import tyro  # noqa: E402, F401
from torch.utils.tensorboard import SummaryWriter  # noqa: E402, F401


def receive(connection: socket.socket) -> tuple[dict, list[int]]:
    """The client's request: a length, its three standard streams (as file descriptors), then the request itself."""
    import json

    data, fds, _, _ = socket.recv_fds(connection, 4, 3)
    (length,) = struct.unpack("!I", data)
    payload = b""
    while len(payload) < length:
        chunk = connection.recv(length - len(payload))
        if not chunk:
            raise ConnectionError("the client left before its request was whole")
        payload += chunk
    return json.loads(payload), fds


def run_as_main(file: str) -> int:
    """Run `file` as __main__ (runpy) and return the exit status `python FILE` would end with: SystemExit's code (a
    message instead of a code goes to stderr, status 1), 1 with the traceback for an uncaught exception, -SIGINT for a
    KeyboardInterrupt (Python ends by the signal itself), 0 for a normal end."""
    import runpy
    import traceback

    try:
        runpy.run_path(file, run_name="__main__")
    except SystemExit as stop:
        if stop.code is None or isinstance(stop.code, int):
            return stop.code or 0
        print(stop.code, file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        traceback.print_exc()
        return -signal.SIGINT
    except BaseException:
        traceback.print_exc()
        return 1
    return 0


def run(request: dict, fds: list[int]) -> None:
    """In the forked run: become `python FILE ARGS...` in the client's folder, environment and streams; never return."""
    import io

    signal.signal(signal.SIGINT, signal.default_int_handler)  # as Python starts (and SIGPIPE ignored, as here)
    for number in (signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2, signal.SIGCHLD):
        signal.signal(number, signal.SIG_DFL)
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    os.environ.clear()
    os.environ.update(request["env"])
    os.chdir(request["cwd"])
    unbuffered = bool(os.environ.get("PYTHONUNBUFFERED"))
    sys.stdin = io.TextIOWrapper(open(0, "rb", closefd=False), encoding="utf-8")
    sys.stdout = io.TextIOWrapper(open(1, "wb", closefd=False), encoding="utf-8", write_through=unbuffered)
    sys.stderr = io.TextIOWrapper(open(2, "wb", closefd=False), encoding="utf-8", errors="backslashreplace",
                                  write_through=True, line_buffering=True)  # fmt: skip
    file, *args = request["argv"]
    extra = [path for path in os.environ.get("PYTHONPATH", "").split(os.pathsep) if path]
    sys.path[:] = [os.path.dirname(os.path.abspath(file)), *extra, *SERVER_PATH]
    sys.argv = [file, *args]
    code = run_as_main(file)
    import atexit

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    if code == -signal.SIGINT:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    os._exit(code)


def keep(connection: socket.socket, request: dict, fds: list[int]) -> None:
    """In the keeper: fork the run, tell the client its pid and then its wait status; kill the run if the client goes."""
    import select

    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    pid = os.fork()
    if pid == 0:
        connection.close()
        run(request, fds)
    for fd in fds:
        os.close(fd)
    connection.sendall(struct.pack("!i", pid))
    watch = os.pidfd_open(pid)
    while True:
        ready, _, _ = select.select([connection, watch], [], [])
        if watch in ready:
            break
        if not connection.recv(1):  # the client is gone (killed): the run goes too
            os.kill(pid, signal.SIGKILL)
    _, status = os.waitpid(pid, 0)
    connection.sendall(struct.pack("!i", status))
    os._exit(0)


def main() -> None:
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # keepers are reaped as they end
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(sys.argv[1])
    server.listen(64)
    print("ready", flush=True)
    while True:
        connection, _ = server.accept()
        try:
            request, fds = receive(connection)
        except (ConnectionError, OSError, ValueError):
            connection.close()
            continue
        if os.fork() == 0:
            server.close()
            keep(connection, request, fds)
        connection.close()
        for fd in fds:
            os.close(fd)


if __name__ == "__main__":
    main()
