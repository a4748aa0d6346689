"""One launcher for every study: a grid of runs of one script (or a named preset), on this machine or on a Slurm cluster.

    python benchmark/launch.py --list-presets                      # every preset (each study of docs/, each paper figure)
    python benchmark/launch.py --preset mnist                      # a study of docs/, two runs at a time
    python benchmark/launch.py --preset mnist --seeds 4 5 6        # the same study, other seeds (a preset's axes change)
    python benchmark/launch.py --script dgrl_ris.py --env-ids AntU AntMaze --groups 0 16 -- --total-timesteps 40000
                                                                   # any grid; the flags after a bare -- go to every run
    python benchmark/launch.py --preset hrac-paper --backend slurm --partition gpu --gpus-per-task 1 --runs-per-task 4
                                                                   # the paper's HRAC grid as one Slurm job array

A sweep is a product: for each arm (a script, env ids, groups, seeds and extra flags) every combination is one run. Each
run gets its own folder, `sweeps/{name}/{run_id}/`, and runs there: its log (`log.txt`), its state (`status.json`) and
the script's own `runs/{run_name}/` (TensorBoard, `resume.pt`, checkpoints) stay together. When every run is done, the
preset's plots (curves and a table per study, by benchmark/plot.py) are written to `sweeps/{name}/`.

Backends:
- local (the default): `--workers` runs at a time, one thread each (`--threads`), a table of the runs (state, step,
  latest figures, SPS, time left) every `--table-every` seconds, a failed run reported with its exit code and the tail
  of its log, and exit status 1 when any run failed. Ctrl-C stops every run cleanly (each writes its resume file).
- slurm: one job array per sweep through submitit (`--partition`, `--time-min`, `--cpus-per-task`, `--gpus-per-task`,
  `--runs-per-task` runs packed in one task, `--array-parallelism`, `--sbatch KEY=VALUE` passed through, `--setup`
  shell lines). Before a time limit or on preemption, Slurm signals the job: each run stops after its current step
  with its resume file written, and the job requeues itself and continues the runs with the scripts' `--resume`
  (exactly: same curves as an uninterrupted run). Waiting on the jobs needs Slurm accounting (sacct): without it, a
  job killed before it wrote its result could never be told from a running one.

Relaunching a sweep is safe: finished runs are skipped, unfinished ones resume from their resume file, runs that
failed are reported again (or run again with `--retry`).
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

ROOT = Path(__file__).resolve().parents[1]
STATUS_FILE = "status.json"
LOG_FILE = "log.txt"
RESUME_FILE = "resume.pt"  # what the scripts write in runs/{run_name}/ (their RESUME_FILE)
DEFAULT_TAIL = 25  # log lines shown for a failed run


# --- Sweeps: arms, presets, runs ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Arm:
    """One product of lists: every (env id, groups, seed) of one script, with the same extra flags."""

    script: str
    env_ids: tuple[str, ...] = ()  # empty: the script's default env (no --env-id flag)
    groups: tuple[int, ...] = (0, 16)
    seeds: tuple[int, ...] = (1, 2, 3)
    flags: str = ""  # extra flags for every run, as typed on a command line
    tag: str = ""  # tells apart the run ids of arms of one script and env with other flags (e.g. K8)


@dataclass(frozen=True)
class Plot:
    """One figure and table of benchmark/plot.py over the sweep's runs: `sweeps/{name}/{out}.png` and `.md`."""

    out: str
    tags: tuple[str, ...]
    title: str = ""
    match: str = ""  # regular expression on the run folder's name (runs/{run_name})
    panel_by: str = ""
    bins: int = 0


@dataclass(frozen=True)
class Preset:
    description: str  # one line: what it runs and what it takes
    arms: tuple[Arm, ...]
    plots: tuple[Plot, ...] = ()
    workers: int = 2  # local runs at a time by default
    note: str = ""  # printed after the table: what the study can and cannot show


def _ris(
    env: str, steps: int, batch: int, start: int, every: int, episodes: int, groups=(0, 16), seeds=(1, 2, 3), extra: str = ""
) -> Arm:
    flags = f"--total-timesteps {steps} --batch-size {batch} --start-timesteps {start} --eval-frequency {every}"
    flags = f"{flags} --eval-episodes {episodes} {extra}".strip()
    return Arm("dgrl_ris.py", (env,), groups, seeds, f"{flags} --save-model", "")


RIS_SNIPPET_SUM = "--vq-loss-reduction sum"  # the CPU studies of docs/dgrl_ris.md ran with the snippet's sum of the losses


def _amigo(
    env: str,
    frames: int,
    groups: tuple[int, ...],
    out: str,
    source: str,
    what: str,
    extra: str = "",
    bins: int = 20,
    workers: int = 2,
) -> Preset:
    """An AMIGo study: AMIGo (G0) against AMIGo+DGRL on one MiniGrid env, 3 seeds, its curves binned over frames."""
    dgrl = ", ".join(f"G{g}" for g in groups if g)
    return Preset(
        f"{source}: AMIGo vs AMIGo+DGRL ({dgrl}) on {env}, {what}, 3 seeds",
        (Arm("dgrl_amigo.py", (env,), groups, (1, 2, 3), f"--total-timesteps {frames} {AMIGO_FLAGS} {extra}".strip()),),
        (Plot(out, AMIGO_TAGS, f"{env}: AMIGo vs AMIGo+DGRL, {what}", bins=bins),),
        workers=workers,
    )


QUICK_NOTE = """\
What this shows. The paper's claim (section 5): with discrete factorial codes for state and goal (DGRL, here G = 16),
a goal-conditioned DQN generalises better to goals it never trained on than the same agent on continuous embeddings
(G0). Read the novel-goal columns. Each agent here has only 2 seeds and 4 novel goals, so one goal is 25 points of a
seed's novel success and the two seeds often disagree: the final values can put either agent ahead, and a gap this
small is not evidence either way. The averages over all evaluations ("avg") say which agent got there sooner. In the
full study (3 seeds), with 8 training goals both agents ended level on the novel goals and DGRL (G = 8 or 16) was
faster on the way. With 5 seeds, the same setting as here (8 training goals) gave G = 16 a significant lead on the
way (mean novel success over the evaluations 0.61 against 0.46, exact permutation p = 0.04) and both agents level at
the end; with 16 training goals no DGRL gain; G = 4 did worse than the baseline. These are short CPU-sized runs,
not the paper's budget. Full study, curves and tables: docs/dgrl_goal_dqn.md#results; every claim: docs/claims.md"""

GOAL_DQN_ARMS = tuple(
    Arm("dgrl_goal_dqn.py", (env,), (0, 4, 8, 16), (1, 2, 3, 4, 5), f"--n-train-goals {k}", f"K{k}")
    for env, k in (("LoopWorld", 4), ("LoopWorld", 8), ("SpiralWorld", 8), ("SpiralWorld", 16))
)
MNIST_TAGS = tuple(
    f"factor/{name}"
    for name in (
        "factor1/digit_acc factor1/colour_acc factor2/digit_acc factor2/colour_acc swap/shape1_colour2 swap/colour1_shape2 "
        "both/digit_acc both/colour_acc test/reconstruction_mse real/digit_acc"
    ).split()
)
AMIGO_TAGS = ("charts/episodic_return", "charts/success_rate", "charts/goal_reach_rate", "teacher/t_star")
AMIGO_FLAGS = "--progress-frequency 50000 --save-model"
RIS_TAGS = ("eval/success_rate", "eval/final_distance", "charts/success_rate", "charts/subgoal_distance")
HRAC_TAGS = ("eval/final_distance", "eval/success_rate", "charts/final_distance", "charts/subgoal_distance")
KEYCHEST_TAGS = ("eval/return", "eval/return_random_subgoals", "eval/subgoal_reach_rate", "eval/subgoal_distance")
KEYCHEST_VQ_TAGS = ("vq/perplexity", "vq/active_codes", "losses/goal_reconstruction", "vq/distinct_cells")
SAWYER_TAGS = ("eval/hand_success_rate", "eval/success_rate", "eval/final_hand_distance", "eval/final_puck_distance")
SAWYER_CPU = "--batch-size 32 --start-timesteps 2000 --eval-frequency 2000 --eval-episodes 10 --save-model"
HIRO_ENVS = ("AntMazeSparse", "AntPush", "AntFall", "AntMaze", "AntGather")

SMOKE_GOAL_DQN = (
    "--total-timesteps 3000 --rep-steps 150 --rep-batch-size 16 --rep-transitions 500 --learning-starts 20 "
    "--eval-frequency 500 --batch-size 16 --buffer-size 1000 --max-episode-steps 50 --save-model"
)
SMOKE_MNIST = "--epochs 1 --train-size 1000 --classifier-epochs 1 --n-swap-pairs 200 --hidden-dim 64 --save-model"

PRESETS: dict[str, Preset] = {
    # The smallest sweep of two scripts (seconds a run): try a machine or a cluster setup before a long study.
    "smoke": Preset(
        "goal-DQN (G0, G4) and Color-MNIST (G2) at tiny budgets, 2 seeds (6 runs of seconds): checks a setup",
        (
            Arm("dgrl_goal_dqn.py", ("SpiralWorld",), (0, 4), (1, 2), SMOKE_GOAL_DQN),
            Arm("dgrl_mnist.py", (), (2,), (1, 2), SMOKE_MNIST),
        ),
        (Plot("smoke_goal_dqn", ("eval/train_success_rate", "eval/novel_success_rate"), "goal-DQN, tiny budget", "^Spiral"),),
    ),
    # The README's main job and the CPU-sized studies of docs/ (each figure and table there comes from one of these).
    "quick": Preset(
        "goal-DQN vs DGRL (G16) on SpiralWorld, 8 training goals and 4 novel ones, 2 seeds (a few minutes on 2 cores)",
        (Arm("dgrl_goal_dqn.py", ("SpiralWorld",), (0, 16), (1, 2), "--n-train-goals 8", "K8"),),
        (
            Plot(
                "quick_spiralworld",
                ("eval/train_success_rate", "eval/novel_success_rate", "eval/novel_total_steps"),
                "SpiralWorld, 8 training goals, 4 novel goals: goal-DQN (G0) vs DGRL (G16)",
            ),
        ),
        note=QUICK_NOTE,
    ),
    "goal-dqn": Preset(
        "docs/dgrl_goal_dqn.md: LoopWorld K = 4, 8 and SpiralWorld K = 8, 16; G in {0, 4, 8, 16}; 5 seeds (80 runs)",
        GOAL_DQN_ARMS,
        (
            Plot(
                "goal_dqn_loopworld",
                ("eval/train_success_rate", "eval/train_total_steps"),
                "LoopWorld: greedy success and total steps on the K training goals",
                "^LoopWorld",
                r"^(LoopWorld__K\d+)",
            ),
            Plot(
                "goal_dqn_spiralworld",
                ("eval/novel_success_rate", "eval/novel_total_steps", "eval/train_success_rate"),
                "SpiralWorld: 4 novel goals after training on K goals",
                "^SpiralWorld",
                r"^(SpiralWorld__K\d+)",
            ),
            Plot(
                "goal_dqn_bonus_and_speed",
                ("charts/bonus_distance_corr", "charts/bonus_step_closer", "charts/SPS"),
                "Bonus quality after pre-training, and env steps/s",
                "",
                r"^([A-Za-z]+World__K\d+)",
            ),
        ),
    ),
    "mnist": Preset(
        "docs/dgrl_mnist.md: Color-MNIST, DGRL (G2) and the continuous autoencoder (G0), 3 seeds (6 runs)",
        (Arm("dgrl_mnist.py", (), (2, 0), (1, 2, 3)),),
        (Plot("mnist_factors", MNIST_TAGS, "Color-MNIST: decoding and swapping the factors"),),
    ),
    "keychest": Preset(
        "docs/dgrl_hrac_keychest.md: Key-Chest as the paper wires it, HRAC (G0) and DGRL G = 4, 16, 5 seeds at 2M frames",
        (Arm("dgrl_hrac_keychest.py", (), (0, 4, 16), (1, 2, 3, 4, 5), "--total-timesteps 2000000 --save-model"),),
        (
            Plot(
                "hrac_keychest",
                (*KEYCHEST_TAGS, "charts/adjacency_accuracy"),
                "Key-Chest: HRAC (G0) vs HRAC+DGRL (G4, G16), 2M frames",
                bins=20,
            ),
            Plot("hrac_keychest_codebook", KEYCHEST_VQ_TAGS, "Key-Chest: DGRL's codebook, 2M frames", r"__G[1-9]", bins=20),
        ),
    ),
    "keychest-decoded": Preset(
        "docs/dgrl_hrac_keychest.md: Key-Chest, our decoded-subgoal variant and HRAC's box reach rule, HRAC (G0) and "
        "DGRL G = 4, 8, 16, 5 seeds at 2M frames",
        (
            Arm(
                "dgrl_hrac_keychest.py",
                (),
                (0, 4, 8, 16),
                (1, 2, 3, 4, 5),
                "--total-timesteps 2000000 --save-model --dgrl-goal decoded --reach-rule box",
            ),
        ),
        (
            Plot(
                "hrac_keychest_decoded",
                (*KEYCHEST_TAGS, "charts/adjacency_accuracy"),
                "Key-Chest, decoded subgoals, box reach rule: HRAC (G0) vs HRAC+DGRL (G4, G8, G16), 2M frames",
                bins=20,
            ),
            Plot(
                "hrac_keychest_decoded_codebook",
                KEYCHEST_VQ_TAGS,
                "Key-Chest, decoded subgoals: DGRL's codebook, 2M frames",
                r"__G[1-9]",
                bins=20,
            ),
        ),
    ),
    "ris-pointmaze": Preset(
        "docs/dgrl_ris.md's CPU preset: RIS vs RIS+DGRL (G16) on PointMaze_UMaze-v3, 30,000 steps, batch 128, 3 seeds",
        (_ris("PointMaze_UMaze-v3", 30_000, 128, 2_000, 2_000, 10, extra=RIS_SNIPPET_SUM),),
        (Plot("ris_pointmaze_cpu", RIS_TAGS, "PointMaze_UMaze-v3: RIS vs RIS+DGRL, 30,000 steps, batch 128", bins=15),),
    ),
    "ris-antu-cpu": Preset(
        "docs/dgrl_ris.md: AntU on a CPU, RIS vs RIS+DGRL (G16), 40,000 steps, batch 256, 1 seed",
        (_ris("AntU", 40_000, 256, 10_000, 5_000, 10, seeds=(1,), extra=RIS_SNIPPET_SUM),),
        (Plot("ris_antu_cpu", RIS_TAGS, "AntU: RIS vs RIS+DGRL, 40,000 steps, batch 256", bins=15),),
    ),
    "hrac-antmaze-cpu": Preset(
        "docs/dgrl_hrac.md: HRAC vs HRAC+DGRL (G16) on AntMaze, 300,000 of the paper's 5M steps, 1 seed",
        (Arm("dgrl_hrac.py", ("AntMaze",), (0, 16), (1,), "--total-timesteps 300000 --save-model"),),
        (Plot("hrac_antmaze_cpu", (*HRAC_TAGS, "charts/controller_reward"), "AntMaze: HRAC vs HRAC+DGRL, 300k steps"),),
    ),
    "sawyer-cpu": Preset(
        "docs/dgrl_ris_sawyer.md's CPU preset: RIS vs RIS+DGRL (G16) from pixels, 30,000 steps, batch 32, 2 seeds",
        (Arm("dgrl_ris_sawyer.py", (), (0, 16), (1, 2), f"--total-timesteps 30000 {SAWYER_CPU}"),),
        (Plot("ris_sawyer_cpu", (*SAWYER_TAGS, "losses/q_values"), "Sawyer push-and-reach from pixels, 30,000 steps"),),
    ),
    # The CPU studies of docs/dgrl_amigo.md ran with the goal channel in both modes (--goal-channel on), or without it in
    # both (off); the script's default, the paper's wiring, keeps it for AMIGo only (amigo-paper).
    "amigo-doorkey": _amigo(
        "MiniGrid-DoorKey-5x5-v0",
        1_000_000,
        (0, 8, 16),
        "amigo_doorkey_cpu",
        "docs/dgrl_amigo.md",
        "1M frames, the goal channel in both modes (--goal-channel on)",
        "--goal-channel on",
    ),
    "amigo-s3r1": _amigo(
        "MiniGrid-KeyCorridorS3R1-v0",
        1_000_000,
        (0, 8, 16),
        "amigo_s3r1_cpu",
        "docs/dgrl_amigo.md",
        "1M frames, the goal channel in both modes (--goal-channel on)",
        "--goal-channel on",
    ),
    "amigo-s3r1-3m": _amigo(
        "MiniGrid-KeyCorridorS3R1-v0",
        3_000_000,
        (0, 16),
        "amigo_s3r1_3m",
        "docs/dgrl_amigo.md",
        "3M frames, the goal channel in both modes (--goal-channel on)",
        "--goal-channel on",
    ),
    "amigo-nochannel": _amigo(
        "MiniGrid-DoorKey-5x5-v0",
        1_000_000,
        (0, 16),
        "amigo_doorkey_nochannel",
        "docs/dgrl_amigo.md",
        "1M frames, the goal only through the encoder in both modes (--goal-channel off)",
        "--goal-channel off",
    ),
    # The paper's figures at the paper's budgets: GPU jobs, for a cluster (`--backend slurm`) or a big machine.
    "amigo-paper": _amigo(
        "MiniGrid-KeyCorridorS3R3-v0",
        30_000_000,
        (0, 8, 16),
        "amigo_kcmedium",
        "the paper's AMIGo figure",
        "KCmedium, 3e7 frames, the paper's wiring (the goal channel for AMIGo only)",
        bins=30,
        workers=1,
    ),
    "hrac-paper": Preset(
        "the paper's HRAC Ant figures (main text and appendix): HRAC vs HRAC+DGRL on the five HIRO Ant envs, "
        "G in {0, 2, 4, 8, 16, 32}, 5M steps, 3 seeds (90 runs)",
        (Arm("dgrl_hrac.py", HIRO_ENVS, (0, 2, 4, 8, 16, 32), (1, 2, 3), "--total-timesteps 5000000 --save-model"),),
        tuple(Plot(f"hrac_{env}", HRAC_TAGS, f"{env}: HRAC vs HRAC+DGRL, 5M steps", f"^{env}__") for env in HIRO_ENVS),
        workers=1,
    ),
    "ris-paper": Preset(
        "the paper's RIS Ant figures (main text and appendix): RIS vs RIS+DGRL (G 4, 8, 16) on AntU and AntMaze, "
        "5M steps at batch 2048, 3 seeds",
        tuple(_ris(env, 5_000_000, 2048, 10_000, 1_000, 5, (0, 4, 8, 16)) for env in ("AntU", "AntMaze")),
        tuple(
            Plot(f"ris_{env}", RIS_TAGS[:2], f"{env}: RIS vs RIS+DGRL, 5M steps", f"^{env}__", bins=50)
            for env in ("AntU", "AntMaze")
        ),
        workers=1,
    ),
    "sawyer-paper": Preset(
        "the paper's Sawyer figures (main text and appendix): RIS vs RIS+DGRL (G 4, 8, 16) from pixels on Sawyer "
        "push-and-reach, 1M steps, 3 seeds",
        (
            Arm(
                "dgrl_ris_sawyer.py",
                (),
                (0, 4, 8, 16),
                (1, 2, 3),
                "--total-timesteps 1000000 --eval-frequency 5000 --save-model",
            ),
        ),
        (Plot("ris_sawyer", SAWYER_TAGS, "Sawyer push-and-reach from pixels, 1M steps", bins=50),),
        workers=1,
    ),
}


@dataclass
class Run:
    """One run of a sweep: `python {script} {argv}`, run in `folder` (which holds its log, status and runs/)."""

    run_id: str
    script: str
    argv: list[str]
    folder: Path

    def run_dir(self) -> Path | None:
        """The script's runs/{run_name} folder, once the run has made it."""
        made = sorted((self.folder / "runs").glob("*/")) if (self.folder / "runs").is_dir() else []
        return made[-1] if made else None

    def status(self) -> dict:
        try:
            return json.loads((self.folder / STATUS_FILE).read_text())
        except (OSError, ValueError):
            return {}


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.=+-]+", "-", text).strip("-")


def expand(arms: tuple[Arm, ...], name: str, sweep_dir: Path, threads: int) -> list[Run]:
    """Every run of the arms, in order (seed outermost, so that an early stop leaves whole seeds). A run is named
    `{script}__{env}__{tag}__G{groups}__s{seed}` (the parts it has); its --exp-name is the sweep's name (the plots
    group runs by the script's run name, which holds the env, groups, the exp name and what else the script puts
    there, such as goal-DQN's K)."""
    runs, seen = [], {}
    for arm in arms:
        flags = shlex.split(arm.flags)
        for seed in arm.seeds:
            for env in arm.env_ids or (None,):
                for groups in arm.groups:
                    argv = ([] if env is None else ["--env-id", env]) + ["--groups", str(groups), "--seed", str(seed)]
                    argv += [*flags, "--exp-name", name, "--threads", str(threads)]
                    parts = [Path(arm.script).stem.removeprefix("dgrl_"), env or "", arm.tag, f"G{groups}", f"s{seed}"]
                    run_id = "__".join(part for part in parts if part)
                    if run_id in seen:
                        if seen[run_id] != (arm.script, argv):
                            raise ValueError(f"two arms make run {run_id} with other flags: give them tags")
                        continue
                    seen[run_id] = (arm.script, argv)
                    runs.append(Run(run_id, arm.script, argv, sweep_dir / run_id))
    return runs


# --- One run: start it (resuming if it can), watch it, record how it ended ----------------------------------------------

PROGRESS = re.compile(
    r"^\S+\s+(\d+)/(\d+)\s+(.*?)\s+SPS (\d+)\s+(?:\d+s elapsed, (?:(\d+)s left|time left unknown)|\(running\))"
)


@dataclass
class Attempt:
    run: Run
    process: subprocess.Popen
    log_start: int  # byte offset of this attempt in log.txt
    started: float
    signalled: bool = False


def command_of(run: Run, python: str) -> list[str]:
    """The run's command line, with `--resume runs/{run_name}` when an earlier attempt left a resume file."""
    command = [python, str(ROOT / run.script), *run.argv]
    run_dir = run.run_dir()
    if run_dir is not None and (run_dir / RESUME_FILE).is_file():
        command += ["--resume", f"runs/{run_dir.name}"]
    return command


STOPPED_BY = (-signal.SIGTERM, -signal.SIGUSR1)  # the launcher's stop signals, as exit statuses of an unhandled one


def start(run: Run, python: str, threads: int) -> Attempt:
    """Start the run in its folder, its output appended to log.txt. A run with no resume file starts afresh: whatever
    an earlier attempt left in runs/ is removed, so that every run has one run folder."""
    run.folder.mkdir(parents=True, exist_ok=True)
    command = command_of(run, python)
    if "--resume" not in command and (run.folder / "runs").exists():
        shutil.rmtree(run.folder / "runs")
    status = run.status()
    attempts = status.get("attempts", 0) + 1
    log = open(run.folder / LOG_FILE, "ab")
    log_start = log.tell()
    header = f"=== attempt {attempts} at {time.strftime('%Y-%m-%d %H:%M:%S')}: {shlex.join(command)}\n"
    log.write(header.encode())
    log.flush()
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONUNBUFFERED="1")
    env.setdefault("MUJOCO_GL", "egl")
    process = subprocess.Popen(command, cwd=run.folder, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    log.close()
    write_status(
        run,
        {
            "state": "running",
            "attempts": attempts,
            "command": command,
            "host": os.uname().nodename,
            "pid": process.pid,
            "parent_pid": os.getpid(),
            "slurm_job": os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID")),
            "seconds": status.get("seconds", 0),  # over every attempt
        },
    )
    return Attempt(run, process, log_start, time.time())


def write_status(run: Run, status: dict) -> None:
    path = run.folder / STATUS_FILE
    run.folder.mkdir(parents=True, exist_ok=True)  # a Slurm job that died before its run started made no folder
    temporary = path.with_name(f"{STATUS_FILE}.{os.getpid()}.tmp")  # the launcher and a job may write at once
    temporary.write_text(json.dumps(status, indent=1) + "\n")
    os.replace(temporary, path)


def attempt_text(attempt: Attempt) -> str:
    with open(attempt.run.folder / LOG_FILE, "rb") as log:
        log.seek(attempt.log_start)
        return log.read().decode(errors="replace")


def finish(attempt: Attempt) -> dict:
    """Record how the ended attempt ended: done (exit 0 and the script's `done:` line), stopped (exit 0 after a stop
    signal, or killed by the stop signal this launcher sent before the script could handle it, in its first seconds:
    it resumes, or starts again, on the next launch or requeue) or failed (any other exit)."""
    rc = attempt.process.returncode
    lines = attempt_text(attempt).splitlines()
    if rc == 0 and any(line.startswith("done: ") for line in lines):
        state = "done"
    elif (rc == 0 and any(line.startswith("stopped: ") for line in lines)) or (attempt.signalled and rc in STOPPED_BY):
        state = "stopped"
    else:
        state = "failed"
    status = attempt.run.status()
    status.update(state=state, rc=rc, seconds=status.get("seconds", 0) + round(time.time() - attempt.started, 1))
    status["tail"] = lines[-DEFAULT_TAIL:] if state == "failed" else []
    write_status(attempt.run, status)
    return status


def progress_of(run: Run) -> dict:
    """The latest progress line of the run's log: step, total, figures, SPS, and the seconds left at the rate since the
    line before, less the time since the log was last written (so the figure keeps counting down between lines)."""
    try:
        with open(run.folder / LOG_FILE, "rb") as log:
            log.seek(max(0, log.seek(0, os.SEEK_END) - 8192))
            lines = log.read().decode(errors="replace").splitlines()
            written = os.fstat(log.fileno()).st_mtime
    except OSError:
        return {}
    for line in reversed(lines):
        found = PROGRESS.match(line)
        if found:
            step, total, figures, sps, left = found.groups()
            return {
                "step": int(step),
                "total": int(total),
                "figures": figures,
                "sps": int(sps),
                "left": None if left is None else max(int(left) - max(time.time() - written, 0), 0),
            }
    return {}


STOP_SIGNALS = {signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2}


def reaped(attempt: Attempt) -> int | None:
    """The run's exit status once it has ended, else None. Reaps the process itself, with the stop signals held back
    meanwhile, so that submitit's signal handler (which waits on the runs too) never finds it half-reaped, nor blocked
    on a lock of Popen.wait that the interrupted main loop holds."""
    if attempt.process.returncode is None:
        held = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            pid, wait_status = os.waitpid(attempt.process.pid, os.WNOHANG)
            if pid:
                attempt.process.returncode = os.waitstatus_to_exitcode(wait_status)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
    return attempt.process.returncode


def stop_attempt(attempt: Attempt, number: int = signal.SIGTERM) -> None:
    """Ask the run to stop after its current step (once: a second signal of the same kind stops it at once)."""
    if not attempt.signalled and reaped(attempt) is None:
        attempt.process.send_signal(number)
        attempt.signalled = True


# --- The table of runs ----------------------------------------------------------------------------------------------------


def clock(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def table(runs: list[Run], states: dict[str, str]) -> str:
    """One line per run: state, step/total, the latest figures the script printed, SPS and time left."""
    width = max(len(run.run_id) for run in runs)
    lines = [f"{'run':<{width}}  {'state':<9} {'step':>21}  {'SPS':>6}  {'left':>8}  latest"]
    for run in runs:
        state = states.get(run.run_id, "queued")
        progress = progress_of(run) if state not in ("queued", "skipped") else {}
        step = f"{progress['step']}/{progress['total']}" if progress else "-"
        sps = str(progress.get("sps", "-"))
        left = clock(progress.get("left")) if state == "running" else "-"
        figures = progress.get("figures", "")[:60]
        lines.append(f"{run.run_id:<{width}}  {state:<9} {step:>21}  {sps:>6}  {left:>8}  {figures}")
    counts = {state: list(states.values()).count(state) for state in dict.fromkeys(states.values())}
    queued = len(runs) - len(states)
    summary = ", ".join(f"{count} {state}" for state, count in counts.items()) + (f", {queued} queued" if queued else "")
    return "\n".join(lines) + f"\n[{time.strftime('%H:%M:%S')}] {len(runs)} runs: {summary}"


def failure_report(run: Run) -> str:
    status = run.status()
    tail = "\n".join(f"    {line}" for line in status.get("tail", []))
    return f"FAILED {run.run_id}: exit code {status.get('rc')}; log {run.folder / LOG_FILE}; its last lines:\n{tail}"


# --- Local backend: a pool of processes on this machine ---------------------------------------------------------------


def run_local(runs: list[Run], workers: int, python: str, threads: int, table_every: float) -> dict[str, str]:
    """Run every run, `workers` at a time; Ctrl-C or SIGTERM stops them cleanly (each writes its resume file)."""
    states: dict[str, str] = {}
    pending, active = list(runs), []
    stop = []
    previous = {number: signal.signal(number, lambda n, f: stop.append(n)) for number in (signal.SIGINT, signal.SIGTERM)}
    last_table = time.time()  # the first table after --table-every seconds, when the runs have something to show
    try:
        while pending or active:
            if stop:  # the first Ctrl-C or SIGTERM stops the runs cleanly, a second one at once
                pending.clear()
                for attempt in active:
                    if len(stop) > 1 and attempt.process.poll() is None:
                        attempt.process.send_signal(signal.SIGTERM)
                    stop_attempt(attempt)
            while pending and len(active) < workers:
                run = pending.pop(0)
                active.append(start(run, python, threads))
                states[run.run_id] = "running"
                print(f"started {run.run_id}", flush=True)
            for attempt in [a for a in active if a.process.poll() is not None]:  # poll() sets returncode
                active.remove(attempt)
                status = finish(attempt)
                states[attempt.run.run_id] = status["state"]
                print(
                    f"{status['state']} {attempt.run.run_id} (exit {status['rc']}, {clock(time.time() - attempt.started)})",
                    flush=True,
                )
                if status["state"] == "failed":
                    print(failure_report(attempt.run), flush=True)
            if time.time() - last_table >= table_every and (pending or active):
                print(table(runs, states), flush=True)
                last_table = time.time()
            time.sleep(0.5)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    return states


# --- Slurm backend: one job array through submitit ---------------------------------------------------------------------

try:
    import submitit
    from submitit.helpers import Checkpointable
except ImportError:  # the local backend needs nothing beyond the standard library
    submitit = None
    Checkpointable = object


class SlurmTask(Checkpointable):
    """One array task: its runs (several when packed on one GPU), side by side. On Slurm's signal before a time limit
    or on preemption, submitit calls `checkpoint`: every run is asked to stop after its current step, its resume file
    written, and the requeued task continues them with --resume. A run that fails makes the task raise, with its log's
    tail, so that the launcher shows the traceback."""

    def __init__(self, runs: list[Run], python: str, threads: int, stop_wait: float):
        self.runs, self.python, self.threads = runs, python, threads
        self.stop_wait = stop_wait  # seconds the runs get to stop (then they are killed): less than Slurm's grace
        self.attempts: list[Attempt] = []

    def __getstate__(self) -> dict:
        return {**self.__dict__, "attempts": []}

    def __call__(self) -> list[dict]:
        todo = [run for run in self.runs if run.status().get("state") != "done"]
        self.attempts = [start(run, self.python, self.threads) for run in todo]
        self.wait()
        statuses = [finish(attempt) for attempt in self.attempts]
        failed = [run for run, status in zip(todo, statuses, strict=True) if status["state"] != "done"]
        if failed:
            raise RuntimeError("\n".join(failure_report(run) for run in failed))
        return statuses

    def wait(self, timeout: float | None = None) -> None:
        """Until every run has ended; after `timeout` seconds, the ones left are killed."""
        end = None if timeout is None else time.time() + timeout
        while any(reaped(attempt) is None for attempt in self.attempts):
            if end is not None and time.time() > end:
                for attempt in self.attempts:
                    if reaped(attempt) is None:
                        attempt.process.kill()
            time.sleep(0.2)

    def checkpoint(self) -> submitit.helpers.DelayedSubmission:
        # Slurm signals every process of the job: the runs have most likely had SIGTERM and/or SIGUSR2 already. SIGUSR1
        # is a kind they have not had, so sending it is harmless when they have and stops them when they have not.
        for attempt in self.attempts:
            stop_attempt(attempt, signal.SIGUSR1)
        self.wait(timeout=self.stop_wait)
        for attempt in self.attempts:
            finish(attempt)
        return submitit.helpers.DelayedSubmission(SlurmTask(self.runs, self.python, self.threads, self.stop_wait))


def slurm_executor(args: Args, folder: Path):
    executor = submitit.AutoExecutor(folder=folder / "slurm" / "%j", cluster="slurm", slurm_max_num_timeout=args.max_requeues)
    parameters = {
        "name": args.name,
        "timeout_min": args.time_min,
        "cpus_per_task": args.cpus_per_task,
        "slurm_array_parallelism": args.array_parallelism,
        "slurm_signal_delay_s": args.signal_delay_s,
        "slurm_setup": [f"export PYTHONPATH={shlex.quote(str(ROOT / 'benchmark'))}${{PYTHONPATH:+:$PYTHONPATH}}", *args.setup],
        "slurm_additional_parameters": dict(option.split("=", 1) for option in args.sbatch),
    }
    if args.partition:
        parameters["slurm_partition"] = args.partition
    if args.gpus_per_task:
        parameters["gpus_per_node"] = args.gpus_per_task
    if args.mem_gb:
        parameters["mem_gb"] = args.mem_gb
    executor.update_parameters(**parameters)
    return executor


def run_slurm(runs: list[Run], args: Args, folder: Path) -> dict[str, str]:
    """Submit one job array (`--runs-per-task` runs a task) and wait for it, with the table of runs; a job that ends
    without a result (killed, out of memory, cancelled) is reported as such, from Slurm's accounting."""
    jobs_file = folder / "slurm_jobs.json"
    if jobs_file.is_file():
        known = json.loads(jobs_file.read_text())
        active = [job for job in known if slurm_state(job) in ACTIVE_STATES]
        if active:
            exit_on_errors(
                [
                    f"this sweep already has jobs in the queue ({', '.join(active)}): wait for them or "
                    f"scancel them before launching it again"
                ]
            )
    chunks = [runs[i : i + args.runs_per_task] for i in range(0, len(runs), args.runs_per_task)]
    stop_wait = max(args.signal_delay_s - 15, 10)  # the time limit comes signal_delay_s after the stop signal
    executor = slurm_executor(args, folder)
    try:
        with executor.batch():
            jobs = [executor.submit(SlurmTask(chunk, args.python, args.threads, stop_wait)) for chunk in chunks]
    except (submitit.core.utils.UncompletedJobError, submitit.core.utils.FailedSubmissionError) as error:
        message = " ".join(str(error).split())  # sbatch's own words, e.g. an unknown partition or account
        exit_on_errors([f"sbatch refused the sweep's job array: {message[-600:]}"])
    submitted = time.time() - 1  # file times may be a little behind this clock
    jobs_file.write_text(json.dumps([job.job_id for job in jobs]) + "\n")
    print(
        f"submitted {len(jobs)} array tasks of job {jobs[0].job_id.split('_')[0]} ({len(runs)} runs); "
        f"submitit's files in {folder / 'slurm'}",
        flush=True,
    )
    states: dict[str, str] = {}
    waiting = dict(zip(jobs, chunks, strict=True))
    stop, requeued = [], set()
    previous = signal.signal(signal.SIGINT, lambda n, f: stop.append(n))
    last_table = time.time()
    try:
        while waiting and not stop:
            for job, chunk in list(waiting.items()):
                for run in chunk:  # a status written before this submission is an earlier launch's: still queued
                    status_file = run.folder / STATUS_FILE
                    if status_file.is_file() and status_file.stat().st_mtime >= submitted:
                        states[run.run_id] = run.status().get("state", "queued")
                if not job.done():
                    continue
                held = slurm_state(job.job_id)  # done() trusts the result file, which an earlier attempt may have left
                if held in ACTIVE_STATES and any(run.status().get("state") not in ("done", "failed") for run in chunk):
                    for run in chunk:  # Slurm requeued the task itself (scontrol requeue, preemption): it will run again
                        if states.get(run.run_id) == "stopped" and held != "COMPLETING":
                            states[run.run_id] = "requeued"
                            if (run.run_id, run.status().get("attempts")) not in requeued:
                                requeued.add((run.run_id, run.status().get("attempts")))
                                print(f"requeued {run.run_id} (job {job.job_id}, Slurm state {held})", flush=True)
                    continue
                del waiting[job]
                try:
                    job.result()
                except Exception as error:  # the runs' own status says which failed and why, unless the job died first
                    if isinstance(error, submitit.core.utils.UncompletedJobError):
                        why = f"job {job.job_id} ended without a result (Slurm state {slurm_state(job.job_id)})"
                    else:
                        why = f"job {job.job_id} failed"
                    for run in chunk:
                        if run.status().get("state") not in ("done", "failed", "stopped"):
                            write_status(
                                run,
                                {
                                    **run.status(),
                                    "state": "failed",
                                    "rc": None,
                                    "tail": [why, *str(error).splitlines()[-DEFAULT_TAIL:]],
                                },
                            )
                for run in chunk:
                    state = run.status().get("state", "failed")
                    states[run.run_id] = state
                    print(f"{state} {run.run_id} (job {job.job_id})", flush=True)
                    if state == "failed":
                        print(failure_report(run), flush=True)
            if time.time() - last_table >= args.table_every and waiting:
                print(table(runs, states), flush=True)
                last_table = time.time()
            time.sleep(2)
    finally:
        signal.signal(signal.SIGINT, previous)
    if stop:
        print(
            f"stopped waiting: the jobs go on in the queue ({jobs[0].job_id.split('_')[0]}); launch the sweep again once "
            "they are done to see its results, or scancel them",
            flush=True,
        )
        sys.exit(130)
    return states


ACTIVE_STATES = (
    "PENDING",
    "RUNNING",
    "REQUEUED",
    "CONFIGURING",
    "COMPLETING",
    "RESIZING",
    "SUSPENDED",
    "REQUEUE_HOLD",
    "REQUEUE_FED",
    "SIGNALING",
    "STAGE_OUT",
    "PREEMPTED",
)


def slurm_state(job_id: str) -> str:
    """A job's state from squeue, or else from sacct ("UNKNOWN" if neither knows it)."""
    for command in (["squeue", "-h", "-j", job_id, "-o", "%T"], ["sacct", "-n", "-X", "-P", "-j", job_id, "-o", "State"]):
        try:
            out = subprocess.run(command, capture_output=True, text=True, timeout=30).stdout.split()
        except (OSError, subprocess.TimeoutExpired):
            continue
        if out:
            return out[-1].split()[0]
    return "UNKNOWN"


# --- The command line ------------------------------------------------------------------------------------------------


@dataclass
class Args:
    preset: str | None = None
    """a named study (--list-presets shows them); --script, --env-ids, --groups, --seeds and --flags change it"""
    script: str | None = None
    """the script of every run (e.g. dgrl_ris.py), for a sweep without a preset"""
    env_ids: list[str] = field(default_factory=list)
    """env ids of the grid (empty: each arm's own, or the script's default)"""
    groups: list[int] = field(default_factory=list)
    """values of --groups of the grid (0 is the baseline; empty: the preset's, or 0 and 16)"""
    seeds: list[int] = field(default_factory=list)
    """seeds of the grid (empty: the preset's, or 1 2 3)"""
    flags: str = ""
    """extra flags for every run, in one string (after the preset's own, so they win); or give them after a bare --"""
    name: str | None = None
    """the sweep's name: its folder sweeps/NAME and the runs' --exp-name (default: the preset's or the script's name)"""
    sweeps_dir: str = "sweeps"
    """folder holding one folder per sweep"""
    backend: Literal["local", "slurm"] = "local"
    """local: a pool of processes on this machine; slurm: one job array through submitit"""
    workers: int | None = None
    """local backend: runs at a time (default: the preset's, or 2)"""
    threads: int = 1
    """torch threads per run (--threads of the scripts; OMP_NUM_THREADS too)"""
    retry: bool = False
    """run again the runs that failed in an earlier launch (from their resume file when they wrote one)"""
    dry_run: bool = False
    """print the runs and their commands, run nothing"""
    plot: bool = True
    """write the preset's curves and tables to the sweep's folder once every run is done"""
    plot_tags: list[str] = field(default_factory=list)
    """scalar tags for one more figure and table of all the sweep's runs, sweeps/NAME/NAME.png and .md"""
    table_every: float = 60.0
    """seconds between two tables of the runs"""
    python: str = sys.executable
    """the Python that runs the scripts (on a cluster: one every node can reach)"""
    list_presets: bool = False
    """list the presets and exit"""
    partition: str | None = None
    """slurm: the partition (default: the cluster's default one)"""
    time_min: int = 240
    """slurm: the time limit of one job, in minutes; a run that needs longer continues in the requeued job"""
    cpus_per_task: int = 1
    """slurm: CPUs of one array task"""
    gpus_per_task: int = 0
    """slurm: GPUs of one array task (its runs share them)"""
    runs_per_task: int = 1
    """slurm: runs packed in one array task, side by side (e.g. 4 runs on one GPU)"""
    mem_gb: float | None = None
    """slurm: memory of one array task in GB (default: the cluster's)"""
    array_parallelism: int = 256
    """slurm: array tasks running at once"""
    signal_delay_s: int = 120
    """slurm: seconds between the stop signal and the time limit (time for the runs to write their resume files)"""
    max_requeues: int = 20
    """slurm: how many times a job may requeue on its time limit (preemptions do not count)"""
    sbatch: list[str] = field(default_factory=list)
    """slurm: extra sbatch options, KEY=VALUE each (e.g. account=myproject qos=low constraint=a100)"""
    setup: list[str] = field(default_factory=list)
    """slurm: shell lines the job runs first (e.g. "module load cuda")"""


def exit_on_errors(errors: list[str]) -> None:
    if errors:
        for error in errors:
            print(f"launch.py: {error}", file=sys.stderr)
        raise SystemExit(2)


def arms_of(args: Args) -> tuple[tuple[Arm, ...], Preset | None]:
    """The sweep's arms: the preset's (or one arm of --script), each axis replaced by the flag given for it."""
    preset = PRESETS.get(args.preset) if args.preset else None
    arms = preset.arms if preset else (Arm(args.script or ""),)
    changed = []
    for arm in arms:
        changed.append(
            Arm(
                args.script or arm.script,
                tuple(args.env_ids) or arm.env_ids,
                tuple(args.groups) or arm.groups,
                tuple(args.seeds) or arm.seeds,
                f"{arm.flags} {args.flags}".strip(),
                arm.tag,
            )
        )
    return tuple(changed), preset


def check(args: Args) -> list[str]:
    """Every problem with the flags, before anything runs."""
    errors = []
    if args.preset is not None and args.preset not in PRESETS:
        errors.append(f"--preset {args.preset}: no such preset; the presets: {', '.join(PRESETS)}")
    if args.preset is None and args.script is None:
        errors.append("pass --preset NAME or --script SCRIPT (--list-presets shows the presets)")
    if args.script is not None and not (ROOT / args.script).is_file():
        scripts = sorted(path.name for path in ROOT.glob("dgrl_*.py"))
        errors.append(f"--script {args.script}: no such script; the scripts: {', '.join(scripts)}")
    for flag in ("threads", "cpus_per_task", "runs_per_task", "array_parallelism", "time_min"):
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    for flag in ("gpus_per_task", "signal_delay_s", "max_requeues"):
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    if args.workers is not None and args.workers < 1:
        errors.append(f"--workers must be >= 1, got {args.workers}")
    if args.table_every <= 0:
        errors.append(f"--table-every must be > 0, got {args.table_every}")
    if args.mem_gb is not None and args.mem_gb <= 0:
        errors.append(f"--mem-gb must be > 0, got {args.mem_gb}")
    errors += [f"--sbatch {option}: give KEY=VALUE (e.g. account=myproject)" for option in args.sbatch if "=" not in option]
    if any(seed < 0 for seed in args.seeds):
        errors.append(f"--seeds must be >= 0, got {args.seeds}")
    if args.name is not None and (not args.name or slug(args.name) != args.name or "__" in args.name):
        errors.append(f"--name {args.name!r}: use letters, digits, '.', '=', '+' and '-' (single '_' too), no spaces")
    try:
        shlex.split(args.flags)
    except ValueError as error:
        errors.append(f"--flags {args.flags!r}: {error}")
    if args.backend == "slurm":
        if submitit is None:
            errors.append("--backend slurm needs submitit: pip install -r requirements.txt")
        if shutil.which("sbatch") is None:
            errors.append("--backend slurm: no sbatch on PATH (run the launcher on a machine of the cluster)")
    elif args.runs_per_task != 1 or args.gpus_per_task or args.partition or args.sbatch or args.setup:
        errors.append("--partition, --gpus-per-task, --runs-per-task, --sbatch and --setup are for --backend slurm")
    return errors


# The script's own parser and validate(), on each run's flags, in a child process (it imports torch), from an empty
# folder: a run of the sweep would refuse the same flags with the same message, after queueing and starting.
FLAG_CHECK = """
import importlib.util, json, sys, tyro
path, on_slurm, runs = sys.argv[1], sys.argv[2] == "slurm", json.load(sys.stdin)
spec = importlib.util.spec_from_file_location("checked_script", path)
script = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(script)
for run_id, argv in runs:
    print(run_id, flush=True)
    args = tyro.cli(script.Args, args=argv, prog=spec.origin.rsplit("/", 1)[-1])
    if on_slurm:
        args.fast = "eager"  # what --fast needs (CUDA, a compiler) is the node's, not this machine's
    script.validate(args)
"""


def flag_errors(runs: list[Run], python: str, backend: str) -> list[str]:
    """The runs' flags as their scripts see them, checked once before the sweep starts: one error per refusing script."""
    errors = []
    for script in dict.fromkeys(run.script for run in runs):
        source = (ROOT / script).read_text()
        if "\nclass Args" not in source or "\ndef validate(" not in source:
            continue  # not a script of this project (a stand-in of the tests): it has no validate to ask
        argvs = [(run.run_id, run.argv) for run in runs if run.script == script]
        with tempfile.TemporaryDirectory() as folder:
            result = subprocess.run(
                [python, "-c", FLAG_CHECK, str(ROOT / script), backend],
                input=json.dumps(argvs),
                capture_output=True,
                text=True,
                cwd=folder,
                env=dict(os.environ, PYTHONPATH=str(ROOT)),
            )
        if result.returncode:
            run_id = (result.stdout.split() or ["(none)"])[-1]
            argv = dict(argvs).get(run_id, [])
            message = "\n".join(f"    {line}" for line in result.stderr.strip().splitlines()[-20:])
            errors.append(f"{script} refuses the flags of run {run_id} ({shlex.join(argv)}):\n{message}")
    return errors


def hold_lock(folder: Path):
    """An exclusive lock on the sweep's folder for as long as this launcher runs (the kernel drops it when the process
    ends, however it ends), so that two launchers never run the same runs at once."""
    handle = open(folder / "launch.lock", "a+")  # kept open: closing it would drop the lock
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        exit_on_errors(
            [
                f"{folder} is in use by another launcher ({handle.read().strip() or 'pid unknown'}): wait for it "
                "to end, or stop it with Ctrl-C, before launching this sweep again"
            ]
        )
    handle.truncate(0)
    handle.write(f"pid {os.getpid()} on {os.uname().nodename}\n")
    handle.flush()
    return handle


def describe_presets() -> str:
    lines = []
    for name, preset in PRESETS.items():
        count = len(expand(preset.arms, name, Path("."), 1))
        lines.append(f"{name:<17} {count:>3} runs  {preset.description}")
    return "\n".join(lines)


def write_plots(plots: tuple[Plot, ...], folder: Path, runs: list[Run]) -> None:
    """The figures and tables of `plots` from the sweep's runs, by benchmark/plot.py."""
    import plot

    run_dirs = [run.run_dir() for run in runs]
    for spec in plots:
        out = folder / spec.out
        plot.plot_study(
            [d for d in run_dirs if d is not None], list(spec.tags), str(out), spec.match, spec.panel_by, spec.title, spec.bins
        )


def main(args: Args) -> int:
    if args.list_presets:
        print(describe_presets())
        return 0
    exit_on_errors(check(args))
    arms, preset = arms_of(args)
    name = args.name or args.preset or Path(arms[0].script).stem
    args.name = name
    folder = Path(args.sweeps_dir).resolve() / name
    runs = expand(arms, name, folder, args.threads)
    exit_on_errors(flag_errors([run for run in runs if run.status().get("state") != "done"], args.python, args.backend))
    if args.dry_run:
        for run in runs:
            print(f"{run.run_id}: cd {run.folder} && {shlex.join(command_of(run, args.python))}")
        return 0
    folder.mkdir(parents=True, exist_ok=True)
    lock = hold_lock(folder)  # noqa: F841 (held until the launcher exits)
    (folder / "sweep.json").write_text(
        json.dumps(
            {
                "name": name,
                "preset": args.preset,
                "runs": [{"id": r.run_id, "script": r.script, "argv": r.argv} for r in runs],
            },
            indent=1,
        )
        + "\n"
    )
    states, todo = {}, []
    for run in runs:
        state = run.status().get("state")
        if state == "done":
            states[run.run_id] = "skipped"
        elif state == "failed" and not args.retry:
            states[run.run_id] = "failed"
        else:
            todo.append(run)
    skipped = sum(state == "skipped" for state in states.values())
    failed_before = [run for run in runs if states.get(run.run_id) == "failed"]
    resuming = sum("--resume" in command_of(run, args.python) for run in todo)
    print(
        f"sweep {name}: {len(runs)} runs in {folder}; {skipped} done before, {len(failed_before)} failed before "
        f"(--retry runs them again), {len(todo)} to run ({resuming} resuming)",
        flush=True,
    )
    if todo:
        if args.backend == "local":
            workers = args.workers or (preset.workers if preset else 2)
            states.update(run_local(todo, workers, args.python, args.threads, args.table_every))
        else:
            states.update(run_slurm(todo, args, folder))
    print(table(runs, {run.run_id: run.status().get("state", "queued") for run in runs}), flush=True)
    failed = [run for run in runs if run.status().get("state") == "failed"]
    unfinished = [run for run in runs if run.status().get("state") != "done"]
    for run in failed:
        print(failure_report(run), flush=True)
    if unfinished:
        print(
            f"{len(unfinished)} of {len(runs)} runs are not done ({len(failed)} failed): launch the same command again "
            f"to resume the stopped ones{' and --retry to rerun the failed ones' if failed else ''}",
            flush=True,
        )
        return 1
    plots = (preset.plots if preset else ()) + ((Plot(name, tuple(args.plot_tags), name),) if args.plot_tags else ())
    if args.plot and plots:
        write_plots(plots, folder, runs)
    if preset and preset.note:
        print(f"\n{preset.note}")
    return 0


def cli(argv: list[str]) -> Args:
    """The launcher's flags; whatever follows a bare `--` is added to --flags (extra flags for every run)."""
    import tyro

    extra = []
    if "--" in argv:
        argv, extra = argv[: argv.index("--")], argv[argv.index("--") + 1 :]
    args = tyro.cli(Args, args=argv, description=__doc__)
    args.flags = f"{args.flags} {shlex.join(extra)}".strip()
    given = {word.split("=", 1)[0] for word in argv}
    lists = [name for name, value in vars(args).items() if isinstance(value, list)]
    empty = [
        f"--{name.replace('_', '-')}" for name in lists if f"--{name.replace('_', '-')}" in given and not getattr(args, name)
    ]
    exit_on_errors([f"{flag} was given no value: give at least one, or leave it out for the preset's own" for flag in empty])
    return args


if __name__ == "__main__":
    import launch  # this file as a module: Slurm jobs unpickle its classes as launch.*, which they can import, not __main__.*

    sys.exit(launch.main(launch.cli(sys.argv[1:])))
