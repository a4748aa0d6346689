"""Throughput of the DGRL bottleneck next to one Linear(dim, dim) forward on the same batch.

    python benchmark/speed/bench_vq.py                  # the figures in docs/vq.md (batch 2048, dim 128, n_embed 512)
    python benchmark/speed/bench_vq.py --device cuda    # on a GPU

For each G it times three calls on the same (batch, dim) fp32 input: quantization alone (`update=False`, as when
acting), quantization plus the pooled EMA update (a training call), and that training call with the backward pass of
the commitment loss and the straight-through gradient. Each figure is the median over `--blocks` blocks of
`--iters` calls, after `--warmup` calls, with the interquartile range of the blocks; vectors/s counts batch rows (each row
is G segments).
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

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
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
    iters: int = 10
    """calls per timed block"""
    blocks: int = 21
    """timed blocks; the median is reported (many short blocks resist the noise of a shared machine)"""
    seed: int = 1
    """random seed"""


def time_ms(fn, args: Args) -> tuple[float, float, float]:
    """Median, first and third quartile of the milliseconds per call of fn over args.blocks blocks of args.iters calls."""
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
    quartiles = statistics.quantiles(per_call, n=4) if len(per_call) > 1 else [per_call[0]] * 3
    return quartiles[1], quartiles[0], quartiles[2]


def cell(timing: tuple[float, float, float], batch: int) -> str:
    median, low, high = timing
    return f"{median:.2f} ms [{low:.2f}-{high:.2f}] ({batch / median * 1e3 / 1e6:.2f} M vec/s)"


if __name__ == "__main__":
    args = tyro.cli(Args)
    for flag, value in (("--batch", args.batch), ("--dim", args.dim), ("--n-embed", args.n_embed)):
        if value < 1:
            raise SystemExit(f"error: {flag} must be >= 1, got {value}")
    if args.warmup < 0 or args.iters < 1 or args.blocks < 1:
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
        linear_ms = time_ms(lambda: linear(z), args)
    cpu = platform.processor() or platform.machine()
    print(f"torch {torch.__version__}, device {args.device}, {torch.get_num_threads()} CPU threads ({cpu})")
    print(f"batch {args.batch}, dim {args.dim}, n_embed {args.n_embed}; ", end="")
    print(f"median [interquartile range] of {args.blocks} blocks x {args.iters} calls\n")
    print("| G | quantize (update=False) | quantize + EMA update | + backward | train call / Linear fwd |")
    print("|---|---|---|---|---|")
    for groups in args.groups:
        vq = VectorQuantizerEMA(args.dim, args.n_embed, groups).to(device)
        with torch.no_grad():
            act_ms = time_ms(lambda vq=vq: vq(z, update=False), args)
            train_ms = time_ms(lambda vq=vq: vq(z), args)

        def train_step(vq=vq):
            quantized, loss, _ = vq(z_grad)
            (quantized.sum() + loss).backward()

        backward_ms = time_ms(train_step, args)
        cells = " | ".join(cell(timing, args.batch) for timing in (act_ms, train_ms, backward_ms))
        print(f"| {groups} | {cells} | {train_ms[0] / linear_ms[0]:.1f}x |")
    print(f"| Linear({args.dim}, {args.dim}) fwd | {cell(linear_ms, args.batch)} | | | 1.0x |")
