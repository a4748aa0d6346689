"""Does torch.compile keep the quantizer's order of reads and writes? One VectorQuantizerEMA call, eager and compiled.

    python benchmark/speed/compiled_vq_probe.py          # prints one line per case; exit status 1 if a compiled call differs

The quantized output must be the codes as they were before the call's EMA update (the codebook moves after it has been
read). Each case starts from the same state and seed, runs one training call eagerly and one compiled, and says which
codebook the compiled output holds: "before the update" (as eager) or "after the update". The second case makes every
code due for a dead-code restart in that call. Both cases agree with eager on torch 2.13.0 and on torch 2.11.0. On torch
2.11.0 the case with restarts returned the codes after the update (the restarted ones) while vq.py wrote the new
codebook with `copy_`: torch 2.11's inductor fused that write and the gather of the selected codes into one kernel
(`TORCH_LOGS=output_code`), the cause of eight of the nine compiled-vs-eager test failures of DGRL updates on that
version (docs/launch.md). vq.py now writes it with `index_copy_`, which that version does not fuse so.
"""

import argparse
import copy
import os
import sys

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from vq import VectorQuantizerEMA


def probe(restart: bool) -> bool:
    """True when the compiled call returns what the eager call returns: the codes from before the update."""
    torch.manual_seed(0)
    quantizer = VectorQuantizerEMA(dim=16, n_embed=8, groups=4, dead_code_steps=3 if restart else 0).train()
    z = torch.randn(64, 16)
    quantizer(z)
    if restart:
        quantizer.steps_unused.fill_(5)  # every code is restarted in the next call
    before = quantizer.codebook.clone()
    eager, compiled = quantizer, copy.deepcopy(quantizer)
    torch.manual_seed(7)
    eager_output, _, eager_indices = eager(z)
    torch.manual_seed(7)
    compiled_output, _, compiled_indices = torch.compile(lambda module, x: module(x), fullgraph=True)(compiled, z)
    assert torch.equal(eager_indices, compiled_indices)
    assert torch.allclose(eager_output, F.embedding(eager_indices, before).flatten(-2))
    agrees = torch.allclose(compiled_output, F.embedding(compiled_indices, before).flatten(-2))
    holds = "before the update (as eager)" if agrees else "after the update (eager: before)"
    case = "with dead-code restarts" if restart else "without dead-code restarts"
    print(f"torch {torch.__version__}, {case}: the compiled call's output holds the codes {holds}", flush=True)
    return agrees


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    torch._inductor.config.fallback_random = True  # as the scripts' --fast compile sets it
    results = [probe(restart) for restart in (False, True)]
    raise SystemExit(0 if all(results) else 1)
