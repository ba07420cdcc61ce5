"""resume=true continues the same run (issue 24, item 2): the run's own config comes from its
checkpoint, the overrides given now are applied to it, and any that would change what the run
computes is refused in one line listing each key, old → new; ``ferl.run.resume.ALLOWED`` lists
what a resume may change."""

import hashlib
import shutil
from pathlib import Path

import pytest

from conftest import RESUMABLE_TMAZE, run_train, validated_config
from ferl.config.params import ConfigError
from ferl.config.validate import resolved
from ferl.run import checkpoint
from ferl.run.checkpoint import RunIdentity
from ferl.run.resume import ALLOWED, apply_overrides, resumed_run

TMAZE = RESUMABLE_TMAZE


def saved_run(tmp_path, overrides=TMAZE, device="cpu") -> Path:
    """A run directory whose checkpoint was written under the composed ``overrides``."""
    cfg = validated_config(overrides)  # Hydra's runtime keys set, as in train.py
    choices = {k: v for k, v in cfg.hydra.runtime.choices.items() if not k.startswith("hydra")}
    checkpoint.write(tmp_path / "checkpoints", {"progress": {}}, RunIdentity(resolved(cfg), choices, device))
    return tmp_path


def cpu(name: str) -> str:
    return "cuda" if name == "cuda" else "cpu"


def test_no_override_continues_under_the_runs_own_config(tmp_path):
    run = saved_run(tmp_path)
    resumed = resumed_run(run, ["resume=true"], cpu)
    assert resumed.config.name == "table4_1_regular" and resumed.config.n_runs == 2
    assert resumed.config.trainer.n_episodes == 300 and resumed.config.resume is True
    assert resumed.identity.choices["experiment"] == "table4_1_regular"


def test_the_same_overrides_again_are_no_change(tmp_path):
    run = saved_run(tmp_path)
    assert resumed_run(run, [*TMAZE, "compile=false", "resume=true"], cpu).config.trainer.n_sample == 200


def test_a_changing_override_is_refused_listing_every_key(tmp_path):
    run = saved_run(tmp_path)
    with pytest.raises(ConfigError) as e:
        resumed_run(
            run,
            [
                "n_runs=3",
                "seed=5",
                "env.corridor_length=4",
                "trainer.log_every=50",
                "compile=true",
                "cpu_threads=2",
                "resume=true",
            ],
            cpu,
        )
    message = str(e.value)
    assert "\n" not in message
    for change in (
        "n_runs: 2 → 3",
        "seed: 0 → 5",
        "env.corridor_length: 3 → 4",
        "trainer.log_every: 100 → 50",
        "compile: false → true",
    ):
        assert change in message, message
    assert "cpu_threads: 1" not in message  # allowed
    assert f"a resume may change only {', '.join(ALLOWED)}" in message


def test_another_experiment_or_group_choice_is_refused(tmp_path):
    run = saved_run(tmp_path)
    with pytest.raises(ConfigError, match="experiment: table4_1_regular → table4_1_matching, actor: ferl_tmaze → drqn"):
        resumed_run(run, ["experiment=table4_1_matching", "actor=drqn"], cpu)


def test_a_key_the_run_does_not_have_is_a_change(tmp_path):
    run = saved_run(tmp_path)
    with pytest.raises(ConfigError, match=r"trainer.steps: \(absent\) → 300"):
        resumed_run(run, ["trainer.steps=300"], cpu)


def test_allowed_keys_are_applied(tmp_path):
    run = saved_run(tmp_path)
    cfg = resumed_run(
        run,
        [
            "cpu_threads=2",
            "device=cpu",
            "trainer.run.checkpoint_minutes=0.5",
            "trainer.phases.predictors.checkpoint_every_epochs=2",
            "memory_check=false",
        ],
        cpu,
    ).config
    assert (
        cfg.cpu_threads,
        cfg.device,
        cfg.trainer.run.checkpoint_minutes,
        cfg.trainer.phases.predictors.checkpoint_every_epochs,
        cfg.memory_check,
    ) == (2, "cpu", 0.5, 2, False)


def test_another_device_is_refused(tmp_path):
    run = saved_run(tmp_path)
    with pytest.raises(ConfigError, match=r"device: cpu → cuda \(a run continues on the device it ran on\)"):
        resumed_run(run, ["device=cuda"], cpu)


def test_every_allowed_key_is_a_key_of_the_configs():
    """The allowed list names keys that exist (a typo would allow nothing)."""
    keys = set()
    for experiment in ("ch3_floor", "table4_1_regular", "table5_1_pixel"):
        keys |= set(flat(resolved(validated_config([f"experiment={experiment}"]))))
    assert set(ALLOWED) <= keys, set(ALLOWED) - keys


def flat(node: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in node.items():
        out[prefix + key] = value
        if isinstance(value, dict):
            out |= flat(value, f"{prefix}{key}.")
    return out


def test_apply_overrides_deletes_and_adds():
    identity = RunIdentity({"a": {"b": 1, "c": 2}}, {})
    config, changes = apply_overrides(identity, ["~a.c", "+a.d=3"])
    assert config == {"a": {"b": 1, "d": 3}}
    assert changes == [("a.c", 2, "(absent)"), ("a.d", "(absent)", 3)]


# ---- through train.py ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("whole") / "run"
    result = run_train(*TMAZE, f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    return run_dir


def cut_copy(whole: Path, dst: Path) -> Path:
    """``whole`` as it was at its checkpoint after episode 200: previous.pt made the last one,
    the records and summary the end writes removed (tb/ is cut back by the resume)."""
    from test_fault_injection import cut_copy as copy

    run_dir = copy(whole, dst)
    (run_dir / "checkpoints" / "last.pt").unlink()
    return run_dir


def snapshot(run_dir: Path) -> dict:
    return {
        p.relative_to(run_dir).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(run_dir.rglob("*"))
        if p.is_file()
    }


def test_plain_resume_continues_the_run_not_the_default_experiment(tmp_path, whole):
    """`resume=true hydra.run.dir=DIR` with no experiment= (the default is ch3_floor) continues the
    regular T-maze run and ends as it would have; .hydra/ holds the run's own files again."""
    from test_fault_injection import assert_same_run

    run_dir = cut_copy(whole, tmp_path / "run")
    result = run_train("resume=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "ferl: table4_1_regular done" in result.stdout
    assert_same_run(run_dir, whole)
    for name in ("config.yaml", "overrides.yaml", "hydra.yaml"):
        assert (run_dir / ".hydra" / name).read_text() == (whole / ".hydra" / name).read_text(), name


def test_resume_on_two_threads_ends_as_the_one_thread_run(tmp_path, whole):
    """cpu_threads is allowed: the actor phase resumed on 2 threads ends with the 1-thread numbers."""
    from test_fault_injection import assert_same_run

    run_dir = cut_copy(whole, tmp_path / "run")
    result = run_train("resume=true", "cpu_threads=2", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert_same_run(run_dir, whole)


def test_n_runs_3_on_a_2_run_run_is_one_line_and_changes_nothing(tmp_path, whole):
    """The issue's case: was `size mismatch for b_r …` and a traceback."""
    run_dir = tmp_path / "run"
    shutil.copytree(whole, run_dir)
    before = snapshot(run_dir)
    result = run_train(*TMAZE, "n_runs=3", "resume=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(
        f"ferl: error: resume=true continues the run in {run_dir} under its own config, and "
        f"these overrides would change what it computes: n_runs: 2 → 3 (a resume may change"
    )
    assert snapshot(run_dir) == before  # .hydra/ put back as the run wrote it, tb/ and checkpoints as they were


def test_a_key_given_twice_counts_with_its_last_value():
    """Hydra lets a later override of a key win (tests pass a tiny base, then their own value)."""
    identity = RunIdentity({"trainer": {"steps": 8000}}, {})
    assert apply_overrides(identity, ["trainer.steps=300", "trainer.steps=8000"]) == ({"trainer": {"steps": 8000}}, [])
    assert apply_overrides(identity, ["trainer.steps=8000", "trainer.steps=300"])[1] == [("trainer.steps", 8000, 300)]
