"""The study database of ``hparams_search=…`` (ferl's Optuna sweeper, ferl/run/study*.py; docs/sweeps.md,
"The study database"): a study killed mid-trial, between trials or while it writes a value resumes
with its finished trials kept and ends as an uninterrupted one; two worker processes fill one study,
no trial twice; a corrupt file, or one that holds another study, is refused in one line and left
byte for byte as it was.

Every study here is a real ``train.py -m hparams_search=matching_optuna`` at a tiny scale (one run,
a few hundred actor episodes: about a second a trial).
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend
from optuna.trial import TrialState

from conftest import ROOT, eager, run_train
from ferl.run.study import INTERRUPTED, RETRY_OF, SLOT, WORKER, consecutive, slot_sampler
from ferl.run.study_space import search_space
from ferl.run.study_storage import IDENTITY

optuna.logging.set_verbosity(optuna.logging.WARNING)

# 4 trials, TPE after the first 2: the trial killed (slot 2) and the one after it are TPE's
STUDY = [
    "hparams_search=matching_optuna",
    "hydra.sweeper.n_trials=4",
    "hydra.sweeper.sampler.n_startup_trials=2",
    "n_runs=1",
    "trainer.n_sample=200",
    "trainer.n_epoch=3",
    "trainer.n_episodes=300",
    "trainer.log_every=100",
    "trainer.td_sample_every=100",
    "trainer.final_window=100",
]


def start(sweep: Path, *overrides: str) -> subprocess.Popen:
    """``train.py -m STUDY overrides`` into ``sweep``, in the background."""
    return subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), "-m", *eager([*STUDY, *overrides, f"hydra.sweep.dir={sweep}"])],
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def trials(sweep: Path, storage: str = "sqlite") -> list:
    """The study's trials, read through Optuna."""
    where = (
        JournalStorage(JournalFileBackend(str(sweep / "study.journal")))
        if storage == "journal"
        else f"sqlite:///{sweep / 'study.db'}"
    )
    return optuna.load_study(study_name="matching_optuna", storage=where).get_trials()


def by_slot(finished: list) -> dict:
    """Slot → (parameters, value) of the study's COMPLETE trials."""
    return {t.user_attrs[SLOT]: (t.params, t.value) for t in finished if t.state == TrialState.COMPLETE}


def wait_for_job(sweep: Path, job: str, process: subprocess.Popen, timeout: float = 120) -> None:
    """Until the sweep's progress file records that ``job`` started."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        progress = sweep / "progress.jsonl"
        if progress.exists() and any(
            e.get("event") == "start" and e.get("job", "").split("+")[0] == job  # the folder may name overrides
            for e in map(json.loads, filter(str.strip, progress.read_text().splitlines()))
        ):
            return
        assert process.poll() is None, process.communicate()[0][-3000:]
        time.sleep(0.05)
    raise AssertionError(f"{job} did not start")


def test_a_killed_study_resumes_as_an_uninterrupted_one(tmp_path):
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    whole, victim = start(reference), start(killed)
    wait_for_job(killed, "2_table4_1_matching", victim)
    victim.send_signal(signal.SIGKILL)  # mid-trial: no handler runs, the trial stays RUNNING
    victim.wait()
    assert whole.wait(timeout=300) == 0, whole.communicate()[0][-3000:]
    before = trials(killed)
    assert [t.state for t in before] == [TrialState.COMPLETE] * 2 + [TrialState.RUNNING]

    resumed = run_train("-m", *STUDY, f"hydra.sweep.dir={killed}", timeout=300)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    assert "2/4 trials done, 1 interrupted to run again" in resumed.stdout
    after = trials(killed)
    # the finished trials kept as they were; the dead one failed, run again with its parameters
    assert [(t.number, t.params, t.value, t.datetime_complete) for t in after[:2]] == [
        (t.number, t.params, t.value, t.datetime_complete) for t in before[:2]
    ]
    assert after[2].state == TrialState.FAIL and after[2].user_attrs[INTERRUPTED]
    assert after[3].user_attrs[RETRY_OF] == 2 and after[3].params == before[2].params
    assert after[3].user_attrs[WORKER] != before[2].user_attrs[WORKER]
    assert sum(t.state == TrialState.COMPLETE for t in after) == 4 and all(t.state.is_finished() for t in after)
    # the same suggestion and value in every slot, so the same best
    assert by_slot(after) == by_slot(trials(reference))
    best, best_reference = (yaml.safe_load((d / "optimization_results.yaml").read_text()) for d in (killed, reference))
    assert best["best_value"] == best_reference["best_value"] and best["best_params"] == best_reference["best_params"]
    assert best["best_value"] == max(t.value for t in after if t.value is not None)


KILL_POINTS = Path(__file__).parent / "kill_points"  # its sitecustomize kills a process at FERL_KILL_AT


def killed_at(sweep: Path, moment: str) -> None:
    """The study in ``sweep`` continued until the sweeper dies by SIGKILL at ``moment``
    (tests/kill_points/sitecustomize.py)."""
    paths = os.pathsep.join(filter(None, [str(KILL_POINTS), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": paths, "FERL_KILL_AT": moment}
    died = run_train("-m", *STUDY, f"hydra.sweep.dir={sweep}", env=env, timeout=300)
    assert died.returncode == -signal.SIGKILL, died.stdout[-3000:] + died.stderr[-3000:]


def test_a_study_killed_between_trials_and_while_writing_ends_as_an_uninterrupted_one(tmp_path):
    """The two other moments of a kill (mid-trial: the test above): after a trial's value is told and
    before the next trial is claimed, then inside the SQLite transaction that tells a value, its rows
    written but not committed. The study resumes each time, and ends with the uninterrupted one's
    parameters and value in every slot and its best."""
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    whole = start(reference)
    killed_at(killed, "between:1")
    assert [(t.state, t.user_attrs[SLOT]) for t in trials(killed)] == [(TrialState.COMPLETE, 0)]
    killed_at(killed, "writing:1")  # the first value this process tells: slot 1's
    before = trials(killed)
    assert [t.state for t in before] == [TrialState.COMPLETE, TrialState.RUNNING]
    assert before[1].value is None and before[1].user_attrs[SLOT] == 1  # never committed

    resumed = run_train("-m", *STUDY, f"hydra.sweep.dir={killed}", timeout=300)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    assert "1/4 trials done, 1 interrupted to run again" in resumed.stdout
    assert whole.wait(timeout=300) == 0, whole.communicate()[0][-3000:]
    after = trials(killed)
    assert after[1].state == TrialState.FAIL and after[2].user_attrs[RETRY_OF] == 1
    assert by_slot(after) == by_slot(trials(reference))
    best, best_reference = (yaml.safe_load((d / "optimization_results.yaml").read_text()) for d in (killed, reference))
    assert (best["best_value"], best["best_params"]) == (best_reference["best_value"], best_reference["best_params"])


@pytest.mark.parametrize("storage", ["sqlite", "journal"])
def test_two_workers_fill_one_study(tmp_path, storage):
    sweep = tmp_path / "study"
    # trials of ~0.5 s: long enough that the second process, ready a moment after the first, gets some
    workers = [start(sweep, f"hydra.sweeper.storage={storage}", "trainer.n_episodes=150") for _ in range(2)]
    for worker in workers:
        assert worker.wait(timeout=300) == 0, worker.communicate()[0][-3000:]
    study = trials(sweep, storage)
    assert [t.state for t in study] == [TrialState.COMPLETE] * 4
    assert sorted(t.user_attrs[SLOT] for t in study) == [0, 1, 2, 3]
    assert len({tuple(sorted(t.params.items())) for t in study}) == 4  # no trial twice
    assert len({t.user_attrs[WORKER] for t in study}) == 2  # both processes ran trials
    assert sorted(p.name for p in sweep.glob("study.*")) == [f"study.{'db' if storage == 'sqlite' else 'journal'}"]
    assert sorted(int(p.name.split("_")[0]) for p in sweep.glob("*_table4_1_matching*")) == [0, 1, 2, 3]
    assert yaml.safe_load((sweep / "optimization_results.yaml").read_text())["n_complete"] == 4


def another_search(file: Path) -> None:
    """A study of the same name, made by this sweeper over another range of the learning rate."""
    space = search_space({"actor.lr.value": "interval(0.1, 0.2)", "actor.beta.end": "interval(2.0, 20.0)"}, [])
    study = optuna.create_study(study_name="matching_optuna", storage=f"sqlite:///{file}", direction="maximize")
    study.set_user_attr(IDENTITY, space.identity())


REFUSED = {
    "not sqlite": (
        "study.db",
        lambda f: f.write_bytes(np.random.default_rng(0).bytes(4096)),
        "is not a SQLite database",
    ),
    "corrupt sqlite": (
        "study.db",
        lambda f: f.write_bytes(b"SQLite format 3\x00" + np.random.default_rng(1).bytes(8192)),
        "is a corrupt SQLite database",
    ),
    "another study": (
        "study.db",
        lambda f: optuna.create_study(study_name="other", storage=f"sqlite:///{f}"),
        "holds another study ('other'), not 'matching_optuna'",
    ),
    "another search": (
        "study.db",
        another_search,
        "holds study 'matching_optuna' (0 trials) of another search: actor.lr.value: interval(0.1, 0.2) there, "
        "tag(log, interval(0.005, 0.5)) here",
    ),
    "corrupt journal": (
        "study.journal",
        lambda f: f.write_text('{"op_code": 0, "study_name": "matching_optuna", "directions": [2]}\n{"op_co'),
        "is not a readable Optuna journal: line 2",
    ),
}


@pytest.mark.parametrize("case", REFUSED)
def test_a_study_file_that_is_not_this_study_is_refused_untouched(tmp_path, case):
    name, make, message = REFUSED[case]
    sweep = tmp_path / "study"
    sweep.mkdir()
    make(sweep / name)
    before = (sweep / name).read_bytes()
    storage = "journal" if name.endswith("journal") else "sqlite"
    result = run_train("-m", *STUDY, f"hydra.sweeper.storage={storage}", f"hydra.sweep.dir={sweep}", timeout=120)
    assert result.returncode == 2, result.stdout[-2000:] + result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ferl: error: {sweep / name} "), result.stderr
    assert message in lines[0]
    assert (sweep / name).read_bytes() == before
    assert not list(sweep.glob("*_table4_1_matching*"))


def test_search_space_reads_hydra_sweep_syntax():
    space = search_space(
        {"a": "tag(log, interval(0.005, 0.5))", "b": "interval(2.0, 20.0)", "c": "range(10, 41, 10)"},
        ["d=choice(x, y)", "e=tag(int, interval(1, 8))", "b=3.5", "n_runs=2"],
    )
    assert {k: type(d).__name__ for k, d in space.distributions.items()} == {
        "a": "FloatDistribution",
        "c": "IntDistribution",
        "d": "CategoricalDistribution",
        "e": "IntDistribution",
    }
    assert space.distributions["a"].log and (space.distributions["c"].low, space.distributions["c"].high) == (10, 40)
    assert space.distributions["c"].step == 10 and space.distributions["d"].choices == ("x", "y")
    assert space.fixed == ["b=3.5", "n_runs=2"]  # the command line fixed b
    assert space.overrides({"a": 0.01, "d": "y"}) == ["b=3.5", "n_runs=2", "a=0.01", "d=y"]


def test_jobs_are_launched_in_runs_of_consecutive_trial_numbers():
    assert consecutive([4, 5, 7, 8, 9, 2]) == [(4, 2), (7, 3), (2, 1)]


def test_a_fresh_tpe_sampler_does_not_repeat_an_uninterrupted_study_but_slot_seeds_do():
    """Why each slot gets its own sampler: Optuna's TPESampler(seed) draws every suggestion from one
    random stream; a process that resumes starts that stream afresh, and its suggestions part from
    the uninterrupted study's at the first trial after the restart."""
    space = search_space({"x": "tag(log, interval(0.005, 0.5))", "y": "interval(2.0, 20.0)"}, [])

    def study(restart_at: int | None, per_slot: bool) -> list:
        config = {"_target_": "optuna.samplers.TPESampler", "seed": 0, "n_startup_trials": 3}
        s = optuna.create_study(direction="maximize")
        for i in range(8):
            if i == 0 or per_slot or i == restart_at:  # restart_at: a new process, a new sampler
                s.sampler = (
                    slot_sampler(config, i) if per_slot else optuna.samplers.TPESampler(seed=0, n_startup_trials=3)
                )
            trial = s.ask(space.distributions)
            s.tell(trial, -((np.log(trial.params["x"]) + 3) ** 2) - (trial.params["y"] - 7) ** 2 / 10)
        return [t.params for t in s.trials]

    assert study(5, per_slot=False)[5:] != study(None, per_slot=False)[5:]
    assert study(5, per_slot=True) == study(None, per_slot=True)
