"""The recipes of docs/architecture.md (and docs/usage.md, where it has any) run exactly as printed.

A recipe is marked in the page by HTML comments before its fenced blocks:

    <!-- recipe: NAME file=PATH -->   the block that follows is the file PATH (relative to the user's folder)
    <!-- recipe: NAME run -->         the block that follows is shell commands, run in that folder

Each recipe's files are written into a fresh folder and its commands run there, one line at a time,
through bash, with two substitutions that are not the page's text: ``python`` becomes this
interpreter, ``train.py`` and ``analyze.py`` ferl's own scripts (the page says to write
``python <ferl>/train.py`` from a folder other than a checkout), and every train.py line gets
``REDUCED`` appended: the same command at a scale a test can afford (2 runs, a few episodes, eager).
Each recipe of a component (``COMPONENTS``) must train through train.py and then be analysed by
analyze.py; the others (a snippet of docs/usage.md) must run.
"""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TINY_ALGORITHM1

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "docs" / "architecture.md", ROOT / "docs" / "usage.md"]
MARKED = re.compile(r"<!-- recipe: (\S+) (file=(\S+)|run) -->\n```[a-z]*\n(.*?)\n```", re.S)
COMPONENTS = {"environment", "predictor", "actor", "gymnasium", "phase"}
OTHERS = {"gym_views"}
ALGORITHM1 = [
    "n_runs=2",
    "compile=false",
    *TINY_ALGORITHM1,
]
# appended to each printed train.py command, by the trainer it names: a tiny scale, eager
REDUCED = {
    "trainer=algorithm1": ALGORITHM1,
    "trainer=algorithm1_norm": ALGORITHM1,  # the phase recipe's trainer: Algorithm 1 and a phase
    "trainer=online": [
        "n_runs=2",
        "compile=false",
        "trainer.n_episodes=40",
        "trainer.replay_sample=4",
        "trainer.log_every=20",
        "trainer.final_window=20",
    ],
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
        line = line.replace(f"python {script}", f"python {shlex.quote(str(ROOT / script))}")
    line = re.sub(r"(^|\s)python ", rf"\1{shlex.quote(sys.executable)} ", line)
    if "train.py" in line:
        scale = next(extra for trainer, extra in REDUCED.items() if trainer in line.split())
        line = f"{line} {' '.join(scale)}"
    return line


def test_every_recipe_is_marked_with_files_and_commands():
    found = recipes()
    assert set(found) == COMPONENTS | OTHERS, sorted(found)
    for name, recipe in found.items():
        assert recipe["files"] and recipe["run"], name
    for name in COMPONENTS:
        recipe = found[name]
        assert recipe["run"][-1].startswith("python analyze.py "), name  # analysed last, its run directory named
        assert any("python train.py" in line and "experiment=none" in line for line in recipe["run"]), name


def run_recipe(name: str, folder: Path) -> dict:
    """Write the recipe's files into ``folder`` and run its lines there (ferl importable from this
    checkout, as train.py itself imports it); returns the recipe."""
    recipe = recipes()[name]
    for path, text in recipe["files"].items():
        (folder / path).parent.mkdir(parents=True, exist_ok=True)
        (folder / path).write_text(text)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for line in recipe["run"]:
        result = subprocess.run(
            ["bash", "-c", as_run(line)], cwd=folder, env=env, capture_output=True, text=True, timeout=600
        )
        assert result.returncode == 0, f"{line}\n{result.stderr[-3000:]}"
    return recipe


@pytest.mark.parametrize("name", sorted(OTHERS))
def test_snippet_runs_as_printed(tmp_path, name):
    run_recipe(name, tmp_path)


@pytest.mark.parametrize("name", sorted(COMPONENTS))
def test_recipe_trains_and_is_analysed_as_printed(tmp_path, name):
    recipe = run_recipe(name, tmp_path)
    run_dir = tmp_path / recipe["run"][-1].split()[-1]  # the directory analyze.py was given
    assert (run_dir / "summary.json").is_file() and (run_dir / "analysis" / "report.md").is_file()
    assert any((run_dir / "analysis").glob("*.png"))
