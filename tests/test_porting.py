"""docs/porting.md, run: the page's code blocks, read from the page, build three tiny goal-conditioned agents (an
actor-critic, a DQN, a hierarchical agent's low level), which train on a toy goal task; the page's claims are checked on
them, and the same checks are shown to fail on copies of the code edited into something that does not do what the page
says.

The page's blocks are fenced ```python or ```diff blocks whose first line is `# porting: NAME`. A diff block holds two
agents: its ` ` and `-` lines are the plain agent, its ` ` and `+` lines the DGRL agent. The `plain` python block belongs
to both, every other python block to the DGRL agent. The blocks run in page order, in one namespace per agent.

The toy task: a point in the square [-0.75, 0.75]^2 must reach a goal in one step. Goals are factorial, x and y each one
of 4 levels (16 goals); the next state is the state moved by half the action (an actor-critic's tanh action, or a DQN's
move of 0.5 in x, y or both: one level), clipped to the square; the reward is minus the distance to the goal, and every
step ends its episode, so the critic's target is the reward itself and its loss can fall within a few hundred updates.
The actor-critics' states are uniform in the square; the DQN's, which it quantizes too, are the 16 lattice points, as
dgrl_goal_dqn.py's are the cells of a maze. The codebook is tiny (G = 4 factors of a 16-d embedding, 16 codes).
"""

import re
from pathlib import Path

import pytest
import torch

from vq import active_codes, perplexity

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "porting.md"
FENCE = re.compile(r"^```(python|diff)\n(.*?)^```$", re.S | re.M)
MARK = re.compile(r"# porting: (\w+)")
KINDS = ("actor_critic", "dqn", "hierarchical")  # the page's three agents, one diff block each

LEVELS = torch.tensor([-0.75, -0.25, 0.25, 0.75])  # each goal coordinate takes one of these values
EDGE = 0.75  # the square's half-width
MOVES = torch.tensor([[x, y] for x in (-1.0, 0.0, 1.0) for y in (-1.0, 0.0, 1.0)])  # the DQN's 9 actions
HIDDEN, BATCH, UPDATES, SYNC_EVERY = 32, 64, 200, 25
LR, ENCODER_LR = 3e-3, 1e-3  # a few hundred updates must show learning: 3x the page's lr, 10x its encoder lr
N_EMBED = 16
VQ = {"embed_dim": 16, "groups": 4, "n_embed": N_EMBED, "dead_code_steps": 50}  # the restart after 50, as goal-DQN's
PROBED = 3  # the first updates whose networks' inputs are traced back to the encoder
N_CANDIDATES = 4  # the relabel check's candidate subgoals
# The one call per update whose goal input may carry gradient to the encoder: the online critic's (the Q-network's) in
# its TD loss, where z_q keeps its straight-through gradient; every other call sees z_q detached.
STRAIGHT_THROUGH = {"actor_critic": ["critic"], "dqn": ["q_network"], "hierarchical": ["critic"]}


# --- The page's code --------------------------------------------------------------------------------------------------


def page_blocks(text: str) -> list[tuple[str, str, str, int]]:
    """(name, the plain agent's code, the DGRL agent's code, the page's line of the block's first line) of each marked
    block. A line of one agent is a blank line in the other's code, so that tracebacks give the page's line numbers."""
    blocks = []
    for match in FENCE.finditer(text):
        language, body = match.groups()
        lines = body.splitlines()
        marker = MARK.fullmatch(lines[0][1:] if language == "diff" else lines[0])
        if marker is None:
            continue
        name, first_line = marker.group(1), text.count("\n", 0, match.start(2)) + 1
        if language == "python":
            blocks.append((name, body if name == "plain" else "", body, first_line))
            continue
        plain, dgrl = [], []
        for line in lines:
            sign, code = (line[:1], line[1:]) if line else (" ", "")
            assert sign in " -+", f"docs/porting.md:{first_line}, block {name}: a diff line starts with {sign!r}"
            plain.append(code if sign in " -" else "")
            dgrl.append(code if sign in " +" else "")
        blocks.append((name, "\n".join(plain), "\n".join(dgrl), first_line))
    return blocks


def build(side: str, edits: tuple[tuple[str, str, str], ...] = ()) -> dict:
    """The namespace of one agent ("plain" or "dgrl") after running the page's blocks. `edits` (block, old, new) first
    change the DGRL code, each `old` found exactly once in its block."""
    blocks = page_blocks(PAGE.read_text())
    for block, old, _ in edits:
        (code,) = [dgrl for name, _, dgrl, _ in blocks if name == block]
        assert code.count(old) == 1, f"block {block} holds {code.count(old)} copies of {old!r}"
    namespace = {"__name__": "porting"}
    for name, plain, dgrl, first_line in blocks:
        code = plain if side == "plain" else dgrl
        for block, old, new in edits:
            code = code.replace(old, new) if block == name else code
        exec(compile("\n" * (first_line - 1) + code, str(PAGE), "exec"), namespace)
    return namespace


# --- The toy task -----------------------------------------------------------------------------------------------------


def lattice(n: int) -> torch.Tensor:
    return LEVELS[torch.randint(len(LEVELS), (n, 2))]


def goals_and_states(kind: str, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    return lattice(n), lattice(n) if kind == "dqn" else (torch.rand(n, 2) * 2 - 1) * EDGE


def step(states: torch.Tensor, actions: torch.Tensor, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(next states, rewards): half the action added, clipped to the square; minus the distance to the goal."""
    next_states = (states + 0.5 * actions).clamp(-EDGE, EDGE)
    return next_states, -torch.linalg.vector_norm(next_states - goals, dim=-1)


def random_batch(kind: str) -> tuple[tuple, torch.Tensor]:
    """(batch (states, actions, rewards, next states, done), goals) of random actions; a DQN's actions are move indices."""
    goals, states = goals_and_states(kind, BATCH)
    actions = torch.randint(len(MOVES), (BATCH,)) if kind == "dqn" else torch.rand(BATCH, 2) * 2 - 1
    next_states, rewards = step(states, MOVES[actions] if kind == "dqn" else actions, goals)
    return (states, actions, rewards, next_states, torch.ones(BATCH)), goals  # every step ends its episode


# --- Training with probes ---------------------------------------------------------------------------------------------


class Probe:
    """Hooks on an agent's networks and quantizers. For each network call while `tracing` it records the network's name
    if its input carries gradient back to the encoder; it counts the quantizers' EMA steps (calls in training mode with
    update=True) and snapshots their buffers."""

    def __init__(self, networks: dict, quantizers: list, encoder_parameters: list):
        self.encoder_parameters, self.quantizers = encoder_parameters, quantizers
        self.tracing, self.connected, self.ema_steps = False, [], 0
        for name, network in networks.items():
            network.register_forward_pre_hook(lambda module, inputs, name=name: self.trace(name, inputs[0]))
        for quantizer in quantizers:
            quantizer.register_forward_pre_hook(self.count, with_kwargs=True)

    def trace(self, name: str, inputs: torch.Tensor) -> None:
        if self.tracing and self.encoder_parameters and inputs.requires_grad:
            grads = torch.autograd.grad(inputs.sum(), self.encoder_parameters, allow_unused=True, retain_graph=True)
            if any(grad is not None and grad.abs().sum() > 0 for grad in grads):
                self.connected.append(name)

    def count(self, module, args, kwargs) -> None:
        self.ema_steps += int(module.training and kwargs.get("update", True))

    def buffers(self) -> list[torch.Tensor]:
        return [buffer.clone() for quantizer in self.quantizers for buffer in quantizer.buffers()]


def make_agent(kind: str, namespace: dict):
    """(agent, the networks that take the goal, update(batch, goals) -> metrics, acting policy(states, goals), the
    online encoder or None), built by the page's functions."""
    flags = {"hidden": HIDDEN, "lr": LR}
    if "GoalEncoder" in namespace:  # the DGRL agent
        flags |= VQ | ({} if kind == "dqn" else {"encoder_lr": ENCODER_LR})  # the DQN's encoder is in its one optimizer
    if kind == "dqn":
        agent = namespace["make_dqn"](2, len(MOVES), **flags)
        networks = {"q_network": agent.q_network, "target_q_network": agent.target_q_network}
        update = lambda batch, goals: namespace["dqn_update"](agent, batch, goals)  # noqa: E731
        return agent, networks, update, lambda s, g: MOVES[namespace["greedy"](agent, s, g)], agent.encoder
    if kind == "actor_critic":
        agent = level = namespace["make_actor_critic"](2, 2, 2, **flags)
        update = lambda batch, goals: namespace["actor_critic_update"](agent, batch, goals)  # noqa: E731
    else:
        agent = namespace["make_hierarchical"](2, 2, 2, 2, **flags)
        level = agent.controller  # the subgoals are absolute and held fixed: the next subgoal is the subgoal
        update = lambda batch, subgoals: namespace["controller_update"](agent, batch, subgoals, subgoals)  # noqa: E731
    networks = {name: getattr(level, name) for name in ("actor", "critic", "actor_target", "critic_target")}
    return agent, networks, update, lambda s, g: namespace["act"](level, s, g), level.encoder


def train(kind: str, namespace: dict) -> dict:
    """UPDATES updates on random batches of the toy task (the DQN syncs its targets every SYNC_EVERY), then acting;
    returns what the checks read."""
    torch.manual_seed(0)
    torch.set_num_threads(1)
    agent, networks, update, policy, encoder = make_agent(kind, namespace)
    quantizers = [] if encoder is None else [encoder.vq] + ([agent.target_encoder.vq] if kind == "dqn" else [])
    probe = Probe(networks, quantizers, [] if encoder is None else list(encoder.encoder.parameters()))
    test_goals, test_states = goals_and_states(kind, 1000)

    def distance() -> float:  # the policy's mean distance to the goal after its one step
        with torch.no_grad():
            return -step(test_states, policy(test_states, test_goals), test_goals)[1].mean().item()

    run = {"distance_before": distance(), "losses": [], "ema_steps": [], "codebook_moved": [], "connected": []}
    for index in range(UPDATES):
        batch, goals = random_batch(kind)
        before, steps_before = probe.buffers(), probe.ema_steps
        probe.tracing, probe.connected = index < PROBED, []
        metrics = update(batch, goals)
        probe.tracing = False
        if kind == "dqn" and (index + 1) % SYNC_EVERY == 0:
            namespace["sync_targets"](agent)
        run["losses"].append(metrics["td_loss" if kind == "dqn" else "critic_loss"].item())
        run["ema_steps"].append(probe.ema_steps - steps_before)
        run["codebook_moved"].append(encoder is not None and not torch.equal(before[0], encoder.vq.codebook))
        if index < PROBED:
            run["connected"].append(probe.connected)
    run["codes"] = metrics.get("codes")
    run["encoder_gradient"] = encoder is not None and any(
        parameter.grad is not None and parameter.grad.abs().sum() > 0 for parameter in encoder.encoder.parameters()
    )

    before, steps_before = probe.buffers(), probe.ema_steps  # acting: the policy, then (hierarchical) relabelling
    run["distance_after"] = distance()
    if kind == "hierarchical":
        run["relabel_accuracy"] = relabel_accuracy(namespace, agent)
    run["acting_moved_codebook"] = probe.ema_steps > steps_before or any(
        not torch.equal(old, new) for old, new in zip(before, probe.buffers(), strict=True)
    )
    if kind == "dqn" and encoder is not None:
        namespace["sync_targets"](agent)
        run["target_codebook_copied"] = torch.equal(agent.target_encoder.vq.codebook, encoder.vq.codebook)
    return run


def relabel_accuracy(namespace: dict, agent, n: int = 200, k: int = 3) -> float:
    """The share of k-step segments, acted by the controller towards a subgoal, whose subgoal the page's relabel picks
    among N_CANDIDATES lattice goals of distinct x (the subgoal one of them)."""
    xs = torch.stack([torch.randperm(len(LEVELS))[:N_CANDIDATES] for _ in range(n)])
    candidates = torch.stack([LEVELS[xs], LEVELS[torch.randint(len(LEVELS), (n, N_CANDIDATES))]], -1)  # (n, C, 2)
    subgoals = candidates[torch.arange(n), torch.randint(N_CANDIDATES, (n,))]
    states, actions = [(torch.rand(n, 2) * 2 - 1) * EDGE], []
    for _ in range(k):
        actions.append(namespace["act"](agent.controller, states[-1], subgoals))
        states.append(step(states[-1], actions[-1], subgoals)[0])
    chosen = namespace["relabel"](agent, torch.stack(states[:k], 1), torch.stack(actions, 1), candidates)
    return (chosen == subgoals).all(-1).float().mean().item()


def failures(kind: str, run: dict) -> list[str]:
    """The names of the checks one trained agent fails."""
    failed = []
    if not sum(run["losses"][-20:]) < 0.5 * sum(run["losses"][:20]):
        failed.append("loss falls")
    if not run["distance_after"] < 0.8 * run["distance_before"]:
        failed.append("goals reached")
    if run["codes"] is None or not perplexity(run["codes"], N_EMBED) > N_EMBED / 4:
        failed.append("codes used")
    if run["connected"] != [STRAIGHT_THROUGH[kind]] * PROBED or not run["encoder_gradient"]:
        failed.append("gradient paths")
    if run["ema_steps"] != [1] * UPDATES or not all(run["codebook_moved"]):
        failed.append("one EMA step per update")
    if run["acting_moved_codebook"]:
        failed.append("acting leaves the codebook")
    if kind == "dqn" and not run.get("target_codebook_copied"):
        failed.append("targets copy the codebook")
    if kind == "hierarchical" and not run["relabel_accuracy"] > 2 / N_CANDIDATES:  # twice chance
        failed.append("relabel finds the subgoal")
    return failed


# --- The tests --------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dgrl_runs() -> dict[str, dict]:
    namespace = build("dgrl")
    return {kind: train(kind, namespace) for kind in KINDS}


def test_the_page_holds_its_blocks_in_porting_order():
    blocks = page_blocks(PAGE.read_text())
    assert [name for name, *_ in blocks] == ["plain", "encoder", *KINDS]
    for name, plain, dgrl, _ in blocks[2:]:
        assert plain.strip() and dgrl.strip() and plain != dgrl, name


@pytest.mark.parametrize("kind", KINDS)
def test_the_pages_dgrl_agent_passes_every_check(dgrl_runs, kind):
    run = dgrl_runs[kind]
    assert failures(kind, run) == [], {key: value for key, value in run.items() if key != "codes"}
    assert active_codes(run["codes"], N_EMBED) >= N_EMBED - 2  # the restart keeps (nearly) every code in use


@pytest.mark.parametrize("kind", KINDS)
def test_the_pages_plain_agent_trains(kind):
    """The diffs' `-` side is a working plain agent: it learns the same task (it has no codebook to check)."""
    failed = failures(kind, train(kind, build("plain")))
    assert not {"loss falls", "goals reached", "acting leaves the codebook", "relabel finds the subgoal"} & set(failed)


# name: ((block, old, new) edit of the page's DGRL code, the agent it is run on, the check that must then fail)
MUTATIONS = {
    "learning step removed": (("dqn", "learn(agent.optimizer, td_loss + representation_loss)", "None"), "dqn", "loss falls"),
    "z_q detached before the Q-network": (("dqn", "z_q.chunk(2)", "z_q.detach().chunk(2)"), "dqn", "gradient paths"),
    "no reconstruction": (("dqn", "F.mse_loss(agent.encoder.decoder(z_q), observations) + ", ""), "dqn", "goals reached"),
    "two EMA steps per update": (
        ("actor_critic", "z_q.detach(), extra_loss", "agent.encoder(goals, update=True)[0].detach(), extra_loss"),
        "actor_critic",
        "one EMA step per update",
    ),
    "acting updates the codebook": (("dqn", "update=False)[0]", "update=True)[0]"), "dqn", "acting leaves the codebook"),
    "target codebook not copied": (
        ("dqn", "update_target(agent.target_encoder, agent.encoder)", "None"),
        "dqn",
        "targets copy the codebook",
    ),
}


@pytest.mark.parametrize("mutation", MUTATIONS)
def test_the_checks_fail_on_page_code_that_does_not_do_what_the_page_says(mutation):
    edit, kind, check = MUTATIONS[mutation]
    assert check in failures(kind, train(kind, build("dgrl", (edit,))))


def test_without_the_detach_the_actors_backward_pass_fails_loudly():
    """td_step detaches z_q before the actor's loss. Without it the actor's backward pass runs into the encoder's graph,
    which the critic's backward pass has freed: an error, not a silent gradient."""
    edit = ("actor_critic", "goal_in = goal_in.detach()", "pass")
    with pytest.raises(RuntimeError, match="backward through the graph a second time"):
        train("actor_critic", build("dgrl", (edit,)))


def test_without_the_dead_code_restart_the_toy_codebook_collapses(monkeypatch):
    """The paper's bottleneck, no restart: the encoder's first outputs are far smaller than the N(0, 1) codes, one code
    wins nearly every factor, and the codes-used check fails."""
    monkeypatch.setitem(VQ, "dead_code_steps", 0)
    run = train("hierarchical", build("dgrl"))
    assert "codes used" in failures("hierarchical", run)
    assert perplexity(run["codes"], N_EMBED) < 2 and active_codes(run["codes"], N_EMBED) <= 2
