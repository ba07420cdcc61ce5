"""Learning under another torch, for ``make test-compat``: the golden numbers are exact only under
the torch that made them, so under another torch the learning results must agree in distribution.

    python tests/compat_learning.py run DIR             # the reduced-scale job below, with this Python's torch
    python tests/compat_learning.py compare REF DIR     # its solved count against REF's, within their s.e.m.

The job is tests/test_tmaze_training.py's reduced-scale regular T-maze (40 predictor epochs at 4×
the learning rate, 2 000 actor episodes) with 10 runs. ``compare`` prints one line per job and
fails (exit 1) unless |solved_REF − solved_DIR| ≤ s.e.m._REF + s.e.m._DIR, the s.e.m. of a count of
n runs being n · sd(solved) / √n over the runs' 0/1 verdicts (docs/usage.md, "Installing into your
own stack").
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# the regular T-maze at reduced scale, a run count aside (tests/test_tmaze_training.py learns it with 3)
REDUCED_REGULAR = (
    "experiment=table4_1_regular",
    "trainer.n_epoch=40",
    "predictor.joint.lr=0.2",
    "trainer.n_episodes=2000",
)
JOB = (*REDUCED_REGULAR, "n_runs=10")


def run(folder: Path) -> None:
    """The job into ``folder`` with this interpreter, and ``folder/torch.txt``: its torch's version."""
    import torch

    command = [sys.executable, str(ROOT / "train.py"), *JOB, f"hydra.run.dir={folder}"]
    subprocess.run(command, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    (folder / "torch.txt").write_text(torch.__version__)


def solved(folder: Path) -> tuple[int, float, int, str]:
    """The job's solved count, its s.e.m., its runs and the torch it ran under."""
    verdicts = np.asarray(json.loads((folder / "summary.json").read_text())["metrics"]["solved"], dtype=float)
    n = len(verdicts)
    sem = n * verdicts.std(ddof=1) / np.sqrt(n) if n > 1 else 0.0
    return int(verdicts.sum()), float(sem), n, (folder / "torch.txt").read_text()


def compare(reference: Path, folder: Path) -> bool:
    """One line for the pair; whether their solved counts agree within the sum of their s.e.m."""
    (a, sem_a, n_a, torch_a), (b, sem_b, n_b, torch_b) = solved(reference), solved(folder)
    agree = abs(a - b) <= sem_a + sem_b
    print(
        f"ferl: test-compat: solved {a}/{n_a} ± {sem_a:.1f} (torch {torch_a}) and {b}/{n_b} ± {sem_b:.1f} "
        f"(torch {torch_b}): {'agree' if agree else 'DISAGREE'} within their s.e.m."
    )
    return agree


if __name__ == "__main__":
    match sys.argv[1:]:
        case ["run", folder]:
            run(Path(folder))
        case ["compare", reference, folder]:
            sys.exit(0 if compare(Path(reference), Path(folder)) else 1)
        case _:
            sys.exit(__doc__)
