"""Preprocessor caches heal (issue 24, item 3): an entry is read only after its checksum, key and
shapes match; one that fails (cut short, other bytes, another fit's file, the format before
checksums) is reported in one warning line, removed and fitted again, and the run ends with the
state of a clean fit. A good entry loads without a fit; two jobs filling one cache at once agree."""

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import ferl.preprocessors.cache as cache
from ferl.preprocessors.cache import MAGIC, entry_header, load_or_fit
from ferl.preprocessors.rbm import RBMPreprocessor

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = dict(n_visible=16, n_hidden=4, sweeps=2, batch_size=20)


def images() -> torch.Tensor:
    return torch.rand(60, 16, generator=torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def clean():
    """A fit without any cache: the state every healed run must end with."""
    model = RBMPreprocessor(2, **SETTINGS)
    errors = model.train(images(), None, None)
    return model.state_dict(), errors


@pytest.fixture
def counted(monkeypatch):
    """How often RBMPreprocessor.train ran, and every torch.load the cache made (what it read)."""
    calls = {"train": 0, "load": []}
    train, load = RBMPreprocessor.train, torch.load

    def counting_train(self, *args, **kwargs):
        calls["train"] += 1
        return train(self, *args, **kwargs)

    def recording_load(f, *args, **kwargs):
        calls["load"].append(f.getvalue() if isinstance(f, io.BytesIO) else f)
        return load(f, *args, **kwargs)

    monkeypatch.setattr(RBMPreprocessor, "train", counting_train)
    monkeypatch.setattr(cache.torch, "load", recording_load)
    return calls


def messages(captured) -> list[str]:
    """ferl's lines on stderr (the fit's progress bar left out)."""
    return [line for line in captured.err.splitlines() if line.startswith("ferl:")]


def entry(tmp_path: Path) -> Path:
    [path] = tmp_path.glob("rbmpreprocessor-*.pt")
    return path


def other_fit(tmp_path: Path) -> bytes:
    """A good entry of another fit (other n_hidden: other key and shapes)."""
    other_dir = tmp_path / "other"
    load_or_fit(RBMPreprocessor(2, **{**SETTINGS, "n_hidden": 3}), images(), other_dir)
    return entry(other_dir).read_bytes()


def old_format(tmp_path: Path) -> bytes:
    """What the cache wrote before entries carried a checksum: a bare torch.save, same key."""
    model = RBMPreprocessor(2, **SETTINGS)
    buffer = io.BytesIO()
    key = cache.cache_key(model, images())
    torch.save({"state_dict": model.state_dict(), "errors": torch.zeros(2, 2), "key": key}, buffer)
    return buffer.getvalue()


def flipped(raw: bytes) -> bytes:
    """One byte of the payload changed (the header intact)."""
    at = len(raw) - 100
    return raw[:at] + bytes([raw[at] ^ 0x55]) + raw[at + 1 :]


DAMAGE = {
    "truncated": lambda raw, tmp: raw[: len(raw) // 2],
    "truncated_header": lambda raw, tmp: raw[: len(MAGIC) + 10],
    "other_bytes": lambda raw, tmp: os.urandom(len(raw)),
    "empty": lambda raw, tmp: b"",
    "flipped_payload_byte": lambda raw, tmp: flipped(raw),
    "other_fit_same_name": lambda raw, tmp: other_fit(tmp),
    "old_format": lambda raw, tmp: old_format(tmp),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_entry_warns_once_is_removed_and_refitted_to_the_clean_state(
    tmp_path, clean, counted, capsys, monkeypatch, damage
):
    load_or_fit(RBMPreprocessor(2, **SETTINGS), images(), tmp_path)
    path = entry(tmp_path)
    good = path.read_bytes()
    path.write_bytes(DAMAGE[damage](good, tmp_path))
    gone = []  # whether the damaged file was gone once discarded (before the fit)
    discard = cache.discard
    monkeypatch.setattr(cache, "discard", lambda p, identity: (discard(p, identity), gone.append(not p.exists()))[0])
    capsys.readouterr()
    counted["train"], counted["load"] = 0, []

    model = RBMPreprocessor(2, **SETTINGS)
    errors, cached = load_or_fit(model, images(), tmp_path)

    lines = messages(capsys.readouterr())
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"ferl: warning: preprocessor cache {path} failed its check (")
    assert lines[0].endswith("removed, fitting again")
    assert not cached and counted["train"] == 1
    assert counted["load"] == []  # nothing of the damaged file was deserialised
    torch.testing.assert_close(model.state_dict(), clean[0], rtol=0, atol=0)
    assert (errors == clean[1]).all()
    # the damaged file is gone; in its place the new fit's entry, equal to the first good one
    assert gone == [True] and path.read_bytes() == good
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_a_good_entry_is_loaded_without_a_fit_and_only_after_its_checksum(tmp_path, clean, counted, capsys):
    first = RBMPreprocessor(2, **SETTINGS)
    load_or_fit(first, images(), tmp_path)
    assert counted["train"] == 1 and counted["load"] == []
    raw = entry(tmp_path).read_bytes()
    header = entry_header(entry(tmp_path))
    assert header["shapes"] == {"W": [2, 16, 4], "b_v": [2, 16], "b_h": [2, 4], "errors": [2, 2]}
    assert header["bytes"] == len(raw) - len(MAGIC) - len(raw[len(MAGIC) :].partition(b"\n")[0]) - 1

    second = RBMPreprocessor(2, **SETTINGS)
    errors, cached = load_or_fit(second, images(), tmp_path)
    assert cached and counted["train"] == 1 and messages(capsys.readouterr()) == []
    assert counted["load"] == [raw[-header["bytes"] :]]  # exactly the checked payload
    torch.testing.assert_close(second.state_dict(), clean[0], rtol=0, atol=0)
    assert (errors == clean[1]).all()


def test_a_header_that_lies_about_shapes_is_caught_before_loading(tmp_path, counted, capsys):
    """A consistent header (key, length, sha256 right) whose shapes are not the preprocessor's:
    refused on the header alone."""
    load_or_fit(RBMPreprocessor(2, **SETTINGS), images(), tmp_path)
    path = entry(tmp_path)
    raw = path.read_bytes()
    line, _, payload = raw[len(MAGIC) :].partition(b"\n")
    path.write_bytes(MAGIC + line.replace(b'"W": [2, 16, 4]', b'"W": [2, 16, 5]') + b"\n" + payload)
    counted["load"] = []
    capsys.readouterr()
    load_or_fit(RBMPreprocessor(2, **SETTINGS), images(), tmp_path)
    [line] = messages(capsys.readouterr())
    assert "W of shape [2, 16, 5], the preprocessor's [2, 16, 4]" in line and counted["load"] == []


def test_an_unwritable_cache_warns_and_the_fit_goes_on(tmp_path, clean, capsys):
    blocked = tmp_path / "file"
    blocked.write_text("")  # a file where the cache folder should be
    model = RBMPreprocessor(2, **SETTINGS)
    errors, cached = load_or_fit(model, images(), blocked / "cache")
    [line] = messages(capsys.readouterr())
    assert line.startswith("ferl: warning: preprocessor cache") and "could not be written" in line
    assert not cached and (errors == clean[1]).all()


FILL = """
import hashlib, sys, torch
from ferl.preprocessors.cache import load_or_fit
from ferl.preprocessors.rbm import RBMPreprocessor
torch.set_num_threads(1)
images = torch.rand(60, 16, generator=torch.Generator().manual_seed(0))
model = RBMPreprocessor(2, n_visible=16, n_hidden=4, sweeps=40, batch_size=20)
errors, cached = load_or_fit(model, images, sys.argv[1])
digest = hashlib.sha256(b"".join(v.numpy().tobytes() for v in model.state_dict().values()) + errors.tobytes())
print(digest.hexdigest(), cached)
"""


@pytest.mark.parametrize("start", ["empty", "damaged"])
def test_two_jobs_filling_one_cache_at_once_agree(tmp_path, start):
    """Both fit (neither finds a finished entry), both write atomically, the results are identical,
    one good entry stays, no temporary file is left; starting from a damaged entry as well."""
    if start == "damaged":
        tmp_path.joinpath("x").mkdir()
        subprocess.run([sys.executable, "-c", FILL, str(tmp_path / "x")], cwd=ROOT, check=True, capture_output=True)
        [path] = (tmp_path / "x").glob("rbmpreprocessor-*.pt")
        (tmp_path / path.name).write_bytes(path.read_bytes()[:300])
    jobs = [
        subprocess.Popen(
            [sys.executable, "-c", FILL, str(tmp_path)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    results = [job.communicate(timeout=300) for job in jobs]
    assert all(job.returncode == 0 for job in jobs), results
    digests = {out.split()[0] for out, _ in results}
    assert len(digests) == 1
    [path] = tmp_path.glob("rbmpreprocessor-*.pt")
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    check = subprocess.run([sys.executable, "-c", FILL, str(tmp_path)], cwd=ROOT, capture_output=True, text=True)
    assert check.stdout.split() == [digests.pop(), "True"] and check.stderr == ""
