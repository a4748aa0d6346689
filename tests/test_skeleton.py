"""The seven scripts are one family: the pieces every script shares (the common Args block, the headless-rendering
default of the MuJoCo scripts, the run-management helpers) are byte-identical across them, and every script answers bad
input the same way: a clean exit with status 2 and a message naming the flag, never a traceback."""

import ast
import itertools
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
import torch
from conftest import HANG_TIMEOUT, run_many, signal_at_line

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(path.name for path in ROOT.glob("dgrl_*.py"))
MUJOCO_SCRIPTS = ["dgrl_hrac.py", "dgrl_ris.py", "dgrl_ris_sawyer.py"]
WITHOUT_VIDEO = {"dgrl_mnist.py"}  # no environment to record
SHARED_NAMES = [
    "CHECKPOINT_FORMAT, RESUME_FORMAT", "RESUME_FILE, LOCK_FILE", "FREE_FLAGS", "seed_and_device", "make_writer",
    "stop_on_signals", "Progress", "save_checkpoint", "load_checkpoint", "rng_states", "save_resume", "load_resume",
    "fast_update", "flag_text", "range_errors", "common_errors", "exit_on_errors", "hold_run_folder",  # the shared block
    "learn",  # beside the first update that steps an optimizer
    "write_video",  # beside the evaluation that records the videos
]  # fmt: skip
BLOCK_START = "# --- Run management and checks: identical in every script (tests/test_skeleton.py) "
BLOCK_END = "# --- end of the shared block "
SHARED_BLOCK_LINES = 233  # the most the shared block (run management and checks) may take, its banners included
SPEED_SWITCH_LINES = 17  # the most --fast may take: fast_update, blank lines not counted
MUJOCO_GL_DEFAULT = (
    'if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):\n    os.environ.setdefault("MUJOCO_GL", "egl")'
)


def region(lines: list[str], start: str, end: str) -> tuple[int, int]:
    """The indices of a shared region's first and last lines (its banners)."""
    first = next(i for i, line in enumerate(lines) if line.startswith(start))
    return first, next(i for i in range(first, len(lines)) if lines[i].startswith(end))


def shared_pieces(source: str) -> dict[str, str]:
    """The shared pieces of one script's source: "Args" (the common fields, from --exp-name through
    --checkpoint-every's docstring), each top-level name of the shared block (the run management and the checks), and
    learn and write_video (each beside its callers), as source text."""
    lines = source.splitlines()
    pieces = {}
    start = next(i for i in range(lines.index("class Args:"), len(lines)) if lines[i].startswith("    exp_name: str"))
    end = next(i for i in range(start, len(lines)) if lines[i].startswith("    checkpoint_every: int")) + 2
    pieces["Args"] = "\n".join(lines[start:end])
    first, last = region(lines, BLOCK_START, BLOCK_END)
    block = "\n".join(lines[first + 1 : last])
    for node in ast.parse(block).body:
        if isinstance(node, ast.Assign):
            name = ast.unparse(node.targets[0]).strip("()")
        elif isinstance(node, ast.FunctionDef | ast.ClassDef):
            name = node.name
        else:
            raise AssertionError(f"the shared block holds a {type(node).__name__}, not a definition")
        pieces[name] = ast.get_source_segment(block, node)
    for node in ast.parse(source).body:
        if isinstance(node, ast.FunctionDef) and node.name in ("learn", "write_video"):  # beside what calls them
            pieces[node.name] = ast.get_source_segment(source, node)
    return pieces


def drift(sources: dict[str, str]) -> list[str]:
    """Every difference between the scripts' shared pieces: a copy that differs from the one most scripts hold."""
    copies, problems = {}, []
    for script, source in sources.items():
        try:
            pieces = shared_pieces(source)
        except (ValueError, StopIteration) as error:
            problems.append(f"{script}: the common Args block or the shared block is missing ({error})")
            continue
        expected = {"Args", *SHARED_NAMES} - ({"write_video"} if script in WITHOUT_VIDEO else set())
        if set(pieces) != expected:
            problems.append(f"{script}: shared pieces {sorted(set(pieces) ^ expected)} missing or extra")
        for name, text in pieces.items():
            copies.setdefault(name, {})[script] = text
        has_default = MUJOCO_GL_DEFAULT in source
        if has_default != (script in MUJOCO_SCRIPTS):
            problems.append(f"{script}: the MUJOCO_GL default is {'present' if has_default else 'missing'}")
    for name, texts in copies.items():
        majority, count = Counter(texts.values()).most_common(1)[0]
        if count < len(texts) // 2 + 1:
            problems.append(f"{name}: no copy is shared by most scripts")
        differing = [script for script, text in texts.items() if text != majority]
        problems += [f"{script}: {name} differs from the other scripts' copy" for script in differing]
    return problems


def read_sources() -> dict[str, str]:
    return {script: (ROOT / script).read_text() for script in SCRIPTS}


def test_all_seven_scripts_are_checked():
    assert SCRIPTS == [
        "dgrl_amigo.py", "dgrl_goal_dqn.py", "dgrl_hrac.py", "dgrl_hrac_keychest.py", "dgrl_mnist.py", "dgrl_ris.py",
        "dgrl_ris_sawyer.py",
    ]  # fmt: skip


def test_shared_pieces_are_identical_in_every_script():
    assert drift(read_sources()) == []


@pytest.mark.parametrize("script", [*SCRIPTS, "vq.py"])
def test_no_line_of_a_script_is_longer_than_120_characters(script):
    """Read on a laptop beside the paper: every line of code, docstring and comment fits in 120 characters."""
    lines = (ROOT / script).read_text().splitlines()
    assert [number for number, line in enumerate(lines, 1) if len(line) > 120] == []


def test_the_shared_block_and_its_speed_switches_stay_short():
    """Read seven times, the shared block takes at most SHARED_BLOCK_LINES lines (one script's copy: the drift test holds
    the others to it), and --fast (fast_update) at most SPEED_SWITCH_LINES."""
    lines = (ROOT / "dgrl_ris.py").read_text().splitlines()
    first, last = region(lines, BLOCK_START, BLOCK_END)
    assert last - first + 1 <= SHARED_BLOCK_LINES
    start = next(i for i in range(first, last) if lines[i].startswith("def fast_update("))
    end = next(i for i in range(start, last) if lines[i] == "    return replayed")
    assert sum(1 for line in lines[start : end + 1] if line.strip()) <= SPEED_SWITCH_LINES


@pytest.mark.parametrize(
    "edit",
    [
        ('"""seed of the experiment"""', '"""the seed"""'),  # a docstring of the common Args block
        ('"stopped" if stopped else "done"', '"stopped" if stopped else "finished"'),  # the end-of-run line
        ("raise SystemExit(2)\n", "raise SystemExit(1)\n"),  # the exit status of a bad flag
        ("weights_only=not resume", "weights_only=False"),  # loading a checkpoint runs no code
    ],
)
def test_drift_check_fails_when_one_copy_is_edited(edit):
    sources = read_sources()
    old, new = edit
    assert old in sources["dgrl_ris.py"]
    sources["dgrl_ris.py"] = sources["dgrl_ris.py"].replace(old, new, 1)
    problems = drift(sources)
    assert problems and all(problem.startswith("dgrl_ris.py") for problem in problems), problems


def test_drift_check_fails_when_a_piece_is_missing():
    sources = read_sources()
    sources["dgrl_amigo.py"] = re.sub(r"\ndef write_video\(.*?\n\n\n", "\n", sources["dgrl_amigo.py"], flags=re.S)
    assert any("dgrl_amigo.py: shared pieces ['write_video']" in problem for problem in drift(sources))


def layout(source: str) -> dict[str, int]:
    """Where the landmarks of a script's layout are: the line of `def main`, of its training loop (main's longest
    top-level `while`/`for`), of the shared block's banner, and of `validate`, and the length of the file."""
    tree = ast.parse(source)
    functions = {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}
    main = functions["main"]
    loop = max((node for node in main.body if isinstance(node, ast.While | ast.For)), key=lambda n: n.end_lineno - n.lineno)
    banner = next(i for i, line in enumerate(source.splitlines(), 1) if line.startswith(BLOCK_START))
    return {"main": main.lineno, "loop": loop.lineno, "shared_block": banner, "validate": functions["validate"].lineno,
            "lines": len(source.splitlines())}  # fmt: skip


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_training_loop_comes_first_and_the_machinery_after(script):
    """The reader meets main and its loop in the first half of the file; the run management and validate are
    appendices after it; running the file is `main(tyro.cli(Args))` and nothing else."""
    source = (ROOT / script).read_text()
    where = layout(source)
    assert where["main"] < where["lines"] / 2 and where["loop"] < where["lines"] / 2, where
    assert where["main"] < where["shared_block"] < where["validate"], where
    last = ast.parse(source).body[-1]
    assert ast.unparse(last) == "if __name__ == '__main__':\n    main(tyro.cli(Args))"
    assert ast.unparse(ast.parse(source).body[-2]).startswith("def validate(args")


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_loops_state_is_one_dataclass_saved_and_restored_whole(script):
    """The variables the training loop carries are one `@dataclass LoopState` in the resume appendix (after main): saved
    as a plain dict of all its fields (vars or asdict, never the pickled class) and rebuilt with LoopState(**saved)."""
    source = (ROOT / script).read_text()
    tree = ast.parse(source)
    classes = {node.name: node for node in tree.body if isinstance(node, ast.ClassDef)}
    main = next(node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == "main")
    assert "LoopState" in classes and classes["LoopState"].lineno > main.end_lineno
    assert [ast.unparse(decorator) for decorator in classes["LoopState"].decorator_list] == ["dataclass"]
    in_main = ast.get_source_segment(source, main)
    builders = [  # main builds it, or calls a function of the appendix that builds a new one
        node.name
        for node in tree.body
        if isinstance(node, ast.FunctionDef) and re.search(r"LoopState\((?!\*\*)", ast.get_source_segment(source, node))
    ]
    assert "LoopState(" in in_main or any(f"{name}(" in in_main for name in builders), builders
    assert re.search(r"(copy\.deepcopy\(vars\(loop\)\)|asdict\(loop\))", source)
    assert re.search(r"LoopState\(\*\*saved\[", source)


# --- Bad input every script shares: a clean exit 2 naming the flag or file, no traceback, nothing written ---------


def assert_clean_refusal(result, *words: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for word in words:
        assert word in result.stderr, (word, result.stderr)


def damaged_resume_files() -> dict[str, bytes]:
    """An empty resume.pt (a disk that filled up) and one cut in half (a copy that did not finish)."""
    import io

    whole = io.BytesIO()
    torch.save({"script": "dgrl_mnist.py", "format": 2, "args": {}, "block": torch.zeros(10_000)}, whole)
    return {"empty": b"", "truncated": whole.getvalue()[: len(whole.getvalue()) // 2]}


@pytest.mark.parametrize("script", SCRIPTS)
def test_bad_input_every_script_shares_is_refused_before_any_work(script, tmp_path):
    """Each case in a folder of its own, run in one process (conftest.run_many), each as a user would run it:
    common bad flags, a garbage, missing, foreign or bare checkpoint, a damaged resume file (left as it is), a file where
    runs/ should be, a folder the run cannot write to, and an --exp-name that is a path. As root the batch runs without
    the capabilities that let root ignore permissions (setpriv), so that the folder's mode bits apply as to anyone."""
    prefix = ()
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("as root, this needs setpriv (util-linux) to drop the capabilities that override permissions")
        prefix = ("setpriv", "--bounding-set=-dac_override,-dac_read_search,-fowner", "--")
    other = "dgrl_amigo.py" if script != "dgrl_amigo.py" else "dgrl_mnist.py"
    cases = {
        "common flags": ["--vq-beta", "nan", "--threads", "0", "--track"],
        "garbage checkpoint": ["--checkpoint", "garbage.pt"],
        "missing checkpoint": ["--checkpoint", "missing.pt"],
        "another script's checkpoint": ["--checkpoint", "other.pt"],
        "a bare state dict": ["--checkpoint", "plain.pt"],
        "empty resume file": ["--resume", "runs/stopped_run"],
        "truncated resume file": ["--resume", "runs/stopped_run"],
        "no resume file": ["--resume", "runs/nothing"],
        "a file named runs": [],
        "a read-only folder": [],
        **{f"--exp-name {name!r}": ["--exp-name", name] for name in ("a/b", "../x", "")},
    }
    folders = {case: tmp_path / f"case{i}" for i, case in enumerate(cases)}
    for folder in folders.values():
        folder.mkdir()
    (folders["garbage checkpoint"] / "garbage.pt").write_bytes(b"not a checkpoint at all")
    torch.save({"script": other, "format": 2, "args": {}, "model": {}}, folders["another script's checkpoint"] / "other.pt")
    torch.save({"model": {"weight": torch.zeros(2)}}, folders["a bare state dict"] / "plain.pt")  # no script name
    damaged = damaged_resume_files()
    for damage in ("empty", "truncated"):
        run_dir = folders[f"{damage} resume file"] / "runs" / "stopped_run"
        run_dir.mkdir(parents=True)
        (run_dir / "resume.pt").write_bytes(damaged[damage])
    (folders["a file named runs"] / "runs").write_text("not a folder")
    folders["a read-only folder"].chmod(0o555)
    before = {case: sorted(str(path.relative_to(folder)) for path in folder.rglob("*")) for case, folder in folders.items()}
    try:
        others = [case for case in cases if case != "a read-only folder"]
        results = dict(zip(others, run_many(script, [(folders[case], cases[case]) for case in others]), strict=True))
        (results["a read-only folder"],) = run_many(script, [(folders["a read-only folder"], [])], prefix)
    finally:
        folders["a read-only folder"].chmod(0o755)

    assert_clean_refusal(
        results["common flags"], "--vq-beta must be a finite number; got nan", "--threads must be >= 1; got 0", "--track"
    )
    assert "pip install wandb" in results["common flags"].stderr
    assert_clean_refusal(results["garbage checkpoint"], "--checkpoint garbage.pt is not a checkpoint")
    assert_clean_refusal(results["missing checkpoint"], "--checkpoint missing.pt: no such file")
    needs = f"needs one that {script}"
    assert_clean_refusal(results["another script's checkpoint"], f"holds {other} format 2", needs)
    assert_clean_refusal(results["a bare state dict"], "holds None format None", needs)
    for damage in ("empty", "truncated"):
        result = results[f"{damage} resume file"]
        problem = "--resume runs/stopped_run: runs/stopped_run/resume.pt cannot be read"
        assert_clean_refusal(result, problem, "damaged or incomplete")
        assert "start the run afresh without --resume, or put back an older copy of the file" in result.stderr
        resume_file = folders[f"{damage} resume file"] / "runs" / "stopped_run" / "resume.pt"
        assert resume_file.read_bytes() == damaged[damage]  # left as it is
    assert_clean_refusal(results["no resume file"], "--resume runs/nothing: no resume.pt there")
    assert_clean_refusal(results["a file named runs"], "runs is in the way: the run writes its logs in a folder of that name")
    assert (folders["a file named runs"] / "runs").read_text() == "not a folder"
    read_only = folders["a read-only folder"]
    assert_clean_refusal(
        results["a read-only folder"], f"cannot create runs/ in {read_only} (permission denied)", "a folder you can write to"
    )
    for name in ("a/b", "../x", ""):
        assert_clean_refusal(results[f"--exp-name {name!r}"], f"--exp-name {name!r} must be a plain name, without '/'")
    after = {case: sorted(str(path.relative_to(folder)) for path in folder.rglob("*")) for case, folder in folders.items()}
    assert after == before  # nothing written, nothing removed


# --- The shared validation helpers themselves (one script's copy; the drift test covers the others) --------------------


def test_range_errors_names_the_flag_and_the_interval():
    import dgrl_mnist as script

    args = script.Args(learning_rate=0.0, batch_size=0, vq_decay=1.0, epochs=3)
    assert script.range_errors(args, "batch_size epochs", 1) == ["--batch-size must be >= 1; got 0"]
    assert script.range_errors(args, "learning_rate", 0, low_open=True) == ["--learning-rate must be > 0; got 0.0"]
    assert script.range_errors(args, "vq_decay", 0, 1, high_open=True) == ["--vq-decay must be in [0, 1); got 1.0"]
    assert script.range_errors(args, "vq_decay", 0, 1) == []
    assert script.range_errors(args, "learning_rate", 0, 1, low_open=True) == ["--learning-rate must be in (0, 1]; got 0.0"]
    assert script.range_errors(script.Args(learning_rate=float("inf")), "learning_rate", 0, 1) == []  # common_errors' job


def test_common_errors_cover_seed_threads_and_the_codebook_flags():
    import dgrl_mnist as script

    assert script.common_errors(script.Args()) == []
    bad = script.Args(seed=-1, threads=0, n_embed=0, vq_beta=-0.5, vq_dead_code_steps=-1, vq_decay=1.0, learning_rate=1e400)
    assert script.common_errors(bad) == [
        "--learning-rate must be a finite number; got inf",
        "--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got -1",
        "--threads must be >= 1; got 0",
        "--n-embed must be >= 1; got 0",
        "--vq-beta must be >= 0; got -0.5",
        "--vq-dead-code-steps must be >= 0; got -1",
        "--vq-decay must be in [0, 1); got 1.0",
    ]
    assert script.common_errors(script.Args(seed=2**64))[0].endswith("got 18446744073709551616")
    cores = os.cpu_count()
    assert script.common_errors(script.Args(threads=cores)) == []
    assert script.common_errors(script.Args(threads=10_000)) == [
        f"--threads 10000 is more than this machine's {cores} cores: use at most {cores}"
    ]


def test_flag_text_writes_booleans_as_tyro_does():
    import dgrl_mnist as script

    assert script.flag_text("n_embed", 64) == "--n-embed 64"
    assert script.flag_text("goal_channel", True) == "--goal-channel"
    assert script.flag_text("goal_channel", False) == "--no-goal-channel"


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_flag_has_a_one_line_help_text(script):
    """tyro turns each Args field's docstring into --help text; an embedded line break breaks its wrapping."""
    args_class = next(
        node for node in ast.parse((ROOT / script).read_text()).body if isinstance(node, ast.ClassDef) and node.name == "Args"
    )
    helps = {}
    for previous, node in itertools.pairwise(args_class.body):
        if isinstance(previous, ast.AnnAssign) and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            helps[previous.target.id] = node.value.value
    fields = [node.target.id for node in args_class.body if isinstance(node, ast.AnnAssign)]
    assert [field for field in fields if field not in helps] == [], "fields without a help text"
    assert {field: text for field, text in helps.items() if "\n" in text or not text.strip()} == {}


WRITER = """
import sys, torch
sys.argv = ["dgrl_mnist.py"]
import dgrl_mnist as script
args = script.Args()
for count in range(1, 10**9):
    script.save_resume("killed", {"count": count, "block": torch.full((4_000_000,), float(count))}, args)
    print(count, flush=True)
"""


def test_a_kill_during_a_resume_write_leaves_the_previous_file_whole(tmp_path):
    """SIGKILL at any moment of save_resume (here: while it rewrites a 16 MB file in a loop) leaves a resume.pt that
    loads and holds one whole state, never a torn mix of two."""
    (tmp_path / "runs" / "killed").mkdir(parents=True)
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for delay in (0.0, 0.013, 0.029, 0.047, 0.071):
        process = subprocess.Popen([sys.executable, "-c", WRITER], cwd=tmp_path, env=env, stdout=subprocess.PIPE, text=True)
        assert process.stdout.readline().strip().isdigit()  # one whole file exists from here on
        time.sleep(delay)
        process.send_signal(signal.SIGKILL)
        process.wait()
        saved = torch.load(tmp_path / "runs" / "killed" / "resume.pt", weights_only=False)
        assert saved["script"] == "dgrl_mnist.py" and saved["count"] >= 1
        assert torch.equal(saved["block"], torch.full((4_000_000,), float(saved["count"])))


# --- Ctrl-C: every script stops after its step, with its checkpoint written and its logs on disk -------------------

# For each script: a run too long to end by itself; the line at which it receives SIGINT (signal_at_line: sent as the
# line prints, so on any machine the stop comes at that step, with updates under way); its stop line; scalars its logs
# must hold by then; and the flags and output of a --checkpoint evaluation of what it saved.
AMIGO_MODEL = ["--env-id", "MiniGrid-Empty-5x5-v0", "--groups", "4", "--embed-dim", "16", "--n-embed", "8"]
RIS_MODEL = ["--env-id", "AntU", "--groups", "4", "--embed-dim", "8", "--n-embed", "8", "--hidden-dim", "16"]
RIS_MODEL += ["--max-episode-steps", "50", "--eval-episodes", "1"]
GOAL_DQN_TINY = ["--learning-starts", "100", "--rep-steps", "5", "--rep-transitions", "500", "--eval-frequency", "200"]
GOAL_DQN_TINY += ["--batch-size", "16", "--buffer-size", "1000", "--max-episode-steps", "30", "--groups", "4"]
KEYCHEST_TINY = ["--num-envs", "4", "--max-episode-steps", "100", "--adj-init-steps", "800", "--adj-init-epochs", "1"]
KEYCHEST_TINY += ["--adj-frequency", "1200", "--adj-epochs", "1", "--man-buffer-size", "200", "--eval-frequency", "400"]
KEYCHEST_TINY += ["--log-frequency", "400", "--eval-episodes", "4", "--hidden-dim", "32", "--ae-init-steps", "5"]
MNIST_TINY = ["--train-size", "1000", "--hidden-dim", "64", "--classifier-epochs", "1"]
CTRL_C = {
    "dgrl_amigo.py": dict(
        flags=[*AMIGO_MODEL, "--num-envs", "2", "--batch-envs", "2", "--num-steps", "10", "--teacher-batch-size", "4",
               "--seed", "2", "--total-timesteps", "10000000", "--progress-frequency", "100"],
        at=r"^frame +100/10000000 ", stopped=r"stopped: \d+ frames, \d+ student and \d+ teacher updates",
        tags=["charts/SPS", "charts/goal_reach_rate"],
        evaluate=[*AMIGO_MODEL, "--num-envs", "1", "--eval-episodes", "1"], evaluated=r"^1 episodes \(t\* 7 at save\)",
    ),
    "dgrl_goal_dqn.py": dict(
        flags=[*GOAL_DQN_TINY, "--total-timesteps", "1000000"],
        at=r"^step +\d+/1000000  train .* novel .* SPS", stopped=r"stopped: ",
        tags=["eval/novel_success_rate", "charts/SPS"],
        evaluate=["--groups", "4", "--max-episode-steps", "30"], evaluated=r"novel goals",
    ),
    "dgrl_hrac.py": dict(
        flags=["--total-timesteps", "100000", "--ctrl-updates", "2", "--man-updates", "1", "--batch-size", "8",
               "--eval-frequency", "500", "--eval-episodes", "1", "--hidden-dim", "32", "--groups", "0"],
        at=r"eval success", stopped=r"stopped: \d+ steps",
        tags=["eval/final_distance", "charts/episodic_return", "losses/controller_critic_loss"],
        evaluate=["--groups", "0", "--hidden-dim", "32", "--eval-episodes", "1", "--n-embed", "32"],  # no codebook in HRAC
        evaluated=r"1 evaluation episodes: success",
    ),
    "dgrl_hrac_keychest.py": dict(
        flags=[*KEYCHEST_TINY, "--total-timesteps", "10000000"],
        at=r"^frame +2000/10000000 ", stopped=r"stopped: ",  # the third evaluation: after the first updates
        tags=["eval/return", "charts/SPS"],
        evaluate=["--max-episode-steps", "100", "--hidden-dim", "32", "--eval-episodes", "2"], evaluated=r"2 episodes: return",
    ),
    "dgrl_mnist.py": dict(
        flags=[*MNIST_TINY, "--epochs", "300"],
        at=r"^image ", stopped=r"stopped: (.|\n)*no factor tests \(stopped\)",
        tags=["charts/SPS"],
        evaluate=MNIST_TINY, evaluated=r"accuracy on reconstructions",
    ),
    "dgrl_ris.py": dict(
        flags=[*RIS_MODEL, "--total-timesteps", "1000000", "--start-timesteps", "100", "--batch-size", "16",
               "--eval-frequency", "200", "--buffer-size", "5000"],
        at=r"^step +200/1000000 +eval success", stopped=r"stopped: \d+ steps, \d+ updates",
        tags=["eval/success_rate", "charts/episodic_return"],
        evaluate=RIS_MODEL, evaluated=r"1 test episodes: success \d+%, final distance [\d.]+",
    ),
    "dgrl_ris_sawyer.py": dict(
        flags=["--total-timesteps", "100000", "--start-timesteps", "100", "--batch-size", "16", "--buffer-size", "1000",
               "--eval-frequency", "150", "--eval-episodes", "1", "--groups", "4"],
        at=r"^step +150/100000 +eval success", stopped=r"stopped: \d+ steps, \d+ updates, last eval success",
        tags=["eval/success_rate", "losses/critic_loss", "vq/commit_loss"],
        evaluate=["--groups", "4", "--eval-episodes", "1"], evaluated=r"1 test episodes: success \d+%, hand success \d+%",
    ),
}  # fmt: skip


def test_ctrl_c_is_tested_for_every_script():
    assert sorted(CTRL_C) == SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_ctrl_c_stops_after_the_step_and_the_run_resumes_under_its_own_flags_only(script, run_script, tmp_path):
    """SIGINT while training: exit status 0 with the stop line, no traceback; the checkpoint of the run (this script's)
    is written and names its path; the scalars logged by then are on disk; --checkpoint evaluates it. --resume with a
    flag the run must keep changed (--seed) exits 2 naming it and leaves the resume file as it was; with free flags
    changed (--threads, --checkpoint-every) the run continues (stopped again at once, at its first line)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    case = CTRL_C[script]
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    command = signal_at_line("SIGINT", case["at"], script, *case["flags"], "--save-model")
    run = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stdout[-2000:] + run.stderr[-3000:]
    assert re.search(case["stopped"], run.stdout), run.stdout[-3000:]
    (checkpoint,) = tmp_path.glob(f"runs/*/{script[:-3]}.cleanrl_model")
    assert f"checkpoint: {checkpoint.relative_to(tmp_path)}" in run.stdout, run.stdout[-2000:]
    assert torch.load(checkpoint, weights_only=True)["script"] == script
    events = EventAccumulator(str(checkpoint.parent), size_guidance={"scalars": 0})
    events.Reload()
    assert set(case["tags"]) <= set(events.Tags()["scalars"]), events.Tags()["scalars"]
    evaluation = run_script(script, *case["evaluate"], "--checkpoint", str(checkpoint))
    assert evaluation.returncode == 0, evaluation.stderr[-3000:]
    assert re.search(case["evaluated"], evaluation.stdout, re.M), evaluation.stdout[-2000:]

    resume = ["--resume", f"runs/{checkpoint.parent.name}"]
    resume_file = checkpoint.parent / "resume.pt"
    saved = resume_file.read_bytes()
    (refused,) = run_many(script, [(tmp_path, [*case["flags"], "--save-model", "--seed", "99", *resume])])
    assert_clean_refusal(refused, f"--resume runs/{checkpoint.parent.name} was started with other settings: pass --seed ")
    assert resume_file.read_bytes() == saved
    free = ["--threads", "2", "--checkpoint-every", "0"]
    first_line = f"^{re.escape(checkpoint.parent.name)}: "
    command = signal_at_line("SIGINT", first_line, script, *case["flags"], "--save-model", *free, *resume)
    resumed = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert resumed.returncode == 0 and re.search(case["stopped"], resumed.stdout), resumed.stdout[-2000:] + resumed.stderr


# --- One writer per run folder ------------------------------------------------------------------------------------------


def folder_snapshot(folder: Path) -> dict:
    return {path.name: (path.read_bytes(), path.stat().st_mtime_ns) for path in sorted(folder.iterdir())}


def test_a_second_process_on_a_run_folder_is_refused_by_every_script_without_touching_it(tmp_path):
    """While another process holds runs/NAME (its lock file taken, as a live run holds it), `--resume runs/NAME` exits 2
    in every script, naming the holder's pid and host, before reading or writing anything there (the resume file here
    is not even a torch file: reading it would fail otherwise)."""
    import fcntl

    folder = tmp_path / "runs" / "held_run"
    folder.mkdir(parents=True)
    (folder / "resume.pt").write_bytes(b"not read")
    lock = open(folder / "run.lock", "a+")
    fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    lock.write("pid 4242 on elsewhere-host\n")
    lock.flush()
    before = folder_snapshot(folder)
    for script in SCRIPTS:
        (refused,) = run_many(script, [(tmp_path, [*CTRL_C[script]["flags"], "--resume", "runs/held_run"])])
        assert refused.returncode == 2 and "Traceback" not in refused.stderr, (script, refused.stderr[-2000:])
        assert "runs/held_run is in use by pid 4242 on elsewhere-host" in refused.stderr, (script, refused.stderr)
        assert folder_snapshot(folder) == before, script
    lock.close()


def test_a_running_run_holds_its_folder_and_a_sigkill_frees_it_at_once(tmp_path):
    """A goal-DQN run holds its folder while it trains: a second `--resume` of it is refused, naming the run's pid. Once
    the run is SIGKILLed (no handler runs), the lock is free as soon as the process is gone, and --resume proceeds."""
    sys.path.insert(0, str(ROOT / "benchmark"))
    import protocol

    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    flags = CTRL_C["dgrl_goal_dqn.py"]["flags"]
    command = [sys.executable, str(ROOT / "tests" / "signal_at_line.py"), "hold", CTRL_C["dgrl_goal_dqn.py"]["at"]]
    held = subprocess.Popen([*command, str(ROOT / "dgrl_goal_dqn.py"), *flags], cwd=tmp_path, env=env, stdout=subprocess.PIPE)
    for line in held.stdout:  # the run waits at this line (its DQN phase has written resume.pt) until a signal comes
        if re.search(CTRL_C["dgrl_goal_dqn.py"]["at"], line.decode()):
            break
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert protocol.lock_holder(run_dir) == f"pid {held.pid} on {os.uname().nodename}"
    (refused,) = run_many("dgrl_goal_dqn.py", [(tmp_path, [*flags, "--resume", f"runs/{run_dir.name}"])])
    assert refused.returncode == 2 and f"is in use by pid {held.pid} on " in refused.stderr, refused.stderr[-2000:]
    held.kill()
    held.wait()
    assert protocol.lock_holder(run_dir) is None
    stopped = subprocess.run(
        signal_at_line("SIGINT", "resumed at DQN step", "dgrl_goal_dqn.py", *flags, "--resume", f"runs/{run_dir.name}"),
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert stopped.returncode == 0 and "stopped: " in stopped.stdout, stopped.stdout[-2000:] + stopped.stderr[-2000:]


# --- Progress: the time left stays current, the step-based resume trigger ----------------------------------------------


class FakeClock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_the_heartbeat_gives_the_time_left_at_its_own_recent_rate(monkeypatch, capsys):
    """A fast start (100 steps/s) then a slow phase (1 step/s): the line at the fast rate says 9s left; the heartbeat a
    minute into the slow phase says what is left at the slow rate, not the line's figure or the whole run's mean."""
    import dgrl_mnist as script

    clock = FakeClock()
    monkeypatch.setattr(script.time, "time", clock)
    progress = script.Progress(1000, unit="step")
    clock.now += 1
    progress.line(100, "loss 1.0")
    clock.now += 30
    progress.line(130, heartbeat=True)  # not yet: half a minute of silence
    clock.now += 31
    progress.line(161, heartbeat=True)
    clock.now += 61
    progress.line(222, heartbeat=True)
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        "step       100/1000  loss 1.0  SPS 100  1s elapsed, 9s left",
        "step       161/1000    SPS 2  62s elapsed, 839s left (running)",
        "step       222/1000    SPS 1  123s elapsed, 778s left (running)",
    ]


def test_resume_due_at_each_multiple_of_the_steps_and_of_the_seconds(monkeypatch):
    import dgrl_mnist as script

    clock = FakeClock()
    monkeypatch.setattr(script.time, "time", clock)
    by_steps = script.Progress(1000, start_step=30)  # a resumed run: the count starts at 30
    assert [step for step in (50, 99, 100, 150, 230, 299, 300, 301) if by_steps.resume_due(step, 0, 100)] == [100, 230, 300]
    by_clock = script.Progress(1000)
    due = []
    for step in range(1, 8):
        clock.now += 25
        due += [step] if by_clock.resume_due(step, 60, 0) else []
    assert due == [3, 6]  # 75 s, then 150 s
    assert not any(script.Progress(1000).resume_due(step, 0, 0) for step in range(1, 500))


@pytest.mark.parametrize("script", SCRIPTS)
def test_files_written_before_a_flag_existed_are_refused(script, tmp_path, capsys):
    """A resume.pt or checkpoint whose saved flags lack one the script has now (a flag added since) cannot say which
    value its run had: continuing or evaluating it with today's default could silently change the run, so it is
    refused, naming the flag."""
    sys.path.insert(0, str(ROOT))
    module = __import__(script[:-3])
    args = module.Args()
    saved_args = dict(vars(args))
    del saved_args["seed"]  # every script has it and it is never a free flag
    run_dir = tmp_path / "runs" / "old_run"
    run_dir.mkdir(parents=True)
    torch.save({"script": script, "format": module.RESUME_FORMAT, "args": saved_args}, run_dir / module.RESUME_FILE)
    args.resume = str(run_dir)
    with pytest.raises(SystemExit) as stopped:
        module.load_resume(args)
    assert stopped.value.code == 2
    assert f"--resume {run_dir} was started before --seed existed" in capsys.readouterr().err
    checkpoint_args = dict(vars(module.Args()))
    dropped = module.MUST_MATCH[0]
    del checkpoint_args[dropped]
    torch.save({"script": script, "format": module.CHECKPOINT_FORMAT, "args": checkpoint_args}, tmp_path / "old.cleanrl_model")
    with pytest.raises(SystemExit) as stopped:
        module.load_checkpoint(str(tmp_path / "old.cleanrl_model"), module.Args(), module.MUST_MATCH, torch.device("cpu"))
    assert stopped.value.code == 2
    flag = "--" + dropped.replace("_", "-")
    assert f"old.cleanrl_model was written before {flag} existed; use its version" in capsys.readouterr().err


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_resume_file_of_an_older_layout_is_refused(script, tmp_path, capsys):
    """A resume.pt of an older layout (format 2, before HRAC's env state held its success flag; 1, before the loop's
    variables became one LoopState) cannot be restored by this version: refused, saying to continue it with the version
    that started it, not a traceback halfway into setup. A checkpoint of layout 1 is refused the same way."""
    sys.path.insert(0, str(ROOT))
    module = __import__(script[:-3])
    assert module.RESUME_FORMAT == 3 and module.CHECKPOINT_FORMAT == 2
    run_dir = tmp_path / "runs" / "old_run"
    run_dir.mkdir(parents=True)
    for old in (1, 2):
        torch.save({"script": script, "format": old, "args": dict(vars(module.Args()))}, run_dir / module.RESUME_FILE)
        args = module.Args(resume=str(run_dir))
        with pytest.raises(SystemExit) as stopped:
            module.load_resume(args)
        assert stopped.value.code == 2
        wanted = f"--resume {run_dir} holds {script} format {old}: continue it with the version that started it"
        assert wanted in capsys.readouterr().err
    # a checkpoint of layout 1: before AMIGo's --goal-channel became auto/on/off (its boolean matches no value now)
    old_checkpoint = str(tmp_path / "old.cleanrl_model")
    torch.save({"script": script, "format": 1, "args": dict(vars(module.Args()))}, old_checkpoint)
    with pytest.raises(SystemExit) as stopped:
        module.load_checkpoint(old_checkpoint, module.Args(), module.MUST_MATCH, torch.device("cpu"))
    assert stopped.value.code == 2
    wanted = f"--checkpoint {old_checkpoint} holds {script} format 1; it needs one that {script} (format 2) wrote"
    assert wanted in capsys.readouterr().err


@pytest.mark.parametrize("script", SCRIPTS)
def test_fast_cudagraphs_is_torch_compiles_reduce_overhead_mode_with_capturable_optimizers(script, monkeypatch):
    """--fast cudagraphs, checked without a GPU (torch.compile stood in for): the update goes to torch.compile in its
    "reduce-overhead" mode (inductor's CUDA graphs), each optimizer becomes capturable with its state kept (a resumed
    one's too), and each call starts a new step for the graphs and returns copies of the compiled call's tensors (a replay
    reuses their memory). --fast compile is torch.compile's default mode; eager is the update itself."""
    sys.path.insert(0, str(ROOT))
    module = __import__(script[:-3])
    modes, steps = [], []
    outputs = {"loss": torch.tensor(1.5), "codes": [torch.arange(3)], "count": 4}

    def fake_compile(function, mode=None):
        modes.append(mode)
        return lambda *args, **kwargs: outputs

    monkeypatch.setattr(torch, "compile", fake_compile)
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: steps.append(len(steps)))
    layer = torch.nn.Linear(2, 1)
    optimizer = torch.optim.Adam(layer.parameters(), lr=0.1)
    layer(torch.ones(1, 2)).sum().backward()
    optimizer.step()  # a state to keep, as a resumed run's optimizer has
    moment = optimizer.state[layer.weight]["exp_avg"].clone()
    update = module.fast_update(lambda: None, "cudagraphs", [optimizer])
    assert modes == ["reduce-overhead"] and all(group["capturable"] for group in optimizer.param_groups)
    assert torch.equal(optimizer.state[layer.weight]["exp_avg"], moment)
    for call in range(2):
        returned = update()
        assert steps == list(range(call + 1)) and returned["count"] == 4
        assert torch.equal(returned["loss"], outputs["loss"]) and returned["loss"] is not outputs["loss"]
        assert returned["codes"][0].data_ptr() != outputs["codes"][0].data_ptr()
    module.fast_update(lambda: None, "compile", [optimizer])
    assert modes == ["reduce-overhead", None]
    plain = lambda: None  # noqa: E731
    assert module.fast_update(plain, "eager", [optimizer]) is plain and len(modes) == 2
