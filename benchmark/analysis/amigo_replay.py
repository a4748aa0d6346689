"""Replay an AMIGo run from one of its resume files and measure how far each student update moves the policy.

    python benchmark/analysis/amigo_replay.py SNAPSHOT.pt --first 120 --last 136 -- THE RUN'S FLAGS
    python benchmark/analysis/amigo_replay.py snapshots/resume_105808.pt --first 120 --last 136 -- \\
        --env-id MiniGrid-KeyCorridorS3R1-v0 --groups 16 --seed 2 --total-timesteps 3000000 \\
        --progress-frequency 50000 --goal-channel on --exp-name amigo-collapse --threads 1

A resume file continues a run exactly (dgrl_amigo.py's `--resume`), so a collapse that happened after it happens again,
update for update. This copies dgrl_amigo.py and vq.py to a scratch folder, adds a measurement after each student
update (the text patch below, checked against the script by the tests) and resumes the run there from SNAPSHOT with
the run's own flags (its log's first line has them; `--checkpoint-every` and `--save-model` may differ). For the
student updates numbered --first to --last after the resume it prints: the mean and largest KL divergence between the
policy before and after the update on the update's own batch (codebook update included), the norm of the parameter
step, the parameter that moved most relative to its norm with the RMS of its (clipped) gradient over the running RMS
RMSprop divided it by, the gradient's norm before clipping, the batch's largest
|advantage|, its rewards and episode ends, and the policy's entropy. It stops after --last. The run's own folder and
resume files are never written. To have resume files to replay from, copy a run's `runs/{run}/resume.pt` while it
runs with a short `--checkpoint-every` (each write replaces the last).
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

ANCHOR = """    learn(agent.student_optimizer, loss + vq_loss * (len(goals) / B), args.max_grad_norm)
"""
MEASURE = """    named = [(n, q) for n, q in agent.student.named_parameters() if q.requires_grad]
    named += [("goal_encoder." + n, q) for n, q in agent.goal_encoder.named_parameters() if q.requires_grad]
    before = {n: q.detach().clone() for n, q in named}
    state = agent.student_optimizer.state
    square_avg = {n: state[q]["square_avg"].clone() for n, q in named if "square_avg" in state.get(q, {})}
    learn(agent.student_optimizer, loss + vq_loss * (len(goals) / B), args.max_grad_norm)
    REPLAY["update"] += 1
    if REPLAY["first"] <= REPLAY["update"] <= REPLAY["last"]:
        with torch.no_grad():
            embedding_after = agent.goal_encoder(batch["goal_frames"], goals, update=False)[0]
            logits_after = agent.student(batch["grids"], batch["carried"], goals, embedding_after)[0][: T * B]
            old, new = F.log_softmax(logits.detach(), -1), F.log_softmax(logits_after.view(T, B, -1), -1)
            kl = (old.exp() * (old - new)).sum(-1)
            moved = {n: float((q.detach() - before[n]).norm()) for n, q in named}
            relative = {n: moved[n] / (float(before[n].norm()) + 1e-8) for n in moved}
            top = max(relative, key=relative.get)
            gradient = dict(named)[top].grad
            surprise = float("nan")  # the clipped gradient's RMS over the RMS RMSprop had for it before this step
            if top in square_avg and gradient is not None:
                surprise = float(gradient.pow(2).mean().sqrt() / square_avg[top].mean().sqrt().clamp_min(1e-12))
        print(
            f"update {REPLAY['update']:4d}  KL mean {float(kl.mean()):.2g} max {float(kl.max()):.2g}  "
            f"step {sum(v * v for v in moved.values()) ** 0.5:.3f} (most: {top} {relative[top]:.1%}, "
            f"its gradient {surprise:.1f}x its running RMS)  "
            f"grad norm {REPLAY['grad_norm']:.0f}  |advantage| max {float(advantages.abs().max()):.2f}  "
            f"rewards {float(batch['rewards'].sum()):.1f}  episode ends {float(batch['dones'].sum()):.0f}  "
            f"entropy {float(entropy.detach()) / T:.3f}",
            flush=True,
        )
    if REPLAY["update"] >= REPLAY["last"]:
        raise SystemExit(0)
"""
CLIP = """        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
"""
CLIP_MEASURED = """        REPLAY["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True))
"""
LEARN = "\ndef learn(optimizer"


def patch(source: str, first: int, last: int) -> str:
    """dgrl_amigo.py's text with the measurement added; a clear error if the script no longer has the anchors."""
    for name, anchor in (("the student's learn call", ANCHOR), ("the gradient clipping", CLIP), ("learn()", LEARN)):
        if source.count(anchor) != 1:
            raise SystemExit(f"amigo_replay.py: dgrl_amigo.py no longer has {name} this patch expects; update the patch")
    source = source.replace(ANCHOR, MEASURE).replace(CLIP, CLIP_MEASURED)
    state = f'\nREPLAY = {{"update": 0, "first": {first}, "last": {last}, "grad_norm": float("nan")}}\n\n'
    return source.replace(LEARN, state + LEARN, 1)


def main(snapshot: Path, first: int, last: int, flags: list[str]) -> int:
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        (folder / "dgrl_amigo.py").write_text(patch((ROOT / "dgrl_amigo.py").read_text(), first, last))
        shutil.copy(ROOT / "vq.py", folder / "vq.py")
        run = folder / "runs" / "replay"
        run.mkdir(parents=True)
        shutil.copy(snapshot, run / "resume.pt")
        command = [sys.executable, "dgrl_amigo.py", *flags, "--checkpoint-every", "0", "--resume", "runs/replay"]
        return subprocess.run(command, cwd=folder).returncode


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("snapshot", type=Path, help="a resume.pt of dgrl_amigo.py (a copy taken while the run ran)")
    parser.add_argument("--first", type=int, default=1, help="first student update after the resume to measure")
    parser.add_argument("--last", type=int, default=50, help="last one: the replay stops after it")
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    options = parser.parse_args(argv[:split])
    flags = argv[split + 1 :]
    if not flags:
        parser.error("give the run's own flags after a bare -- (its log's first line has them)")
    if not options.snapshot.is_file():
        parser.error(f"no resume file at {options.snapshot}")
    if not 1 <= options.first <= options.last:
        parser.error(f"--first and --last must satisfy 1 <= first <= last, got {options.first} and {options.last}")
    sys.exit(main(options.snapshot, options.first, options.last, flags))
