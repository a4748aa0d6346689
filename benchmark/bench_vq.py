"""Throughput of the DGRL bottleneck next to one Linear(dim, dim) forward on the same batch.

    python benchmark/bench_vq.py                  # the figures in docs/vq.md (batch 2048, dim 128, n_embed 512)
    python benchmark/bench_vq.py --device cuda    # on a GPU

For each G it times three calls on the same (batch, dim) fp32 input: quantization alone (`update=False`, as when
acting), quantization plus the pooled EMA update (a training call), and that training call with the backward pass of
the commitment loss and the straight-through gradient. Each figure is the median over `--blocks` blocks of
`--iters` calls, after `--warmup` calls; vectors/s counts batch rows (each row is G segments).
"""

import platform
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from vq import VectorQuantizerEMA


@dataclass
class Args:
    batch: int = 2048
    """rows per call"""
    dim: int = 128
    """embedding size m"""
    n_embed: int = 512
    """codebook size L"""
    groups: tuple[int, ...] = (1, 8, 16)
    """factor counts G to time"""
    device: str = "cpu"
    """torch device"""
    threads: int = 0
    """torch CPU threads (0 = torch's default)"""
    warmup: int = 10
    """untimed calls before timing"""
    iters: int = 50
    """calls per timed block"""
    blocks: int = 5
    """timed blocks; the median is reported"""
    seed: int = 1
    """random seed"""


def median_ms(fn, args: Args) -> float:
    """Median milliseconds per call of fn over args.blocks blocks of args.iters calls."""
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    for _ in range(args.warmup):
        fn()
    sync()
    per_call = []
    for _ in range(args.blocks):
        start = time.perf_counter()
        for _ in range(args.iters):
            fn()
        sync()
        per_call.append((time.perf_counter() - start) / args.iters * 1e3)
    return statistics.median(per_call)


if __name__ == "__main__":
    args = tyro.cli(Args)
    for flag, value in (("--batch", args.batch), ("--dim", args.dim), ("--n-embed", args.n_embed)):
        if value < 1:
            raise SystemExit(f"error: {flag} must be >= 1, got {value}")
    if min(args.warmup, args.iters, args.blocks) < 0 or args.iters < 1 or args.blocks < 1:
        raise SystemExit("error: --warmup must be >= 0, --iters and --blocks >= 1")
    bad_groups = [g for g in args.groups if g < 1 or args.dim % g]
    if bad_groups:
        raise SystemExit(f"error: --groups {bad_groups} do not divide --dim {args.dim}")
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda asked for, but torch sees no GPU")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    z = torch.randn(args.batch, args.dim, device=device)
    z_grad = z.clone().requires_grad_(True)
    linear = nn.Linear(args.dim, args.dim).to(device)

    with torch.no_grad():
        linear_ms = median_ms(lambda: linear(z), args)
    cpu = platform.processor() or platform.machine()
    print(f"torch {torch.__version__}, device {args.device}, {torch.get_num_threads()} CPU threads ({cpu})")
    print(f"batch {args.batch}, dim {args.dim}, n_embed {args.n_embed}; median of {args.blocks} blocks x {args.iters} calls\n")
    print("| G | quantize (update=False) | quantize + EMA update | + backward | vs Linear fwd (train call) |")
    print("|---|---|---|---|---|")
    for groups in args.groups:
        vq = VectorQuantizerEMA(args.dim, args.n_embed, groups).to(device)
        with torch.no_grad():
            act_ms = median_ms(lambda vq=vq: vq(z, update=False), args)
            train_ms = median_ms(lambda vq=vq: vq(z), args)

        def train_step(vq=vq):
            quantized, loss, _ = vq(z_grad)
            (quantized.sum() + loss).backward()

        backward_ms = median_ms(train_step, args)

        def cell(ms: float) -> str:
            return f"{ms:.3f} ms ({args.batch / ms * 1e3 / 1e6:.2f} M vec/s)"

        print(f"| {groups} | {cell(act_ms)} | {cell(train_ms)} | {cell(backward_ms)} | {train_ms / linear_ms:.1f}x |")
    print(f"| Linear({args.dim}, {args.dim}) fwd | {cell(linear_ms)} | | | 1.0x |")
