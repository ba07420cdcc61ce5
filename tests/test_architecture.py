"""The architecture's rules (docs/architecture.md), checked on the code: ferl's own components meet
the protocols of ferl/interfaces.py, imports follow the data flow — models never import
trainers or analysis, analysis imports no model, and ferl never imports the dissertation's analysis
(reproduction/), which plugs into ferl's — and a trainer is written in config: its phases, not a
class of its own."""

import ast
import re
import sys
from pathlib import Path

import pytest
import torch

from conftest import ROOT
from ferl import interfaces
from ferl.actors.free_energy import FERLActor
from ferl.conformance import required_members
from ferl.envs.digit_floor import DigitFloor
from ferl.envs.digit_tmaze import DigitTMaze
from ferl.envs.tmaze import TMaze
from ferl.predictors.elman import ElmanPredictor
from ferl.preprocessors.rbm import RBMPreprocessor
from ferl.schedules import Constant
from test_digit_floor import tiny_split

FERL = ROOT / "ferl"
REPRODUCTION = ROOT / "reproduction"
MODELS = ("envs", "preprocessors", "predictors", "actors")


def test_components_meet_their_protocols():
    gen = torch.Generator().manual_seed(0)
    digits = {
        n: i
        for i, n in enumerate(("start_0", "start_1", "corridor", "junction_0", "junction_1", "goal_left", "goal_right"))
    }
    assert isinstance(DigitFloor(2, tiny_split(), gen), interfaces.ContinuingEnvironment)
    assert isinstance(TMaze(2, gen), interfaces.EpisodicEnvironment)
    assert isinstance(DigitTMaze(2, gen, tiny_split(), digits, matching=True), interfaces.EpisodicEnvironment)
    assert isinstance(RBMPreprocessor(2, n_visible=16, n_hidden=4), interfaces.Preprocessor)
    assert isinstance(ElmanPredictor(2, 7, 4, n_reward=4), interfaces.Predictor)
    actor = FERLActor(
        n_runs=2,
        n_state=27,
        n_actions=4,
        n_hidden=20,
        td_rule="sarsa",
        gamma=0.95,
        lr=Constant(0.05),
        beta=Constant(1.0),
    )
    assert isinstance(actor, interfaces.Actor) and isinstance(actor, interfaces.ActorViews)


@pytest.mark.parametrize(
    "protocol, base",
    [
        (interfaces.Environment, interfaces.EnvironmentBase),
        (interfaces.EpisodicEnvironment, interfaces.EpisodicEnvironmentBase),
        (interfaces.Preprocessor, interfaces.PreprocessorBase),
        (interfaces.TrainingBatch, interfaces.TrainingBatchBase),
        (interfaces.Predictor, interfaces.PredictorBase),
        (interfaces.Actor, interfaces.ActorBase),
        (interfaces.Trainer, interfaces.TrainerBase),
    ],
)
def test_every_default_a_base_gives_is_a_member_its_protocol_declares(protocol, base):
    """A hook exists once as a declared member and once as a default: a base class that gave a
    member its protocol does not declare would bring back an undeclared, discovered hook."""
    given = {name for cls in base.__mro__[:-1] for name in vars(cls) if not name.startswith("_")}
    assert given and given <= set(required_members(protocol))


def imports(path: Path, package: str = "ferl") -> set[str]:
    """The modules of `package` that a file imports."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return {n for n in names if n == package or n.startswith(f"{package}.")}


def module_file(name: str) -> Path | None:
    """The file of ferl module ``name`` (a package: its __init__.py); None for what is no module."""
    base = ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def imported_modules(name: str) -> set[str]:
    """Every ferl module that module ``name`` imports, in each form: ``import ferl.a.b``,
    ``from ferl.a import b`` (b a module), ``from ferl.a.b import c``, and relative imports."""
    path = module_file(name)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1] if node.level else [])
            base = ".".join(p for p in (base, node.module or "") if p)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {m for m in found if m.startswith("ferl") and module_file(m) is not None}


def reachable(name: str) -> set[str]:
    """The ferl modules that importing ``name`` loads, through any chain of imports (a module
    brings its parent packages' __init__ with it)."""
    seen, todo = set(), [name]
    while todo:
        module = todo.pop()
        for m in imported_modules(module) | {".".join(module.split(".")[:i]) for i in range(1, module.count(".") + 1)}:
            if m not in seen and module_file(m) is not None:
                seen.add(m)
                todo.append(m)
    return seen - {name}


def trainer_modules() -> dict[str, str]:
    """conf/trainer option → the module of the class it names as the trainer (the trainer node's
    ``_target_``, its defaults list composed): the entry points, whatever their phases are."""
    from omegaconf import OmegaConf

    from conftest import compose_config

    options = sorted(p.stem for p in (ROOT / "conf" / "trainer").glob("*.yaml"))
    targets = {o: OmegaConf.select(compose_config([f"trainer={o}"]), "trainer._target_") for o in options}
    assert options and all(targets.values()), targets
    return {o: t.rpartition(".")[0] for o, t in targets.items()}


@pytest.mark.parametrize("package", MODELS)
def test_models_import_no_trainer_and_no_analysis(package):
    """docs/architecture.md: data flows one way; a model loads no trainer and no analysis module,
    directly or through any chain of imports."""
    for path in (FERL / package).glob("*.py"):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        bad = {m for m in reachable(module) if m.startswith(("ferl.trainers", "ferl.analysis"))}
        assert not bad, (module, bad)


def test_every_trainer_is_written_in_config():
    """Every conf/trainer option builds the one trainer class, PhasedTrainer, from its phases; no
    module of ferl/ defines another procedure in Python (a class with fit, or a PhasedTrainer's subclass)."""
    assert set(trainer_modules().values()) == {"ferl.trainers.phased"}
    for path in FERL.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases}
                methods = {f.name for f in node.body if isinstance(f, ast.FunctionDef)}
                is_trainer = "PhasedTrainer" in bases or ({"setup", "fit"} <= methods and "Protocol" not in bases)
                assert not is_trainer or node.name == "PhasedTrainer", (path, node.name)


def test_import_scan_finds_every_form(tmp_path, monkeypatch):
    """The scan below sees each way of importing a module (a scan that missed one would pass the
    rule vacuously)."""
    package = tmp_path / "ferl" / "pkg"
    package.mkdir(parents=True)
    (tmp_path / "ferl" / "__init__.py").write_text("")
    for name in ("__init__", "a", "b", "c", "d", "e"):
        (package / f"{name}.py").write_text("")
    (package / "a.py").write_text("import ferl.pkg.b\nfrom ferl.pkg import c\nfrom . import d\nfrom .e import x\n")
    (package / "d.py").write_text("from ferl.pkg.e import y\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert imported_modules("ferl.pkg.a") == {"ferl.pkg", "ferl.pkg.b", "ferl.pkg.c", "ferl.pkg.d", "ferl.pkg.e"}
    assert reachable("ferl.pkg.d") == {"ferl", "ferl.pkg", "ferl.pkg.e"}
    assert reachable("ferl.pkg.c") == {"ferl", "ferl.pkg"}


def trainer_files() -> dict[str, Path]:
    """Module name → file of every module of ferl.trainers."""
    return {f"ferl.trainers.{p.stem}": p for p in (FERL / "trainers").glob("*.py") if p.stem != "__init__"}


def test_trainers_import_no_circle_and_handoffs_lie_below_the_phases():
    """docs/architecture.md, "Trainers": the trainers' modules import one another without a
    circle (every import, also those under TYPE_CHECKING or inside a function), and the hand-offs
    (``ferl.trainers.handoffs``) import no other trainer module: they lie below the phases."""
    modules = trainer_files()
    edges = {m: {n for n in imported_modules(m) if n in modules and n != m} for m in modules}
    assert edges["ferl.trainers.handoffs"] == set()
    # a depth-first search; a module met again on the current path closes a circle
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for n in sorted(edges[module]):
            assert state.get(n) != 1, " → ".join([*path, module, n])
            if n not in state:
                visit(n, [*path, module])
        state[module] = 2

    for module in sorted(modules):
        if module not in state:
            visit(module, [])


def test_circle_search_sees_a_circle(tmp_path, monkeypatch):
    """The search above finds a circle through a TYPE_CHECKING import (one that missed it would
    pass vacuously)."""
    package = tmp_path / "ferl" / "trainers"
    package.mkdir(parents=True)
    for path in (tmp_path / "ferl" / "__init__.py", package / "__init__.py"):
        path.write_text("")
    (package / "handoffs.py").write_text("")
    (package / "a.py").write_text("from ferl.trainers.b import x\n")
    (package / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ferl.trainers.a import y\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "FERL", tmp_path / "ferl")
    with pytest.raises(AssertionError, match=re.escape("ferl.trainers.a → ferl.trainers.b → ferl.trainers.a")):
        test_trainers_import_no_circle_and_handoffs_lie_below_the_phases()


def test_analysis_reads_records_not_models():
    for path in [*(FERL / "analysis").glob("*.py"), *REPRODUCTION.glob("*.py")]:
        bad = {n for n in imports(path) if n.startswith(tuple(f"ferl.{p}" for p in (*MODELS, "trainers")))}
        assert not bad, (path, bad)


def test_ferl_never_imports_the_reproduction():
    """Data flows one way: reproduction/ registers its analyses into ferl.analysis.dispatch, and
    no module of ferl imports it (analyze.py, outside ferl, does)."""
    assert "ferl.analysis" in imports(REPRODUCTION / "__init__.py", "ferl")  # the other way it does
    for path in FERL.rglob("*.py"):
        bad = imports(path, "reproduction")
        assert not bad, (path, bad)
    assert imports(ROOT / "analyze.py", "reproduction") == {"reproduction"}


def test_trainers_call_hooks_and_never_look_for_them():
    """The phases call every member of a component directly: a ``hasattr``/``getattr`` in
    ferl/trainers would be a hook discovered rather than declared. The config checks' hooks of a
    ``_target_`` (``ferl.config.params.ConfigTarget``: any callable, no base class) are the exception."""
    from ferl.config.params import ConfigTarget

    allowed = set(required_members(ConfigTarget))
    found = []
    for path in sorted((FERL / "trainers").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("hasattr", "getattr"):
                name = node.args[1].value if isinstance(node.args[1], ast.Constant) else None
                if name not in allowed:
                    found.append(f"{path.name}:{node.lineno} {node.func.id}(…, {name!r})")
    assert allowed == {"kwargs_to", "check_config", "resolve"} and found == []
