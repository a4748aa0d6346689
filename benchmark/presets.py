"""The studies, as data: one `Preset` per study of docs/ and per paper figure, each with its arms (a script and the lists
of env ids, groups and seeds it runs), its plots, and the docs page that reports it. benchmark/launch.py runs them:

    python benchmark/launch.py --list-presets
    python benchmark/launch.py --preset NAME [--seeds 4 5 6 ...]

A new study is one more entry of PRESETS (and its page); nothing else changes. tests/test_launch.py checks every entry:
its scripts and flags (each run's flags through the script's own validate), its plots, and its page.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    """One figure and table of benchmark/analysis/plot.py over the sweep's runs: `sweeps/{name}/{out}.png` and `.md`."""

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
    page: str = ""  # the page that reports the study (its results, figures and commands)


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
    page: str = "docs/dgrl_amigo.md",
) -> Preset:
    """An AMIGo study: AMIGo (G0) against AMIGo+DGRL on one MiniGrid env, 3 seeds, its curves binned over frames."""
    dgrl = ", ".join(f"G{g}" for g in groups if g)
    return Preset(
        f"{source}: AMIGo vs AMIGo+DGRL ({dgrl}) on {env}, {what}, 3 seeds",
        (Arm("dgrl_amigo.py", (env,), groups, (1, 2, 3), f"--total-timesteps {frames} {AMIGO_FLAGS} {extra}".strip()),),
        (Plot(out, AMIGO_TAGS, f"{env}: AMIGo vs AMIGo+DGRL, {what}", bins=bins),),
        workers=workers,
        page=page,
    )


QUICK_NOTE = """\
What this shows. The paper's claim (section 5): with discrete factorial codes for state and goal (DGRL, here G = 16),
a goal-conditioned DQN generalises better to goals it never trained on than the same agent on continuous embeddings
(G0). Read the novel-goal columns. Each agent here has only 2 seeds and 4 novel goals, so one goal is 25 points of a
seed's novel success and the two seeds often disagree: the final values can put either agent ahead, and a gap this
small is not evidence either way. The averages over all evaluations ("avg") say which agent got there sooner. In the
full study (5 seeds), the same setting as here (8 training goals) gave G = 16 a lead on the way (mean novel success
over the evaluations 0.58 against 0.47, exact permutation p = 0.14) and G = 8 a significant one (0.61, p = 0.016),
all agents level at the end; with 16 training goals DGRL ahead on the way, not significantly; G = 4 did worse than
the baseline. A seeded run repeats exactly only on a machine with the same instruction set. These are short
CPU-sized runs, not the paper's budget. Full study, curves and tables: docs/dgrl_goal_dqn.md#results; every claim:
docs/claims.md"""

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
        page="docs/launch.md",
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
        page="README.md",
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
        page="docs/dgrl_goal_dqn.md",
    ),
    "mnist": Preset(
        "docs/dgrl_mnist.md: Color-MNIST, DGRL (G2) and the continuous autoencoder (G0), 3 seeds (6 runs)",
        (Arm("dgrl_mnist.py", (), (2, 0), (1, 2, 3)),),
        (Plot("mnist_factors", MNIST_TAGS, "Color-MNIST: decoding and swapping the factors"),),
        page="docs/dgrl_mnist.md",
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
        page="docs/dgrl_hrac_keychest.md",
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
        page="docs/dgrl_hrac_keychest.md",
    ),
    "ris-pointmaze": Preset(
        "docs/dgrl_ris.md's CPU preset: RIS vs RIS+DGRL (G16) on PointMaze_UMaze-v3, 30,000 steps, batch 128, 3 seeds",
        (_ris("PointMaze_UMaze-v3", 30_000, 128, 2_000, 2_000, 10, extra=RIS_SNIPPET_SUM),),
        (Plot("ris_pointmaze_cpu", RIS_TAGS, "PointMaze_UMaze-v3: RIS vs RIS+DGRL, 30,000 steps, batch 128", bins=15),),
        page="docs/dgrl_ris.md",
    ),
    "ris-antu-cpu": Preset(
        "docs/dgrl_ris.md: AntU on a CPU, RIS vs RIS+DGRL (G16), 40,000 steps, batch 256, 1 seed",
        (_ris("AntU", 40_000, 256, 10_000, 5_000, 10, seeds=(1,), extra=RIS_SNIPPET_SUM),),
        (Plot("ris_antu_cpu", RIS_TAGS, "AntU: RIS vs RIS+DGRL, 40,000 steps, batch 256", bins=15),),
        page="docs/dgrl_ris.md",
    ),
    "hrac-antmaze-cpu": Preset(
        "docs/dgrl_hrac.md: HRAC vs HRAC+DGRL (G16) on AntMaze, 300,000 of the paper's 5M steps, 1 seed",
        (Arm("dgrl_hrac.py", ("AntMaze",), (0, 16), (1,), "--total-timesteps 300000 --save-model"),),
        (Plot("hrac_antmaze_cpu", (*HRAC_TAGS, "charts/controller_reward"), "AntMaze: HRAC vs HRAC+DGRL, 300k steps"),),
        page="docs/dgrl_hrac.md",
    ),
    "sawyer-cpu": Preset(
        "docs/dgrl_ris_sawyer.md's CPU preset: RIS vs RIS+DGRL (G16) from pixels, 30,000 steps, batch 32, 2 seeds",
        (Arm("dgrl_ris_sawyer.py", (), (0, 16), (1, 2), f"--total-timesteps 30000 {SAWYER_CPU}"),),
        (Plot("ris_sawyer_cpu", (*SAWYER_TAGS, "losses/q_values"), "Sawyer push-and-reach from pixels, 30,000 steps"),),
        page="docs/dgrl_ris_sawyer.md",
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
        page="docs/dgrl_amigo.md",
    ),
    "amigo-s3r1": _amigo(
        "MiniGrid-KeyCorridorS3R1-v0",
        1_000_000,
        (0, 8, 16),
        "amigo_s3r1_cpu",
        "docs/dgrl_amigo.md",
        "1M frames, the goal channel in both modes (--goal-channel on)",
        "--goal-channel on",
        page="docs/dgrl_amigo.md",
    ),
    "amigo-s3r1-3m": _amigo(
        "MiniGrid-KeyCorridorS3R1-v0",
        3_000_000,
        (0, 16),
        "amigo_s3r1_3m",
        "docs/dgrl_amigo.md",
        "3M frames, the goal channel in both modes (--goal-channel on)",
        "--goal-channel on",
        page="docs/dgrl_amigo.md",
    ),
    "amigo-nochannel": _amigo(
        "MiniGrid-DoorKey-5x5-v0",
        1_000_000,
        (0, 16),
        "amigo_doorkey_nochannel",
        "docs/dgrl_amigo.md",
        "1M frames, the goal only through the encoder in both modes (--goal-channel off)",
        "--goal-channel off",
        page="docs/dgrl_amigo.md",
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
        page="docs/dgrl_amigo.md",
    ),
    "hrac-paper": Preset(
        "the paper's HRAC Ant figures (main text and appendix): HRAC vs HRAC+DGRL on the five HIRO Ant envs, "
        "G in {0, 2, 4, 8, 16, 32}, 5M steps, 3 seeds (90 runs)",
        (Arm("dgrl_hrac.py", HIRO_ENVS, (0, 2, 4, 8, 16, 32), (1, 2, 3), "--total-timesteps 5000000 --save-model"),),
        tuple(Plot(f"hrac_{env}", HRAC_TAGS, f"{env}: HRAC vs HRAC+DGRL, 5M steps", f"^{env}__") for env in HIRO_ENVS),
        workers=1,
        page="docs/dgrl_hrac.md",
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
        page="docs/dgrl_ris.md",
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
        page="docs/dgrl_ris_sawyer.md",
    ),
}
