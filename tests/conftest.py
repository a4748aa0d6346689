import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # headless in-process rendering; read when mujoco is first imported

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]
HANG_TIMEOUT = 1800  # seconds: a guard against a run that hangs, far beyond any run's time on a slow, busy machine
FORK = os.environ.get("DGRL_TESTS_FORK", "1") != "0"  # 0: every script run starts a fresh interpreter
FORK_SERVER = {}


def python() -> list[str]:
    """The command that starts `python FILE ARGS...` for a test. A script run pays seconds of CPU to import torch; the
    tests run scripts some two hundred times, so each run is a fork of one server that has torch and the scripts'
    other libraries imported already (tests/forkserver.py, one per test process, started on first use), reached through
    tests/forked.py, which behaves as the run's own process would: same folder, environment, streams, signals and exit
    status. With DGRL_TESTS_FORK=0 in the environment every run starts a fresh interpreter instead."""
    if not FORK:
        return [sys.executable]
    if not FORK_SERVER:
        import atexit
        import shutil
        import tempfile

        folder = tempfile.mkdtemp(prefix="dgrl-tests-")
        socket_path = os.path.join(folder, "forkserver")
        server = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "forkserver.py"), socket_path],
            stdout=subprocess.PIPE, text=True, env={"PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"},
        )  # fmt: skip
        assert server.stdout.readline().strip() == "ready", "the tests' fork server did not start"
        atexit.register(lambda: (server.kill(), server.wait(), shutil.rmtree(folder, ignore_errors=True)))
        FORK_SERVER["socket"] = socket_path
    return [sys.executable, str(ROOT / "tests" / "forked.py"), FORK_SERVER["socket"]]


@pytest.fixture(autouse=True)
def _seed_everything():
    """Every test starts from the same torch random state, so a failure reproduces; one torch thread per test worker
    (pytest -n auto already fills the cores, and two threads per worker made small-network tests 3x slower)."""
    torch.manual_seed(0)
    torch.set_num_threads(1)


@pytest.fixture
def run_script(tmp_path):
    """Run a project script as a user would, in a fresh working directory, on one thread, with HANG_TIMEOUT as a guard
    against a hang; `env` adds environment variables (e.g. MUJOCO_GL)."""

    def run(script: str, *flags: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        base = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
        return subprocess.run(
            [*python(), str(ROOT / script), *flags],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=HANG_TIMEOUT,
            env=base | (env or {}),
        )

    return run


def run_many(script: str, cases: list[tuple[Path, list[str]]], prefix: tuple[str, ...] = ()) -> list:
    """Run `script` once per (folder, flags) case, each as a user would run it in that folder, all in ONE process
    (tests/run_many.py): for refusals of bad input, which end before any work, at the cost of one start of Python and
    torch. Returns a subprocess.CompletedProcess per case. `prefix` goes before the Python command (e.g. setpriv)."""
    import json

    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    interpreter = [*prefix, sys.executable] if prefix else python()  # a fork would not drop the prefix's privileges
    command = [*interpreter, str(ROOT / "tests" / "run_many.py"), str(ROOT / script)]
    payload = json.dumps([{"cwd": str(folder), "argv": list(flags)} for folder, flags in cases])
    batch = subprocess.run(command, input=payload, capture_output=True, text=True, timeout=HANG_TIMEOUT, env=env)
    assert batch.returncode == 0, batch.stderr[-3000:]
    results = json.loads(batch.stdout)
    return [
        subprocess.CompletedProcess([script, *flags], result["returncode"], result["stdout"], result["stderr"])
        for (_, flags), result in zip(cases, results, strict=True)
    ]


class NoHostSync(TorchDispatchMode):
    """Fails on every op that makes the host wait for the device: reading a value back (`.item()`, `bool(tensor)`:
    aten._local_scalar_dense), ops whose output size depends on the data (nonzero, masked_select, unique, bincount,
    which reads its largest index), and copies from a device to the host. Code that runs clean under it on the CPU
    never stalls a GPU stream and can be captured in a CUDA graph."""

    FORBIDDEN = frozenset(
        getattr(torch.ops.aten, name)
        for name in (
            "_local_scalar_dense",
            "nonzero",
            "masked_select",
            "bincount",
            "unique",
            "_unique",
            "_unique2",
            "unique_consecutive",
            "unique_dim",
            "repeat_interleave",
            "argwhere",
            "nonzero_static",
        )
        if hasattr(torch.ops.aten, name)
    )

    INDEXING = frozenset(getattr(torch.ops.aten, name) for name in ("index", "index_put", "index_put_", "_index_put_impl_"))

    ops = 0  # how many ops ran under the guard: a measure of per-op dispatch overhead

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.ops += 1
        if func.overloadpacket in self.FORBIDDEN:
            raise AssertionError(f"{func} makes the host wait for the device")
        if func.overloadpacket in self.INDEXING and any(
            index is not None and index.dtype in (torch.bool, torch.uint8) for index in args[1]
        ):  # a boolean mask as an index is a nonzero on the device
            raise AssertionError(f"{func} with a boolean mask makes the host wait for the device")
        out = func(*args, **kwargs)
        if func.overloadpacket in (torch.ops.aten._to_copy, torch.ops.aten.copy_):
            source = args[1] if func.overloadpacket is torch.ops.aten.copy_ else args[0]
            target = args[0] if func.overloadpacket is torch.ops.aten.copy_ else out
            if source.device.type != "cpu" and target.device.type == "cpu":
                raise AssertionError(f"{func} copies from {source.device} to the host")
        return out


WALL_CLOCK_TAGS = ("charts/SPS",)  # scalars that measure time, not the run: never compared


def tensorboard_scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of a run folder as TensorBoard shows it: all its event files in order, with what a resumed run's
    purge_step drops already dropped. NaN is returned as the string "nan" so that equal runs compare equal."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {
        tag: [(event.step, "nan" if event.value != event.value else event.value) for event in accumulator.Scalars(tag)]
        for tag in accumulator.Tags()["scalars"]
    }


def checkpoint_tensors(path: Path) -> dict[str, torch.Tensor]:
    """The tensors of a --save-model checkpoint, by dotted key (its flags left out: a resumed run adds --resume)."""

    def flatten(value, prefix: str) -> dict:
        if isinstance(value, dict):
            return {key: tensor for name, item in value.items() for key, tensor in flatten(item, f"{prefix}{name}.").items()}
        return {prefix[:-1]: value} if isinstance(value, torch.Tensor) else {}

    saved = torch.load(path, map_location="cpu", weights_only=True)
    return flatten({key: value for key, value in saved.items() if key != "args"}, "")


def assert_same_run(straight_dir: Path, resumed_dir: Path, ignore: tuple[str, ...] = ()) -> None:
    """A resumed run's folder holds what a straight run's does: every TensorBoard scalar (but WALL_CLOCK_TAGS and
    `ignore`) at the same steps with the same values, and a final checkpoint with equal tensors."""
    skip = set(WALL_CLOCK_TAGS) | set(ignore)
    expected = {tag: points for tag, points in tensorboard_scalars(straight_dir).items() if tag not in skip}
    got = {tag: points for tag, points in tensorboard_scalars(resumed_dir).items() if tag not in skip}
    assert sorted(got) == sorted(expected)
    for tag, points in expected.items():
        assert got[tag] == points, f"{tag}: straight {points[:6]}... resumed {got[tag][:6]}..."
    (straight_checkpoint,) = straight_dir.glob("*.cleanrl_model")
    (resumed_checkpoint,) = resumed_dir.glob("*.cleanrl_model")
    expected_tensors, got_tensors = checkpoint_tensors(straight_checkpoint), checkpoint_tensors(resumed_checkpoint)
    assert sorted(got_tensors) == sorted(expected_tensors)
    for key, tensor in expected_tensors.items():
        assert torch.equal(got_tensors[key], tensor), key


def signal_at_line(signal_name: str, pattern: str, script: str | Path, *flags: str) -> list[str]:
    """The command that runs `script` with `flags` and sends its own process `signal_name` (SIGTERM, SIGKILL...) right
    after it prints the first line matching the regex `pattern` (tests/signal_at_line.py): a stop or kill at an exact
    point of the run, on any machine."""
    return [*python(), str(ROOT / "tests" / "signal_at_line.py"), signal_name, pattern, str(ROOT / script), *flags]


@pytest.fixture
def resume_check(tmp_path):
    """`check(script, flags, stop_after)`: run A straight through; run B, stopped by SIGTERM right after it prints a line
    matching the regex `stop_after` (so at that line's step, however fast the machine), then continued with --resume to
    the same budget. Every TensorBoard scalar of B (but WALL_CLOCK_TAGS and `ignore`) must equal A's, step for step, and
    so must every tensor of the final checkpoints (pass --save-model in `flags`). Returns B's first output, so that a
    test can check where it stopped."""

    def check(script: str, flags: list[str], stop_after: str, ignore: tuple[str, ...] = ()) -> str:
        env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        command = [*python(), str(ROOT / script), *flags]
        straight, stopped = tmp_path / "straight", tmp_path / "stopped"
        straight.mkdir()
        stopped.mkdir()
        result = subprocess.run(command, cwd=straight, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
        assert result.returncode == 0, result.stderr[-3000:]
        run = subprocess.run(
            signal_at_line("SIGTERM", stop_after, script, *flags), cwd=stopped, env=env, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, timeout=HANG_TIMEOUT,
        )  # fmt: skip
        output = run.stdout
        assert run.returncode == 0, output[-3000:]
        assert "stopped:" in output, (
            f"the run printed no line matching {stop_after!r}, or ended without stopping:\n{output[-2000:]}"
        )
        (run_dir,) = (stopped / "runs").iterdir()
        resume_command = [*command, "--resume", f"runs/{run_dir.name}"]
        resumed = subprocess.run(resume_command, cwd=stopped, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert "stopped:" not in resumed.stdout
        (straight_dir,) = (straight / "runs").iterdir()
        assert_same_run(straight_dir, run_dir, ignore)
        return output

    return check


@pytest.fixture
def kill_check(tmp_path):
    """`check(script, flags, kill_after, before_resume=None)`: run A straight through; run B killed outright (SIGKILL, no
    clean stop) right after it prints a line matching the regex `kill_after`, with everything it logged until then on
    disk, then continued with --resume from its last periodic resume file (pass --checkpoint-every-steps in `flags`).
    Every TensorBoard scalar of B (but WALL_CLOCK_TAGS) must equal A's, step for step: what B logged after its file is
    dropped and logged again, none twice, none missing; so must every tensor of the final checkpoints (pass
    --save-model). `before_resume(run_dir)` may look at B's folder as the kill left it. Returns the resume file the
    kill left (loaded) and the resumed run's output."""

    def check(script: str, flags: list[str], kill_after: str, before_resume=None) -> tuple[dict, str]:
        env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        command = [*python(), str(ROOT / script), *flags]
        straight, killed = tmp_path / "straight", tmp_path / "killed"
        straight.mkdir()
        killed.mkdir()
        result = subprocess.run(command, cwd=straight, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
        assert result.returncode == 0, result.stderr[-3000:]
        kill = signal_at_line("SIGKILL", kill_after, script, *flags)
        run = subprocess.run(kill, cwd=killed, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
        assert run.returncode == -9, f"no line matched {kill_after!r}:\n{run.stdout[-2000:]}{run.stderr[-2000:]}"
        (run_dir,) = (killed / "runs").iterdir()
        saved = torch.load(run_dir / "resume.pt", weights_only=False)
        if before_resume is not None:
            before_resume(run_dir)
        resume_command = [*command, "--resume", f"runs/{run_dir.name}"]
        resumed = subprocess.run(resume_command, cwd=killed, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        (straight_dir,) = (straight / "runs").iterdir()
        assert_same_run(straight_dir, run_dir)
        return saved, resumed.stdout

    return check


def training_tensors(agent) -> dict[str, torch.Tensor]:
    """Every tensor of an agent's training state: its modules' parameters and buffers and its optimizers' state, by
    name. `agent` is a dataclass whose fields are modules, optimizers, nested such dataclasses, or other values."""
    import dataclasses

    found = {}
    for field in dataclasses.fields(agent):
        value = getattr(agent, field.name)
        if isinstance(value, torch.nn.Module):
            found |= {f"{field.name}.{key}": tensor for key, tensor in value.state_dict().items()}
        elif isinstance(value, torch.optim.Optimizer):
            for index, state in enumerate(value.state.values()):
                found |= {f"{field.name}.{index}.{key}": tensor for key, tensor in state.items()}
        elif dataclasses.is_dataclass(value):
            found |= {f"{field.name}.{key}": tensor for key, tensor in training_tensors(value).items()}
    return found


def check_fast_update(script, update, agent, call, optimizers, warm=20, updates=10, fast="compile") -> None:
    """The contract of a script's --fast path for one update function:

    - from the same state and random state, `updates` compiled updates (--fast compile: torch.compile of the update,
      the optimizers' own steps; or the `fast` path given) equal as many eager ones within rtol = atol = 1e-5: every
      parameter, buffer (codebooks) and optimizer moment, and every returned metric;
    - an eager update runs under NoHostSync: nothing in it makes the host wait for the device (what lets --fast
      cudagraphs capture it).

    `call(function, agent, i)` makes the i-th update of `agent` with `function` (the script's update or its compiled
    version) and returns its metrics; `optimizers(agent)` lists the optimizers the update steps. The comparison starts
    after `warm` eager updates: at Adam's first steps a parameter moves by lr * sign(gradient), so a gradient that is
    rounding noise around zero (any reordering of a sum changes it) moves by a whole learning rate either way.
    """
    import copy

    torch._dynamo.reset()  # compiled code of earlier tests holds guards on their agents
    for i in range(warm):
        call(update, agent, i)
    eager_agent, fast_agent = copy.deepcopy(agent), copy.deepcopy(agent)
    fast = script.fast_update(update, fast, optimizers(fast_agent))

    metrics = {}
    for name, function, state in (("eager", update, eager_agent), ("fast", fast, fast_agent)):
        torch.manual_seed(7)
        metrics[name] = [call(function, state, i) for i in range(warm, warm + updates)]
    eager, compiled = training_tensors(eager_agent), training_tensors(fast_agent)
    assert eager.keys() == compiled.keys() and eager
    for key in eager:
        torch.testing.assert_close(compiled[key], eager[key], rtol=1e-5, atol=1e-5, msg=lambda text, key=key: f"{key}: {text}")
    for step, (eager_metrics, fast_metrics) in enumerate(zip(metrics["eager"], metrics["fast"], strict=True)):
        for key in eager_metrics:
            message = lambda text, key=key, step=step: f"update {step}, {key}: {text}"  # noqa: E731
            torch.testing.assert_close(fast_metrics[key], eager_metrics[key], rtol=1e-5, atol=1e-5, msg=message)

    guard = NoHostSync()
    with guard:
        call(update, copy.deepcopy(agent), warm)
    assert guard.ops > 0


def record_outputs_with_grad(module: torch.nn.Module) -> tuple[list, list]:
    """(outputs, gradients), filled as `module` runs: each of its outputs that carries a gradient (detached) and, after
    the backward pass, the gradient that output received."""
    outputs, grads = [], []

    def keep(module, inputs, output):
        if output.requires_grad:
            outputs.append(output.detach())
            output.register_hook(grads.append)

    module.register_forward_hook(keep)
    return outputs, grads


# --- The two test tiers -------------------------------------------------------------------------------------------------
# `make test` runs every test not marked `full`: each script's smoke run in both modes, the maths and environment tests,
# one resume check (tests/test_skeleton.py's Ctrl-C test) and one bad-input check per script. `make test-all` (what CI
# runs) adds the tests below, marked `full` here in one place: the compiled-equals-eager tests (minutes of compilation),
# the kill tests, the exact-resume tests, the launcher's sweeps and its Slurm tests, and the other smoke variants.
FULL_TIER = {
    "compiled equals eager": (
        "equals_eager_and_is_free_of_host_syncs",
        "follows_a_decaying_learning_rate_without_recompiling",
        "fast_cudagraphs_path_computes_the_eager",
    ),
    "kill and exact resume": (
        "kill",
        "resumes_exactly",
        "resume_inside_",
        "resume_from_",
        "resume_mid_episode",
        "resume_of_a_gymnasium",
        "resume_after_",
        "resumes_to_its_end",
        "resumes_from_its_last",
        "resumes_with_the_same_factor_tests",
        "a_finished_run_resumed_with_free_flags",
        "resume_refuses_changed_flags",
    ),
    "the launcher's sweeps": (
        "test_a_local_sweep_runs",
        "test_ctrl_c_stops_a_local_sweep",
        "flag_check_leaves_what_fast_needs",
        "every_preset_dry_runs",
        "every_tool_of_benchmark_answers_help",
        "test_dry_run_prints_every_command",
        "test_bad_flags_exit_2_with_a_message_before_anything_runs[flags9",
        "[flags10",
    ),
    "other smoke variants and slow tools": (
        "test_smoke_run[AntU",
        "test_smoke_run[AntF",
        "test_smoke_run[PointMaze",
        "test_smoke_run[AntMaze_UMaze",
        "test_smoke_run_every_env_in_both_modes[AntPush",
        "test_smoke_run_every_env_in_both_modes[AntFall",
        "test_smoke_run_every_env_in_both_modes[AntGather",
        "saves_evaluates_refuses_other_settings_and_records_video",
        "test_smoke_run[baseline-finetune-video]",
        "test_smoke_run[dgrl-finetune-noise-ae]",
        "test_smoke_run_trains_evaluates_and_reloads[16-decoded]",
        "capture_video_writes_an_mp4",
        "test_the_offline_package_holds_real_mnist",
        "test_mnist.py::test_bad_flags_fail_before_any_work",
        "goal_autoencoder_round_trip_separates_cells",
        "test_factor_map.py::",
        "test_a_replay_too_large_for_memory",
        "test_float_paths_runs_one_seeded_command",
    ),
}


def pytest_collection_modifyitems(config, items):
    patterns = [pattern for group in FULL_TIER.values() for pattern in group]
    for item in items:
        if item.get_closest_marker("slurm") or any(pattern in item.nodeid for pattern in patterns):
            item.add_marker(pytest.mark.full)
