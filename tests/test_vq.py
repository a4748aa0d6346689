"""vq.py: the grouped, shared-codebook EMA quantizer, checked against an independent numpy reference."""

import itertools

import numpy as np
import pytest
import torch
import torch.nn as nn

from tests.conftest import NoHostSync
from vq import (
    VectorQuantizerEMA,
    active_codes,
    code_counts,
    code_sums,
    factor_match,
    make_target,
    perplexity,
    update_target,
)


def numpy_vqvae_ema_step(codebook, ema_count, ema_sum, vectors, decay, eps):
    """Textbook VQ-VAE EMA step (van den Oord et al. 2017, appendix A.1) on rows of `vectors`, in float64.

    Returns (indices, codes used for the output, new codebook, new counts, new sums).
    """
    distances = ((vectors[:, None, :] - codebook[None, :, :]) ** 2).sum(-1)
    indices = distances.argmin(1)
    one_hot = np.eye(len(codebook))[indices]
    ema_count = decay * ema_count + (1 - decay) * one_hot.sum(0)
    ema_sum = decay * ema_sum + (1 - decay) * one_hot.T @ vectors
    total = ema_count.sum()
    smoothed = (ema_count + eps) / (total + len(codebook) * eps) * total
    return indices, codebook[indices], ema_sum / smoothed[:, None], ema_count, ema_sum


def set_codebook(vq: VectorQuantizerEMA, codebook: np.ndarray) -> None:
    """Put the module in the consistent initial state around a chosen codebook."""
    vq.codebook.copy_(torch.as_tensor(codebook, dtype=torch.float32))
    vq.ema_sum.copy_(vq.codebook)
    vq.ema_count.fill_(1.0)


def state(vq: VectorQuantizerEMA) -> dict[str, torch.Tensor]:
    return {name: buffer.clone() for name, buffer in vq.named_buffers()}


def assert_state_equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=0, atol=0, msg=name)


# --- the EMA update ---------------------------------------------------------------------------------------------------


def test_one_ema_step_matches_hand_computation():
    rng = np.random.default_rng(0)
    dim, n_embed, groups, batch, decay, eps, beta = 6, 5, 3, 4, 0.9, 1e-5, 0.25
    codebook = rng.normal(size=(n_embed, dim // groups))
    z = rng.normal(size=(batch, dim))
    vq = VectorQuantizerEMA(dim, n_embed, groups, beta=beta, decay=decay, eps=eps)
    set_codebook(vq, codebook)

    quantized, loss, indices = vq(torch.as_tensor(z, dtype=torch.float32))

    segments = z.reshape(batch * groups, dim // groups)
    ref_idx, ref_codes, ref_codebook, ref_count, ref_sum = numpy_vqvae_ema_step(
        codebook, np.ones(n_embed), codebook.copy(), segments, decay, eps
    )
    np.testing.assert_array_equal(indices.numpy(), ref_idx.reshape(batch, groups))
    np.testing.assert_allclose(quantized.numpy(), ref_codes.reshape(batch, dim), atol=1e-6)
    np.testing.assert_allclose(loss.item(), beta * ((segments - ref_codes) ** 2).sum(1).mean(), rtol=1e-5)
    np.testing.assert_allclose(vq.codebook.numpy(), ref_codebook, atol=1e-6)
    np.testing.assert_allclose(vq.ema_count.numpy(), ref_count, atol=1e-6)
    np.testing.assert_allclose(vq.ema_sum.numpy(), ref_sum, atol=1e-6)


def test_selected_code_moves_as_in_the_paper():
    """With one segment per code and the consistent init, e <- eta * e + (1 - eta) * c exactly (paper, section 3)."""
    eta = 0.8
    codebook = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    z = np.array([[1.0, 0.5, 9.0, 1.0], [-1.0, 9.0, 9.5, 10.5]])  # segments near codes 0, 1 | 2, 3
    vq = VectorQuantizerEMA(dim=4, n_embed=4, groups=2, decay=eta)
    set_codebook(vq, codebook)
    _, _, indices = vq(torch.as_tensor(z, dtype=torch.float32))
    assert indices.tolist() == [[0, 1], [2, 3]]
    np.testing.assert_allclose(vq.codebook.numpy(), eta * codebook + (1 - eta) * z.reshape(4, 2), atol=1e-5)


def test_groups_share_one_pooled_update():
    """G segments of a batch of B count as B*G samples of ONE update: the decay is applied once, not G times."""
    dim, n_embed, groups, batch, decay = 8, 16, 4, 32, 0.9
    vq = VectorQuantizerEMA(dim, n_embed, groups, decay=decay)
    vq(torch.randn(batch, dim))
    torch.testing.assert_close(vq.ema_count.sum(), torch.tensor(decay * n_embed + (1 - decay) * batch * groups))


def test_grouped_equals_plain_vq_on_the_segments():
    """q(z, L, G) on (B, dim) behaves as G=1 on the (B*G, dim/G) segments: same codes, losses and codebook path."""
    dim, n_embed, groups, batch = 12, 7, 4, 10
    torch.manual_seed(3)
    grouped = VectorQuantizerEMA(dim, n_embed, groups)
    torch.manual_seed(3)
    plain = VectorQuantizerEMA(dim // groups, n_embed, 1)
    torch.testing.assert_close(grouped.codebook, plain.codebook)
    for _ in range(5):
        z = torch.randn(batch, dim)
        q_grouped, loss_grouped, idx_grouped = grouped(z)
        q_plain, loss_plain, idx_plain = plain(z.reshape(batch * groups, dim // groups))
        torch.testing.assert_close(q_grouped, q_plain.reshape(batch, dim))
        torch.testing.assert_close(loss_grouped, loss_plain)
        torch.testing.assert_close(idx_grouped, idx_plain.reshape(batch, groups))
        torch.testing.assert_close(grouped.codebook, plain.codebook)


def test_g1_equals_plain_vqvae_ema_over_several_steps():
    rng = np.random.default_rng(1)
    dim, n_embed, decay, eps = 3, 6, 0.95, 1e-5
    codebook = rng.normal(size=(n_embed, dim))
    count, ema_sum = np.ones(n_embed), codebook.copy()
    vq = VectorQuantizerEMA(dim, n_embed, 1, decay=decay, eps=eps)
    set_codebook(vq, codebook)
    for _ in range(20):
        z = rng.normal(loc=0.5, size=(16, dim))
        _, _, indices = vq(torch.as_tensor(z, dtype=torch.float32))
        ref_idx, _, codebook, count, ema_sum = numpy_vqvae_ema_step(codebook, count, ema_sum, z, decay, eps)
        np.testing.assert_array_equal(indices.squeeze(-1).numpy(), ref_idx)
    np.testing.assert_allclose(vq.codebook.numpy(), codebook, atol=1e-5)
    np.testing.assert_allclose(vq.ema_count.numpy(), count, atol=1e-5)


def test_code_sums_agree_on_both_paths_and_with_a_loop():
    """The CPU path (index_add_) and the accelerator path (one-hot GEMM) compute the same per-code sums."""
    segments, indices = torch.randn(300, 4), torch.randint(0, 9, (300,))
    expected = torch.stack([segments[indices == k].sum(0) for k in range(9)])
    torch.testing.assert_close(code_sums(segments, indices, 9, use_gemm=False), expected)
    torch.testing.assert_close(code_sums(segments, indices, 9, use_gemm=True), expected)


def test_nearest_code_is_exact_across_cpu_blocks():
    """More rows than one CPU block holds: the blocked argmin agrees with the brute-force one everywhere."""
    vq = VectorQuantizerEMA(dim=4, n_embed=1024, groups=2)
    z = torch.randn(3000, 4)  # 6000 segments; a block holds 2**21 // 1024 = 2048 rows
    _, _, indices = vq(z, update=False)
    distances = torch.cdist(z.reshape(-1, 2).double(), vq.codebook.double()).pow(2)
    nearest, second = distances.topk(2, dim=1, largest=False).values.unbind(1)
    clear = second - nearest > 1e-4  # leave out near-ties that fp32 rounding may legitimately flip
    assert clear.float().mean() > 0.95
    torch.testing.assert_close(indices.flatten()[clear], distances.argmin(1)[clear], rtol=0, atol=0)


def test_unused_code_decays_smoothly_instead_of_exploding():
    """Counts start at 1 and sums at the codebook, so a code nobody picks is never divided by ~eps: it shrinks
    towards the origin as decay^t / (decay^t + eps) (as in Sonnet), never growing on the way."""
    vq = VectorQuantizerEMA(dim=2, n_embed=3, groups=1)
    set_codebook(vq, np.array([[50.0, 50.0], [51.0, 51.0], [-100.0, -100.0]]))
    norms = [vq.codebook[2].norm().item()]
    for _ in range(2000):
        _, _, indices = vq(50.0 + torch.rand(64, 2))
        assert (indices != 2).all()
        assert torch.isfinite(vq.codebook).all()
        norms.append(vq.codebook[2].norm().item())
    assert all(later <= earlier * (1 + 1e-6) for earlier, later in itertools.pairwise(norms))
    assert norms[1] > 0.99 * norms[0] and norms[-1] < 1.0


def test_dead_code_restart_moves_unused_codes_onto_the_data():
    z = torch.rand(64, 2)
    far = np.array([[0.5, 0.5], [100.0, 100.0]])
    kept = VectorQuantizerEMA(dim=2, n_embed=2, groups=1)
    restarted = VectorQuantizerEMA(dim=2, n_embed=2, groups=1, dead_code_steps=3)
    set_codebook(kept, far)
    set_codebook(restarted, far)
    for step in range(3):
        kept(z)
        restarted(z)
        if step < 2:
            torch.testing.assert_close(restarted.codebook[1], kept.codebook[1])
    assert kept.codebook[1].min() > 50  # off by default: the dead code stays where it was
    assert ((z - restarted.codebook[1]).abs().sum(1) == 0).any()  # restarted exactly at a batch vector
    assert restarted.steps_unused[1] == 0 and restarted.ema_count[1] == 1.0


# --- loss and gradients -----------------------------------------------------------------------------------------------


def test_loss_is_beta_over_g_times_sum_of_segment_distances_batch_averaged():
    dim, groups, batch, beta = 8, 4, 5, 0.4
    vq = VectorQuantizerEMA(dim, 9, groups, beta=beta)
    z = torch.randn(batch, dim)
    quantized, loss, _ = vq(z, update=False)
    per_sample = [
        beta / groups * sum(((z[b, i * 2 : i * 2 + 2] - quantized[b, i * 2 : i * 2 + 2]) ** 2).sum() for i in range(groups))
        for b in range(batch)
    ]
    torch.testing.assert_close(loss, torch.stack(per_sample).mean())
    assert loss.dtype == torch.float32 and loss.ndim == 0


def test_commitment_gradient_and_straight_through_identity():
    dim, groups, batch, beta = 6, 3, 4, 0.25
    vq = VectorQuantizerEMA(dim, 5, groups, beta=beta)
    z = torch.randn(batch, dim, requires_grad=True)
    quantized, loss, _ = vq(z)
    upstream = torch.randn(batch, dim)
    (quantized * upstream).sum().backward()
    torch.testing.assert_close(z.grad, upstream, rtol=0, atol=0)  # straight-through: identity

    z.grad = None
    quantized, loss, _ = vq(z, update=False)
    loss.backward()
    # d/dz of beta/G * sum_i ||c_i - sg(e)||^2, averaged over the batch; codes get no gradient (they are buffers).
    torch.testing.assert_close(z.grad, 2 * beta / (groups * batch) * (z - quantized).detach())
    assert list(vq.parameters()) == []


def test_quantized_values_are_exactly_codebook_rows():
    vq = VectorQuantizerEMA(16, 32, 4)
    z = torch.randn(3, 7, 16, requires_grad=True)
    quantized, _, indices = vq(z, update=False)
    assert quantized.shape == z.shape
    assert indices.shape == (3, 7, 4) and indices.dtype == torch.int64
    assert indices.min() >= 0 and indices.max() < 32
    torch.testing.assert_close(quantized, vq.codebook[indices].flatten(-2), rtol=0, atol=0)
    torch.testing.assert_close(vq.embed_indices(indices), quantized.detach(), rtol=0, atol=0)


# --- when the codebook must not move ----------------------------------------------------------------------------------


def test_no_update_in_eval_mode_or_with_update_false():
    vq = VectorQuantizerEMA(8, 16, 2)
    before = state(vq)
    vq(torch.randn(32, 8), update=False)
    assert_state_equal(before, state(vq))
    vq.eval()
    vq(torch.randn(32, 8))
    assert_state_equal(before, state(vq))


def test_no_grad_alone_does_not_stop_the_update():
    """Pitfall: acting under torch.no_grad() in training mode still moves the codebook, hence update=False."""
    vq = VectorQuantizerEMA(8, 16, 2)
    before = vq.codebook.clone()
    with torch.no_grad():
        vq(torch.randn(32, 8))
    assert not torch.equal(before, vq.codebook)


class _Net(nn.Module):
    def __init__(self):
        super().__init__()
        self.encoder = nn.Linear(4, 8)
        self.vq = VectorQuantizerEMA(8, 16, 4)

    def forward(self, x):
        return self.vq(self.encoder(x))


def test_target_copy_is_frozen_and_receives_the_codebook():
    online = _Net()
    target = make_target(online)
    assert not target.training and all(not p.requires_grad for p in target.parameters())
    frozen = state(target.vq)
    target(torch.randn(32, 4))
    assert_state_equal(frozen, state(target.vq))

    for _ in range(3):
        online(torch.randn(32, 4))
    assert not torch.equal(online.vq.codebook, target.vq.codebook)
    old_weight = target.encoder.weight.clone()
    tau = 0.1
    update_target(target, online, tau)
    torch.testing.assert_close(target.encoder.weight, (1 - tau) * old_weight + tau * online.encoder.weight)
    assert_state_equal(state(online.vq), state(target.vq))  # buffers are copied, not averaged
    assert target.vq.codebook.data_ptr() != online.vq.codebook.data_ptr()


# --- dtypes, state, determinism ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_low_precision_input_keeps_its_dtype_and_fp32_statistics(dtype):
    vq = VectorQuantizerEMA(16, 32, 4)
    z = torch.randn(64, 16).to(dtype)
    reference = VectorQuantizerEMA(16, 32, 4)
    reference.load_state_dict(vq.state_dict())
    quantized, loss, indices = vq(z)
    _, ref_loss, ref_indices = reference(z.float())
    assert quantized.dtype == dtype and loss.dtype == torch.float32
    torch.testing.assert_close(indices, ref_indices, rtol=0, atol=0)
    torch.testing.assert_close(loss, ref_loss)
    assert all(buffer.dtype in (torch.float32, torch.int64) for buffer in vq.buffers())
    torch.testing.assert_close(vq.codebook, reference.codebook)


def test_autocast_does_not_lower_the_distance_precision():
    vq = VectorQuantizerEMA(16, 32, 4)
    reference = VectorQuantizerEMA(16, 32, 4)
    reference.load_state_dict(vq.state_dict())
    z = torch.randn(64, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        quantized, _, indices = vq(z)
    _, _, ref_indices = reference(z)
    assert quantized.dtype == torch.float32
    torch.testing.assert_close(indices, ref_indices, rtol=0, atol=0)


def test_state_dict_round_trip_keeps_the_codebook():
    vq = VectorQuantizerEMA(8, 16, 2, dead_code_steps=5)
    for _ in range(4):
        vq(torch.randn(32, 8))
    restored = VectorQuantizerEMA(8, 16, 2, dead_code_steps=5)
    restored.load_state_dict(vq.state_dict())
    assert set(vq.state_dict()) == {"codebook", "ema_count", "ema_sum", "steps_unused"}
    assert_state_equal(state(vq), state(restored))
    z = torch.randn(10, 8)
    torch.testing.assert_close(vq(z, update=False)[2], restored(z, update=False)[2], rtol=0, atol=0)


def test_fixed_seed_gives_identical_results():
    def run(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        torch.manual_seed(seed)
        vq = VectorQuantizerEMA(8, 16, 4, dead_code_steps=2)
        losses = torch.stack([vq(torch.randn(32, 8) * 3)[1] for _ in range(10)])
        return vq.codebook, losses

    first, second, other = run(7), run(7), run(8)
    torch.testing.assert_close(first, second, rtol=0, atol=0)
    assert not torch.equal(first[0], other[0])


# --- helpers ----------------------------------------------------------------------------------------------------------


def test_factor_match_is_the_fraction_of_equal_factors():
    a = torch.tensor([[1, 2, 3, 4], [5, 5, 5, 5], [0, 1, 2, 3]])
    b = torch.tensor([[1, 0, 3, 0], [5, 5, 5, 5], [3, 2, 1, 0]])
    torch.testing.assert_close(factor_match(a, b), torch.tensor([0.5, 1.0, 0.0]))


def test_perplexity_and_active_codes():
    uniform = torch.arange(8).repeat(4).reshape(4, 8)
    collapsed = torch.full((4, 8), 3)
    assert perplexity(uniform, 16).item() == pytest.approx(8.0)
    assert perplexity(collapsed, 16).item() == pytest.approx(1.0)
    assert active_codes(uniform, 16).item() == 8
    assert active_codes(collapsed, 16).item() == 1


# --- no host sync: the update never waits for the device ------------------------------------------------------------


def test_code_counts_equal_bincount():
    indices = torch.randint(0, 37, (5000,))
    indices[:7] = 36  # the last bin used
    torch.testing.assert_close(code_counts(indices, 40), torch.bincount(indices, minlength=40).float(), rtol=0, atol=0)
    assert code_counts(indices.view(50, 100), 40).dtype == torch.float32


def test_the_no_host_sync_guard_catches_what_it_names():
    """The guard the update tests rely on: each of these must fail under it (a guard that lets them pass is useless)."""
    x = torch.randn(64)
    for sync in (
        lambda: x.sum().item(),
        lambda: torch.bincount(x.long().abs()),
        lambda: x[x > 0],
        lambda: x.nonzero(),
        lambda: bool(x.max() > 0),
        lambda: torch.unique(x),
    ):
        with pytest.raises(AssertionError, match="makes the host wait"), NoHostSync():
            sync()
    with NoHostSync():  # what a sync-free update does is allowed
        (x * 2).sum().add_(1)
        torch.where(x > 0, x, 0.0).index_add_(0, torch.zeros(64, dtype=torch.long), x)


@pytest.mark.parametrize("dead_code_steps", [0, 3])
def test_a_training_step_never_makes_the_host_wait(dead_code_steps):
    """Quantization, the loss, the EMA update with a non-finite row dropped, and a dead-code restart: all without a
    value read back or a data-dependent shape (bincount was one: it reads its largest index)."""
    vq = VectorQuantizerEMA(dim=16, n_embed=32, groups=4, dead_code_steps=dead_code_steps)
    z = torch.randn(64, 16, requires_grad=True)
    bad = z.detach().clone()
    bad[3, 5] = float("nan")
    with NoHostSync():
        for inputs in (z, z, bad, z, z):
            quantized, loss, indices = vq(inputs)
        (quantized.sum() + loss).backward()
        perplexity(indices, 32), active_codes(indices, 32)
    assert vq.steps_unused.max() < max(dead_code_steps, 1) or dead_code_steps == 0


# --- bad input --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"dim": 10, "n_embed": 8, "groups": 4}, r"dim \(10\) must be divisible by groups \(4\).*\[1, 2, 5, 10\]"),
        ({"dim": 8, "n_embed": 8, "groups": 0}, "groups must be an integer >= 1, got 0"),
        ({"dim": 8, "n_embed": 0, "groups": 2}, "n_embed must be an integer >= 1, got 0"),
        ({"dim": 0, "n_embed": 8, "groups": 1}, "dim must be an integer >= 1, got 0"),
        ({"dim": 8, "n_embed": 8.0, "groups": 2}, "n_embed must be an integer >= 1, got 8.0"),
        ({"dim": 8, "n_embed": 8, "groups": 2, "decay": 1.0}, r"decay must be in \[0, 1\), got 1.0"),
        ({"dim": 8, "n_embed": 8, "groups": 2, "beta": -1.0}, "beta must be >= 0"),
        ({"dim": 8, "n_embed": 8, "groups": 2, "eps": 0.0}, "eps must be > 0"),
        ({"dim": 8, "n_embed": 8, "groups": 2, "dead_code_steps": -1}, "dead_code_steps must be an integer >= 0"),
    ],
)
def test_bad_arguments_raise_value_errors_that_name_them(kwargs, message):
    with pytest.raises(ValueError, match=message):
        VectorQuantizerEMA(**kwargs)


def test_bad_shapes_raise_value_errors():
    vq = VectorQuantizerEMA(8, 16, 2)
    with pytest.raises(ValueError, match=r"last dimension 8, got shape \(4, 6\)"):
        vq(torch.randn(4, 6))
    with pytest.raises(ValueError, match="last dimension 2"):
        vq.embed_indices(torch.zeros(4, 3, dtype=torch.long))
    with pytest.raises(ValueError, match="index shapes differ"):
        factor_match(torch.zeros(2, 4), torch.zeros(2, 3))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_segments_never_reach_the_codebook(bad):
    """A segment with a NaN or infinite entry takes no part in the EMA update: codebook, counts and sums move exactly as
    if the batch held only its finite segments (the other segment of a half-bad row still counts), and later finite
    inputs are quantized as before."""
    torch.manual_seed(3)
    batch = torch.randn(33, 8)  # groups=2: each row is two segments of 4
    batch[16] = bad  # a wholly bad row
    batch[5, 3] = bad  # one bad entry in the first segment of row 5
    tested = VectorQuantizerEMA(8, 16, groups=2)
    reference = VectorQuantizerEMA(4, 16, groups=1)  # the same codebook fed the finite segments alone, in order
    reference.load_state_dict(tested.state_dict())
    segments = batch.reshape(-1, 4)
    tested(batch)
    reference(segments[segments.isfinite().all(1)])
    for name in ("codebook", "ema_count", "ema_sum"):
        assert torch.isfinite(getattr(tested, name)).all(), name
        torch.testing.assert_close(getattr(tested, name), getattr(reference, name), rtol=0, atol=0)
    clean = torch.randn(64, 8)
    _, _, after = tested(clean, update=False)
    _, _, expected = reference(clean.reshape(-1, 4), update=False)
    assert torch.equal(after.flatten(), expected.flatten())


def test_non_finite_segments_add_nothing_on_the_gemm_path():
    """code_sums' one-hot GEMM (the CUDA path) and index_add_ (the CPU path) agree on the zeroed rows the guard makes."""
    segments = torch.randn(10, 3)
    indices = torch.randint(4, (10,))
    torch.testing.assert_close(code_sums(segments, indices, 4, use_gemm=True), code_sums(segments, indices, 4, use_gemm=False))
