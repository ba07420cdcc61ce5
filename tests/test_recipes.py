"""The recipes of docs/architecture.md (and docs/usage.md, where it has any) run exactly as printed.

A recipe is marked in the page by HTML comments before its fenced blocks:

    <!-- recipe: NAME file=PATH -->   the block that follows is the file PATH (relative to the user's folder)
    <!-- recipe: NAME run -->         the block that follows is shell commands, run in that folder

Each recipe's files are written into a fresh folder and its commands run there, one line at a time,
through bash, with two substitutions that are not the page's text: ``python train.py`` and
``python analyze.py`` become this interpreter and ferl's own scripts (the page says to write
``python <ferl>/train.py`` from a folder other than a checkout), and every train.py line gets
``REDUCED`` appended: the same command at a scale a test can afford (2 runs, a few episodes, eager).
Each recipe must train through train.py and then be analysed by analyze.py.
"""
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "docs" / "architecture.md", ROOT / "docs" / "usage.md"]
MARKED = re.compile(r"<!-- recipe: (\S+) (file=(\S+)|run) -->\n```[a-z]*\n(.*?)\n```", re.S)
EXPECTED = {"environment", "predictor", "actor", "gymnasium"}
# appended to each printed train.py command, by the trainer it names: a tiny scale, eager
REDUCED = {
    "trainer=algorithm1": ["n_runs=2", "compile=false", "trainer.n_sample=200", "trainer.n_epoch=2",
                           "trainer.n_episodes=50", "trainer.log_every=25", "trainer.td_sample_every=25",
                           "trainer.final_window=25"],
    "trainer=online": ["n_runs=2", "compile=false", "trainer.n_episodes=40", "trainer.replay_sample=4",
                       "trainer.log_every=20", "trainer.final_window=20"],
}


def recipes() -> dict:
    """Recipe name → {"files": {path: text}, "run": [command lines]}, from every page's marked blocks."""
    found = {}
    for page in PAGES:
        for name, kind, path, body in MARKED.findall(page.read_text()):
            recipe = found.setdefault(name, {"files": {}, "run": []})
            if kind == "run":
                recipe["run"] += [line for line in body.splitlines() if line.strip()]
            else:
                recipe["files"][path] = body + "\n"
    return found


def as_run(line: str) -> str:
    """The printed line with ferl's scripts under this interpreter, and a train.py line reduced."""
    for script in ("train.py", "analyze.py"):
        line = line.replace(f"python {script}", f"{shlex.quote(sys.executable)} {shlex.quote(str(ROOT / script))}")
    if "train.py" in line:
        scale = next(extra for trainer, extra in REDUCED.items() if trainer in line.split())
        line = f"{line} {' '.join(scale)}"
    return line


def test_every_recipe_is_marked_with_files_and_commands():
    found = recipes()
    assert EXPECTED <= set(found), sorted(found)
    for name, recipe in found.items():
        assert recipe["files"], name
        assert recipe["run"][-1].startswith("python analyze.py "), name  # analysed last, its run directory named
        assert any("python train.py" in line and "experiment=none" in line for line in recipe["run"]), name


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_recipe_trains_and_is_analysed_as_printed(tmp_path, name):
    recipe = recipes()[name]
    for path, text in recipe["files"].items():
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(text)
    for line in recipe["run"]:
        result = subprocess.run(["bash", "-c", as_run(line)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, f"{line}\n{result.stderr[-3000:]}"
    run_dir = tmp_path / recipe["run"][-1].split()[-1]  # the directory analyze.py was given
    assert (run_dir / "summary.json").is_file() and (run_dir / "analysis" / "report.md").is_file()
    assert any((run_dir / "analysis").glob("*.png"))
