"""The architecture's rules (docs/architecture.md), checked on the code: ferl's own components meet
the protocols of ferl/interfaces.py, imports follow the data flow — models never import
trainers or analysis, analysis imports no model, and ferl never imports the dissertation's analysis
(reproduction/), which plugs into ferl's — and a trainer is written in config: its phases, not a
class of its own."""
import ast
from pathlib import Path

import pytest
import torch

from conftest import ROOT
from ferl import interfaces
from ferl.actors.free_energy import FERLActor
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
    digits = {n: i for i, n in enumerate(("start_0", "start_1", "corridor", "junction_0", "junction_1",
                                          "goal_left", "goal_right"))}
    assert isinstance(DigitFloor(2, tiny_split(), gen), interfaces.ContinuingEnvironment)
    assert isinstance(TMaze(2, gen), interfaces.EpisodicEnvironment)
    assert isinstance(DigitTMaze(2, gen, tiny_split(), digits, matching=True), interfaces.EpisodicEnvironment)
    assert isinstance(RBMPreprocessor(2, n_visible=16, n_hidden=4), interfaces.Preprocessor)
    assert isinstance(ElmanPredictor(2, 7, 4, n_reward=4), interfaces.Predictor)
    actor = FERLActor(2, 27, 4, 20, "sarsa", 0.95, Constant(0.05), Constant(1.0))
    assert isinstance(actor, interfaces.Actor) and isinstance(actor, interfaces.ActorViews)


@pytest.mark.parametrize("protocol, base", [
    (interfaces.Environment, interfaces.EnvironmentBase),
    (interfaces.EpisodicEnvironment, interfaces.EpisodicEnvironmentBase),
    (interfaces.Preprocessor, interfaces.PreprocessorBase),
    (interfaces.TrainingBatch, interfaces.TrainingBatchBase),
    (interfaces.Predictor, interfaces.PredictorBase),
    (interfaces.Actor, interfaces.ActorBase),
    (interfaces.Trainer, interfaces.TrainerBase)])
def test_every_default_a_base_gives_is_a_member_its_protocol_declares(protocol, base):
    """A hook exists once as a declared member and once as a default: a base class that gave a
    member its protocol does not declare would bring back an undeclared, discovered hook."""
    given = {name for cls in base.__mro__[:-1] for name in vars(cls) if not name.startswith("_")}
    assert given and given <= set(interfaces.required_members(protocol))


def imports(path: Path, package: str = "ferl") -> set[str]:
    """The modules of `package` that a file imports."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return {n for n in names if n == package or n.startswith(f"{package}.")}


@pytest.mark.parametrize("package", MODELS)
def test_models_import_no_trainer_and_no_analysis(package):
    for path in (FERL / package).glob("*.py"):
        bad = {n for n in imports(path) if n.startswith(("ferl.trainers", "ferl.analysis"))}
        assert not bad, (path, bad)


def test_every_trainer_is_written_in_config():
    """Every conf/trainer option builds the one trainer class, PhasedTrainer, from its phases; no
    module of ferl/ defines another procedure in Python (a class with fit, or a PhasedTrainer's subclass)."""
    for path in (ROOT / "conf" / "trainer").glob("*.yaml"):
        text = path.read_text()
        assert "_target_: ferl.trainers.phased.PhasedTrainer" in text or "\n  - algorithm1\n" in text \
            or "\n  - online\n" in text, path
    for path in FERL.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases}
                methods = {f.name for f in node.body if isinstance(f, ast.FunctionDef)}
                is_trainer = "PhasedTrainer" in bases or ({"setup", "fit"} <= methods and "Protocol" not in bases)
                assert not is_trainer or node.name == "PhasedTrainer", (path, node.name)


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
    allowed = set(interfaces.required_members(ConfigTarget))
    found = []
    for path in sorted((FERL / "trainers").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("hasattr", "getattr"):
                name = node.args[1].value if isinstance(node.args[1], ast.Constant) else None
                if name not in allowed:
                    found.append(f"{path.name}:{node.lineno} {node.func.id}(…, {name!r})")
    assert allowed == {"kwargs_to", "check_config", "resolve"} and found == []
