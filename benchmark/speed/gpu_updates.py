"""Each script's training update at its paper (or default) batch size through each speed path, side by side on one device:
milliseconds per update and how far each path's numbers are from eager's.

    python benchmark/speed/gpu_updates.py                                  # every case; on a GPU: eager, compile, cudagraphs
    python benchmark/speed/gpu_updates.py --device cpu --cases ris_G16     # one case on the CPU (eager and compile)
    python benchmark/speed/gpu_updates.py --device cpu --paths eager       # every case eager only: does each build and run?
    python benchmark/speed/gpu_updates.py --help                           # the cases' names

The speed paths are the scripts' `--fast` choices, `fast_update(update, fast, optimizers)` of every script: eager (the
update as it is), compile (torch.compile, one graph) and cudagraphs (torch.compile's "reduce-overhead" mode with
capturable optimizers: the graph replayed as CUDA graphs; CUDA only). A case is one update function of one script, with
DGRL and, where the script has a baseline, without, built by the script's own make_agent at its default flags (those of
the paper presets of benchmark/presets.py) on inputs made beforehand (so the update alone is timed). For each case and
path:

1. The agent is built from a fixed seed (torch.manual_seed(0), numpy's default_rng(0)) with the same inputs, the update is
   wrapped by `fast_update(update, path, optimizers)`, and 10 (--updates) updates run after torch.manual_seed(7) (the
   first ones compile and capture; the scripts compile with inductor's fallback_random, so a seed draws the same numbers
   compiled as eager). Then every parameter, buffer and optimizer state tensor of the agent is compared with eager's
   after the same updates. The relative difference of a tensor a against eager's b is
   max|a - b| / max(max|b|, 1e-12); the figure is the largest over the agent's tensors, with that tensor's name. (Adam
   moves a parameter by about a learning rate at its first steps whatever the size of its gradient, so a gradient that
   is rounding noise around zero can give a difference of the order of lr / max|b| that is rounding, not an error;
   goal-DQN's infomax pretrain_step has such a gradient all along, psi_next.bias's, InfoNCE being blind to that bias (see
   tests/test_goal_dqn.py): its Adam moments, rep_optimizer.13.*, differ by as much as their own size.)
2. On a CUDA device the eager updates also run on the CPU (same seeds, same inputs: they are made on the CPU and copied
   to the device), and "GPU vs CPU" is eager-on-the-GPU's largest relative difference against eager-on-the-CPU. The two
   devices' random generators differ, so updates drawing random numbers on the device (the target policy noise and the
   actor's samples of TD3 and RIS, Sawyer's random translate, codebook restarts) differ there by their draws, not only
   by rounding; for the others it is the rounding of 10 updates.
3. Time per update: after those updates, the median over 5 blocks of benchmark/speed/timing.py's median_time, each call
   followed by torch.cuda.synchronize() on CUDA; "x eager" is eager's time / the path's (above 1: faster than eager).

Each figure line starts with `update` (what benchmark/speed/gpu_check.sh keeps); the table follows a line `== table`.
The figure lines, failures and the table are also appended to --out. A case that fails prints `case NAME: failed: ...`
and the next case runs; a path that fails after eager ran prints the same with the path's name.

Setups: bench_*.py's builders where they exist (bench_hrac.build and filled_replays, bench_ris_sawyer.filled_replay
and agent_of, bench_goal_dqn.goal_dqn_agent, bench_hrac_keychest.fast_updates); 8 batches made beforehand, used in turn.
bench_hrac_keychest.fast_updates builds its agents and inputs on the CPU: on another device each agent is moved there and
each input tensor is copied there on its first use (then reused), so that part of keychest's time is a dictionary look-up
per argument. dgrl_hrac_keychest.py itself runs its controller (A2C) update compiled, not captured, under --fast
cudagraphs (its episode length varies; here it is always 500), and passes the TD3 delay switch as a device tensor there
(here a Python bool: two graphs); the controller's cudagraphs rows (path `cudagraphs*`) measure what capture would give.
"""

import argparse
import dataclasses
import functools
import itertools
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.utils._pytree import tree_map_only

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

FAST_PATHS = ("eager", "compile", "cudagraphs")  # every script's --fast choices
BATCHES = 8  # input batches made beforehand per case, used in turn
BLOCK_SECONDS = 0.2  # about this long per timed block (at eager's speed), 2 to 200 updates
CPU = torch.device("cpu")


# --- The cases: each builds (agent, step, make_fast) on a device ------------------------------------------------------


@dataclasses.dataclass
class Built:
    agent: object  # the script's agent dataclass: its modules and optimizers are compared
    step: Callable  # step(update): one update of `agent` by `update` (the script's function or make_fast's)
    make_fast: Callable  # make_fast(path): the update through --fast path


@dataclasses.dataclass
class Case:
    name: str
    what: str
    build: Callable  # build(device, rng) -> Built, called right after torch.manual_seed(0)
    captured: bool = True  # False: the script runs this update compiled, not captured, under --fast cudagraphs


def in_turn(inputs: list, call: Callable) -> Callable:
    """step(update) that calls call(update, item) with the items of `inputs` in turn."""
    count = itertools.count()
    return lambda update: call(update, inputs[next(count) % len(inputs)])


def with_fast(script, function, optimizers: list) -> Callable:
    return lambda path: script.fast_update(function, path, optimizers)


def to_device(tensors, device: torch.device):
    return tree_map_only(torch.Tensor, lambda tensor: tensor.to(device), tensors)


def ris(groups: int) -> Callable:
    def build(device, rng):
        import dgrl_ris as ris

        args = ris.Args(groups=groups)  # batch 2048
        state_dim, goal_dim, action_dim = 31, 31, 8  # Ant (bench_ris.py)
        agent = ris.make_agent(state_dim, goal_dim, action_dim, args, device)
        replay = ris.EpisodeReplay(60_000, state_dim, action_dim, goal_dim, CPU)  # bench_ris.py's 100 random episodes
        for _ in range(100):
            replay.add_episode(
                rng.normal(size=(600, state_dim)), rng.uniform(-1, 1, (600, action_dim)), rng.normal(size=(600, state_dim)),
                rng.normal(size=(600, goal_dim)),
            )  # fmt: skip
        fractions = (args.her_goal_frac, args.her_random_frac)
        batches = [replay.sample(args.batch_size, goal_dim, ris.ANT_THRESHOLD, *fractions) for _ in range(BATCHES)]
        optimizers = [agent.critic_optimizer, agent.high_optimizer, agent.actor_optimizer]
        step = in_turn(to_device(batches, device), lambda update, batch: update(agent, batch, args))
        return Built(agent, step, with_fast(ris, ris.ris_update, optimizers))

    return build


@functools.cache
def sawyer_replay(device: torch.device):
    """bench_ris_sawyer.py's replay of 20 rendered random-action episodes, made once per device."""
    import bench_ris_sawyer

    return bench_ris_sawyer.filled_replay(20, np.random.default_rng(0), device)


def ris_sawyer(groups: int) -> Callable:
    def build(device, rng):
        import bench_ris_sawyer

        import dgrl_ris_sawyer as sawyer

        args = sawyer.Args(groups=groups)  # batch 256
        agent = bench_ris_sawyer.agent_of(args, device)
        replay = sawyer_replay(device)
        batches = [replay.sample(args.batch_size, args.her_goal_frac, args.her_random_frac, rng) for _ in range(BATCHES)]
        optimizers = [agent.critic_optimizer, agent.high_optimizer, agent.actor_optimizer]
        step = in_turn(batches, lambda update, batch: update(agent, batch, args))
        return Built(agent, step, with_fast(sawyer, sawyer.ris_update, optimizers))

    return build


def hrac(level: str, groups: int) -> Callable:
    def build(device, rng):
        import bench_hrac

        import dgrl_hrac as hrac

        args, bounds, agent = bench_hrac.build(groups, str(device))  # AntMaze, batch 128
        controller_replay, manager_replay = bench_hrac.filled_replays(rng)
        if level == "controller":
            batches = [hrac.as_tensors(controller_replay.sample(args.batch_size, rng), device) for _ in range(BATCHES)]
            function, trained, extra = hrac.controller_update, agent.controller, ()
        else:
            batches = [
                hrac.manager_batch(manager_replay.sample(args.batch_size, rng), rng, bounds=bounds,
                                   correction_samples=args.correction_samples, device=device)
                for _ in range(BATCHES)
            ]  # fmt: skip
            function, trained, extra = hrac.manager_update, agent.manager, (torch.as_tensor(bounds, device=device),)
        step = in_turn(batches, lambda update, batch: update(agent, batch, args, *extra))
        return Built(agent, step, with_fast(hrac, function, [trained.critic_optimizer, trained.actor_optimizer]))

    return build


class CopiedOnce:
    """Tensor arguments copied to `device` on first use, the copy reused after (each original kept, so its id stays)."""

    def __init__(self, device: torch.device):
        self.device, self.copies = device, {}

    def copy(self, tensor: torch.Tensor) -> torch.Tensor:
        if id(tensor) not in self.copies:
            self.copies[id(tensor)] = (tensor, tensor.to(self.device))
        return self.copies[id(tensor)][1]

    def wrap(self, function: Callable) -> Callable:
        def on_device(agent, *args, **kwargs):
            args, kwargs = tree_map_only(torch.Tensor, self.copy, (args, kwargs))
            return function(agent, *args, **kwargs)

        return on_device


def move_agent(agent, device: torch.device) -> None:
    """The agent's modules moved to `device` in place (their parameters stay the objects the optimizers hold)."""
    for field in dataclasses.fields(agent):
        value = getattr(agent, field.name)
        if isinstance(value, torch.nn.Module):
            value.to(device)
    optimizers = [value for value in vars(agent).values() if isinstance(value, torch.optim.Optimizer)]
    if any(p.device != device for optimizer in optimizers for group in optimizer.param_groups for p in group["params"]):
        raise RuntimeError("an optimizer's parameters did not move with the agent's modules")


def keychest(*words: str) -> Callable:
    """The update of bench_hrac_keychest.fast_updates whose name holds all `words`."""

    def build(device, rng):
        import bench_hrac_keychest

        import dgrl_hrac_keychest as kc

        updates = bench_hrac_keychest.fast_updates(rng)  # seeds torch itself before each agent
        (name,) = [name for name in updates if all(word in name for word in words)]
        function, agent, call, optimizers = updates[name]
        make_fast = with_fast(kc, function, optimizers(agent))
        if device == CPU:
            return Built(agent, lambda update: call(update, agent), make_fast)
        move_agent(agent, device)
        inputs = CopiedOnce(device)
        return Built(agent, lambda update: call(inputs.wrap(update), agent), make_fast)

    return build


def random_transitions(gdqn, layout, size: int, rng: np.random.Generator, device: torch.device):
    """A td_update batch of uniformly random transitions, as a full replay of them (bench_goal_dqn.py's) gives."""
    cells, goals, actions = (rng.integers(n, size=size) for n in (layout.n_cells, layout.n_cells, len(gdqn.MOVES)))
    following = layout.next_cell[cells, actions]
    reached = following == goals
    columns = (np.stack([cells, following, goals], 1), actions, np.where(reached, 5.0, -1.0), reached)
    dtypes = (torch.int64, torch.int64, torch.float32, torch.float32)
    tensors = (torch.as_tensor(column, dtype=dtype, device=device) for column, dtype in zip(columns, dtypes, strict=True))
    return gdqn.Batch(*tensors)


def goal_dqn(update: str, groups: int) -> Callable:
    def build(device, rng):
        import bench_goal_dqn

        import dgrl_goal_dqn as gdqn

        args, agent = bench_goal_dqn.goal_dqn_agent(groups, False, device)  # SpiralWorld, batch 128, frozen phi
        layout = gdqn.MazeLayout(args.env_id)
        embedder = gdqn.CellEmbedder(layout, args.noise, device, rng)
        if update == "pretrain":
            walks = gdqn.random_walks(layout, args.rep_transitions, args.max_episode_steps, rng)
            walks = tuple(torch.as_tensor(column, device=device) for column in walks)
            rows = [torch.as_tensor(rng.integers(args.rep_transitions, size=args.rep_batch_size), device=device)
                    for _ in range(BATCHES)]  # fmt: skip
            inputs = [gdqn.pretrain_inputs(embedder, walks, batch_rows, args.rep) for batch_rows in rows]
            step = in_turn(inputs, lambda update, batch: update(agent, *batch))
            return Built(agent, step, with_fast(gdqn, gdqn.pretrain_step, [agent.rep_optimizer]))
        agent.rep.eval()  # the DQN phase of the default run: phi frozen, its cell table computed once
        agent.rep.requires_grad_(False)
        table = gdqn.cell_table(agent.rep, embedder)
        batches = [random_transitions(gdqn, layout, args.batch_size, rng, device) for _ in range(BATCHES)]
        inputs = [(batch, table, gdqn.td_inputs(embedder, batch, table, False, args.double_dqn)) for batch in batches]
        step = in_turn(inputs, lambda update, batch: update(agent, *batch, args))
        return Built(agent, step, with_fast(gdqn, gdqn.td_update, [agent.q_optimizer]))

    return build


def amigo(update: str, groups: int) -> Callable:
    """bench_amigo.py's batches: rollouts of the reset frames with random goals, actions, rewards and ends."""

    def build(device, rng):
        import dgrl_amigo as amigo

        args = amigo.Args(groups=groups)  # KeyCorridorS3R3: 8 rollouts of 100 steps; 150 goal outcomes
        envs = amigo.MiniGridVecEnv(args.env_id, args.batch_envs)
        cells, t, b = envs.width * envs.height, args.num_steps, args.batch_envs
        agent = amigo.make_agent(envs.width, envs.height, envs.n_actions, args, device)
        obs, _ = envs.reset(seed=0)
        grids, carried = obs["grid"], obs["carried"]

        def student_batch():
            rollout = {
                "grids": np.repeat(grids[None], t, 0),
                "carried": np.repeat(carried[None], t, 0),
                "goal_frames": np.repeat(grids[None], t, 0),
                "goals": rng.integers(cells, size=(t, b)),
                "actions": rng.integers(envs.n_actions, size=(t, b)),
                "logps": np.full((t, b), -np.log(envs.n_actions), dtype=np.float32),
                "rewards": rng.random((t, b), dtype=np.float32),
                "dones": (rng.random((t, b)) < 0.01).astype(np.float32),
            }
            last = {"grids": grids, "carried": carried, "goal_frames": grids, "goals": rng.integers(cells, size=b)}
            return amigo.student_batch(rollout, last, device)

        def teacher_batch():
            n = args.teacher_batch_size
            outcomes = {"frame": grids[rng.integers(b, size=n)], "goal": rng.integers(cells, size=n),
                        "logp": np.full(n, -np.log(cells), dtype=np.float32)}  # fmt: skip
            return amigo.teacher_tensors(outcomes, rng.choice([-0.3, 0.7, 1.0], size=n), device)

        make_batch, function, optimizer = {
            "student": (student_batch, amigo.student_update, agent.student_optimizer),
            "teacher": (teacher_batch, amigo.teacher_update, agent.teacher_optimizer),
        }[update]
        batches = [make_batch() for _ in range(BATCHES)]

        def make_fast(path):
            amigo.learning_rates_as_tensors([optimizer], as_tensors=path != "eager")  # as the script does
            return amigo.fast_update(function, path, [optimizer])

        return Built(agent, in_turn(batches, lambda update, batch: update(agent, batch, args)), make_fast)

    return build


def mnist(groups: int) -> Callable:
    def build(device, rng):
        import dgrl_mnist as mnist

        args = mnist.Args(groups=groups)  # batch 128
        model = mnist.make_model(args, device)
        images = torch.rand(BATCHES, args.batch_size, 3, 28, 28).to(device)  # drawn on the CPU: the same on every device
        step = in_turn(list(images), lambda update, batch: update(model, batch))
        return Built(model, step, with_fast(mnist, mnist.train_step, [model.optimizer]))

    return build


A2C = "dgrl_hrac_keychest.py controller_update (A2C), 500 steps"  # the script compiles it, never captures it
CASES = [
    Case("ris_G0", "dgrl_ris.py ris_update, Ant sizes (state 31, goal 31, action 8), batch 2048, RIS", ris(0)),
    Case("ris_G16", "dgrl_ris.py ris_update, Ant sizes, batch 2048, RIS+DGRL G16", ris(16)),
    Case("ris_sawyer_G0", "dgrl_ris_sawyer.py ris_update, 84x84 pixels, batch 256, RIS", ris_sawyer(0)),
    Case("ris_sawyer_G16", "dgrl_ris_sawyer.py ris_update, 84x84 pixels, batch 256, RIS+DGRL G16", ris_sawyer(16)),
    Case("hrac_controller_G0", "dgrl_hrac.py controller_update, AntMaze, batch 128, HRAC", hrac("controller", 0)),
    Case("hrac_controller_G16", "dgrl_hrac.py controller_update, AntMaze, batch 128, DGRL G16", hrac("controller", 16)),
    Case("hrac_manager_G0", "dgrl_hrac.py manager_update (manager_batch), AntMaze, batch 128, HRAC", hrac("manager", 0)),
    Case("hrac_manager_G16", "dgrl_hrac.py manager_update, AntMaze, batch 128, DGRL G16", hrac("manager", 16)),
    Case("keychest_manager", "dgrl_hrac_keychest.py manager_update (TD3), batch 64", keychest("TD3")),
    Case("keychest_controller_G0", f"{A2C}, G0 (the script: compiled, never captured)", keychest("A2C", "G0"), False),
    Case("keychest_controller_G16", f"{A2C}, G16 (the script: compiled, never captured)", keychest("A2C", "G16"), False),
    Case("keychest_autoencoder", "dgrl_hrac_keychest.py goal_autoencoder_update, batch 256, G16", keychest("autoencoder")),
    Case("goal_dqn_td_G0", "dgrl_goal_dqn.py td_update, frozen phi's table, batch 128, G0", goal_dqn("td", 0)),
    Case("goal_dqn_td_G16", "dgrl_goal_dqn.py td_update, frozen phi's table, batch 128, DGRL G16", goal_dqn("td", 16)),
    Case("goal_dqn_pretrain_G0", "dgrl_goal_dqn.py pretrain_step (infomax), batch 128, G0", goal_dqn("pretrain", 0)),
    Case("goal_dqn_pretrain_G16", "dgrl_goal_dqn.py pretrain_step (infomax), batch 128, DGRL G16", goal_dqn("pretrain", 16)),
    Case("amigo_student_G0", "dgrl_amigo.py student_update, KeyCorridorS3R3, 8 x 100 frames, AMIGo", amigo("student", 0)),
    Case("amigo_student_G16", "dgrl_amigo.py student_update, KeyCorridorS3R3, 8 x 100 frames, DGRL", amigo("student", 16)),
    Case("amigo_teacher", "dgrl_amigo.py teacher_update, KeyCorridorS3R3, 150 goal outcomes", amigo("teacher", 16)),
    Case("mnist_G0", "dgrl_mnist.py train_step, batch 128, continuous autoencoder", mnist(0)),
    Case("mnist_G2", "dgrl_mnist.py train_step, batch 128, DGRL G2", mnist(2)),
]


# --- Measuring --------------------------------------------------------------------------------------------------------


def training_tensors(agent, prefix: str = "") -> dict[str, torch.Tensor]:
    """Every parameter, buffer and optimizer state tensor of an agent dataclass, by name (an optimizer's state keyed by
    its parameters' positions in its groups), as tests/conftest.py's training_tensors."""
    found = {}
    for field in dataclasses.fields(agent):
        value, name = getattr(agent, field.name), prefix + field.name
        if isinstance(value, torch.nn.Module):
            found |= {f"{name}.{key}": tensor for key, tensor in value.state_dict().items()}
        elif isinstance(value, torch.optim.Optimizer):
            parameters = [p for group in value.param_groups for p in group["params"]]
            for index, parameter in enumerate(parameters):
                state = value.state.get(parameter, {})
                found |= {f"{name}.{index}.{key}": item for key, item in state.items() if isinstance(item, torch.Tensor)}
        elif dataclasses.is_dataclass(value):
            found |= training_tensors(value, f"{name}.")
    return found


def snapshot(agent) -> dict[str, torch.Tensor]:
    return {key: tensor.detach().to(CPU, torch.float64, copy=True) for key, tensor in training_tensors(agent).items()}


def largest_difference(got: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> tuple[float, str]:
    """(max over tensors of max|a - b| / max(max|b|, 1e-12), that tensor's name); b: `expected`'s tensor."""
    if got.keys() != expected.keys():
        raise ValueError(f"different tensors: {sorted(got.keys() ^ expected.keys())[:4]}")
    names = [name for name in expected if expected[name].numel()]
    ratios = torch.stack([
        (got[name] - expected[name]).abs().max() / expected[name].abs().max().clamp_min(1e-12) for name in names
    ])  # fmt: skip
    largest = int(ratios.nan_to_num(nan=torch.inf).argmax())
    return ratios[largest].item(), names[largest] if ratios[largest] != 0 else "(all equal)"


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def fresh(case: Case, device: torch.device) -> Built:
    torch._dynamo.reset()  # compiled code of the previous build holds guards on its agent
    torch.manual_seed(0)
    return case.build(device, np.random.default_rng(0))


def run_updates(built: Built, update: Callable, updates: int, device: torch.device) -> float:
    """`updates` updates after torch.manual_seed(7); returns the seconds per update of all but the first."""
    torch.manual_seed(7)
    built.step(update)
    synchronize(device)
    start = time.perf_counter()
    for _ in range(updates - 1):
        built.step(update)
    synchronize(device)
    return (time.perf_counter() - start) / max(updates - 1, 1)


@dataclasses.dataclass
class Row:
    case: str
    path: str
    seconds: float
    speedup: float
    difference: str  # "1.2e-07 critic.0.weight", or "(reference)" for eager
    cpu_difference: str = ""


def measure(case: Case, path: str, device: torch.device, options, repeats: int | None = None) -> tuple:
    """(tensors after --updates updates, seconds per update, repeats per timed block) of `case` through `path`."""
    print(f"  {path}: {options.updates} updates" + ("" if path == "eager" else " (compiling first)"), flush=True)
    built = fresh(case, device)
    update = built.make_fast(path)
    estimate = run_updates(built, update, options.updates, device)
    tensors = snapshot(built.agent)
    repeats = repeats or int(np.clip(BLOCK_SECONDS / max(estimate, 1e-9), 2, 200))

    def timed():
        built.step(update)
        synchronize(device)

    return tensors, median_time(timed, repeats), repeats


def run_case(case: Case, paths: list[str], device: torch.device, options, say: Callable) -> list[Row]:
    """The case's rows, eager first (the reference); a failing path other than eager gives a line and no row."""
    torch.set_flush_denormal(case.name.startswith("hrac_"))  # as dgrl_hrac.py does (its critics' weight decay)
    reference, eager_seconds, repeats = measure(case, "eager", device, options)
    cpu_difference = ""
    if device.type == "cuda":
        print("  eager on the CPU: the reference of GPU vs CPU", flush=True)
        built = fresh(case, CPU)
        run_updates(built, built.make_fast("eager"), options.updates, CPU)
        cpu_difference = "{:.1e} {}".format(*largest_difference(reference, snapshot(built.agent)))
    rows = [Row(case.name, "eager", eager_seconds, 1.0, "(reference)", cpu_difference)]
    for path in paths[1:]:
        try:
            tensors, seconds, _ = measure(case, path, device, options, repeats)
        except Exception as error:  # any failure of one path is reported and the next one runs
            say(f"case {case.name}: failed: {path}: {one_line(error)}")
            continue
        difference = "{:.1e} {}".format(*largest_difference(tensors, reference))
        label = path if case.captured or path != "cudagraphs" else "cudagraphs*"  # * the script does not capture it
        rows.append(Row(case.name, label, seconds, eager_seconds / seconds, difference))
    for row in rows:
        gpu_cpu = f", eager GPU vs CPU {row.cpu_difference}" if row.cpu_difference else ""
        say(f"update {row.case:<24} {row.path:<10} {row.seconds * 1e3:9.3f} ms/update {row.speedup:6.2f}x eager, "
            f"largest rel. diff vs eager: {row.difference}{gpu_cpu} ({device}, {options.threads} thread(s))")  # fmt: skip
    return rows


def one_line(error: Exception) -> str:
    text = f"{type(error).__name__}: {error}".strip().splitlines()
    return text[0][:300] if text else type(error).__name__


def table(rows: list[Row], cuda: bool) -> list[str]:
    header = ["case", "path", "ms/update", "x eager", "largest rel. diff vs eager (tensor)"]
    header += ["eager GPU vs CPU (tensor)"] if cuda else []
    cells = [
        [row.case, row.path, f"{row.seconds * 1e3:.3f}", f"{row.speedup:.2f}", row.difference]
        + ([row.cpu_difference] if cuda else [])
        for row in rows
    ]
    widths = [max(len(line[i]) for line in [header, *cells]) for i in range(len(header))]
    lines = [[cell.ljust(width) for cell, width in zip(line, widths, strict=True)] for line in [header, *cells]]
    return [" | ".join(line).rstrip() for line in lines]


def main() -> None:
    cases = {case.name: case for case in CASES}
    epilog = "cases:\n" + "\n".join(f"  {case.name:<24} {case.what}" for case in CASES)
    parser = argparse.ArgumentParser(description="\n\n".join(__doc__.split("\n\n")[:2]), epilog=epilog,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="default: %(default)s")
    parser.add_argument("--paths", nargs="+", choices=FAST_PATHS, help="default: eager compile, and cudagraphs on CUDA")
    parser.add_argument("--cases", nargs="+", choices=list(cases), default=list(cases), metavar="NAME",
                        help="the cases to run (default: all; their names below)")  # fmt: skip
    parser.add_argument("--updates", type=int, default=10, help="updates before the comparison (default: %(default)s)")
    parser.add_argument("--out", default="gpu_updates.txt", help="figure lines appended here (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default: %(default)s)")
    options = parser.parse_args()
    device = torch.device(options.device)
    cuda = device.type == "cuda"
    if cuda and not torch.cuda.is_available():
        parser.error(f"torch {torch.__version__} sees no CUDA device")
    if cuda and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())  # as tensors name it (cuda:0), for comparisons
    paths = options.paths or ["eager", "compile", *(["cudagraphs"] if cuda else [])]
    if "cudagraphs" in paths and not cuda:
        parser.error("cudagraphs needs a CUDA device")
    if options.updates < 1:
        parser.error("--updates must be >= 1")
    paths = ["eager", *(path for path in FAST_PATHS[1:] if path in paths)]  # eager: always, first (the reference)
    torch.set_num_threads(options.threads)
    torch.backends.cudnn.deterministic = True  # every script's default (--torch-deterministic)

    with open(options.out, "a") as out:

        def say(line: str) -> None:
            print(line, flush=True)
            out.write(line + "\n")
            out.flush()

        where = torch.cuda.get_device_name(device) if cuda else "CPU"
        say(f"gpu_updates: torch {torch.__version__}, {where}, paths {' '.join(paths)}, {options.updates} updates, "
            f"{options.threads} thread(s), {time.strftime('%Y-%m-%dT%H:%M:%S')}")  # fmt: skip
        rows = []
        for name in options.cases:
            case = cases[name]
            print(f"case {name}: {case.what}", flush=True)
            try:
                rows += run_case(case, paths, device, options, say)
            except Exception as error:  # a failing case is reported and the next one runs
                say(f"case {name}: failed: {one_line(error)}")
        say("== table")
        for line in table(rows, cuda):
            say(line)
        if any(row.path == "cudagraphs*" for row in rows):
            say("cudagraphs*: an update the script runs compiled, not captured, under --fast cudagraphs")


if __name__ == "__main__":
    main()
