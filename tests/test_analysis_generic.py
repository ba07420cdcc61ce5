"""The analysis every run gets (ferl.analysis.generic) and the dispatch on what a run recorded
(ferl.analysis.dispatch, with the chapters `reproduction` registers), on synthetic runs: a run of a task no chapter knows, a digit-floor
run, T-mazes with predictors of every role, and a run without records/run.json."""

import csv
import json
import math
import statistics
from pathlib import Path

import numpy as np
import pytest

from ferl.analysis import dispatch, generic, runner
from ferl.analysis.claims import HELD, NOT_HELD, Chapter, Claim, Measured, Numbering
from ferl.analysis.records import Manifest, predictor_role
from ferl.analysis.report import RunAnalysis
from reproduction import ch3, ch4, ch5
from synthetic_runs import assert_analysis_outputs, load_run, make_floor_run, make_tmaze_run, make_toy_run
from test_analyze_cli import analyze, event_files

WINDOW = 200  # episodes: the moving average of Figs. 4.6–4.8


def rows(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def trailing_means(values: np.ndarray, window: int) -> np.ndarray:
    """Each run's mean over every `window` consecutive entries, one window at a time."""
    return np.array(
        [
            [row[k - window : k].mean() for k in range(window, len(row) + 1)]
            for row in np.asarray(values, dtype=np.float64)
        ]
    )


def test_a_run_of_an_unknown_task_gets_the_generic_figures_and_no_claims(tmp_path):
    """A task of one's own: a plain "Report", no claims section and no word of the dissertation
    (its claims and chapters do not speak to it)."""
    run_dir = make_toy_run(tmp_path / "toy", n_episodes=300, n_epochs=5)
    result = analyze(run_dir)
    assert result.returncode == 0, result.stderr
    report = assert_analysis_outputs(
        run_dir,
        ["learning_curves", "td_errors", "prediction_errors_world"],
        ["summary.csv", "learning_curves.csv", "prediction_errors_world.csv", "claims.json"],
    )
    assert report.startswith("# Report: toy_experiment (task `toy`)")
    assert "## Claims" not in report and "claim applies" not in report
    assert "dissertation" not in report and "chapter" not in report and "Fig. " not in report
    assert json.loads((run_dir / "analysis" / "claims.json").read_text()) == []
    assert event_files(run_dir)

    # summary table: mean ± s.d. (ddof 1) over the runs with a value
    summary = {r["metric"]: r for r in rows(run_dir / "analysis" / "summary.csv")}
    assert set(summary) == {"final_return", "score/easy", "score/hard"}
    for name, values in (
        ("final_return", [1.0, 2.0, 3.0]),
        ("score/easy", [1.0, 0.5]),
        ("score/hard", [0.2, 0.4, 0.9]),
    ):
        assert float(summary[name]["mean"]) == pytest.approx(statistics.mean(values), rel=1e-5)
        assert float(summary[name]["sd"]) == pytest.approx(statistics.stdev(values), rel=1e-5)
        assert int(summary[name]["n_runs"]) == len(values)
    assert "| score/easy | 0.75 | 0.35 | 2 |" in report

    # learning curves: the return of run r is r + episode/300, |δ| is 1 − episode/300
    curves = rows(run_dir / "analysis" / "learning_curves.csv")
    assert [int(r["episode"]) for r in curves] == list(range(WINDOW, 301))
    progress = np.arange(300) / 300
    returns = trailing_means(np.arange(3)[:, None] + progress, WINDOW)
    for k in (0, 50, -1):
        r = curves[k]
        assert float(r["discounted_return_ma200_mean"]) == pytest.approx(returns[:, k].mean(), rel=1e-5)
        assert float(r["discounted_return_ma200_sem"]) == pytest.approx(
            statistics.stdev(returns[:, k]) / math.sqrt(3), rel=1e-5
        )
        assert float(r["td_abs_mean_ma200_mean"]) == pytest.approx(
            trailing_means((1 - progress)[None], WINDOW)[0, k], rel=1e-5
        )
        assert float(r["discounted_return_ma200_run_2"]) == pytest.approx(returns[2, k], rel=1e-5)
    assert "reached_ma200_mean" in curves[0]  # the environment's boolean outcome, as a rate

    # prediction errors: n_epochs − epoch everywhere, so 5 at epoch 0 and 0 at the last
    errors = rows(run_dir / "analysis" / "prediction_errors_world.csv")
    assert {(r["split"], int(r["T"])) for r in errors} == {(s, T) for s in ("train", "test") for T in (2, 3, 4)}
    assert all(float(r["epoch0_mean"]) == 5.0 and float(r["epoch5_mean"]) == 0.0 for r in errors)
    assert all(r["trained_length"] == "1" for r in errors)  # no L_training: all trained


def test_continuing_runs_get_reward_and_td_curves_from_steps_npz(tmp_path):
    run = load_run(make_floor_run(tmp_path / "floor", n_runs=3, steps=400))
    c = generic.curves(run)
    steps = run.records("steps")
    assert (c.unit, c.window, c.length) == ("step", 100, 400)
    np.testing.assert_array_equal(c.x, np.arange(100, 401))
    np.testing.assert_allclose(c.series["reward"], trailing_means(steps["rewards"], 100), rtol=1e-6)
    np.testing.assert_allclose(c.series["td_abs"], trailing_means(np.abs(steps["td_errors"]), 100), rtol=1e-6)
    _, sem = c.mean_sem("reward")
    k = 123
    assert sem[k] == pytest.approx(statistics.stdev(c.series["reward"][:, k]) / math.sqrt(3))
    assert c.optima["reward"] == 8.0


def test_episodic_curves_take_the_optimum_from_the_records_and_the_environment(tmp_path):
    c = generic.curves(load_run(make_tmaze_run(tmp_path / "maze")))
    assert list(c.series) == ["discounted_return", "steps", "terminal_reward", "correct_goal", "td_abs_mean"]
    assert c.optima["discounted_return"] == pytest.approx(4.3175)
    assert (c.optima["steps"], c.optima["terminal_reward"]) == (3.0, 5.0)  # env.goal_reward


@pytest.mark.parametrize(
    "facts, role",
    [
        ({"predicts_observation": True, "reward_output": "bits"}, "joint"),
        ({"predicts_observation": True, "reward_output": "none"}, "observation"),
        ({"predicts_observation": False, "reward_output": "linear"}, "reward"),
        ({"predicts_observation": True, "reward_output": "linear"}, None),
        ({"predicts_observation": False, "reward_output": "bits"}, None),
    ],
)
def test_a_predictor_role_follows_what_it_predicts(facts, role):
    assert predictor_role({"kind": "anything", **facts}) == role


PHASED = {"kind": "phased", "phases": ["collect", "predictors", "actor"]}


def manifest(kind: str, predictors: dict, trainer: dict = PHASED, memory: str = "elman", **env) -> Manifest:
    facts = {
        "joint": {"predicts_observation": True, "reward_output": "bits"},
        "obs": {"predicts_observation": True, "reward_output": "none"},
        "rew": {"predicts_observation": False, "reward_output": "linear"},
    }
    return Manifest(
        "t",
        "e",
        trainer,
        {"kind": kind, **env},
        None,
        {name: {"kind": memory, **facts[f]} for name, f in predictors.items()},
        {},
    )


def test_chapters_are_chosen_by_recorded_facts_not_names():
    assert dispatch.REGISTRY.chapter_of(manifest("digit_floor", {})) is ch3.CHAPTER
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"anything": "joint"})) is ch4.CHAPTER
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"a": "obs", "b": "rew"})) is ch5.CHAPTER
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"j1": "joint", "j2": "joint"})) is None
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"a": "obs"})) is None
    assert dispatch.REGISTRY.chapter_of(manifest("toy", {"joint": "joint"})) is None
    # the dissertation's claims speak to its procedure and memory only (§5.4's are findings of ours)
    online = {"kind": "online", "phases": ["online"]}
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"anything": "joint"}, trainer=online)) is None
    assert dispatch.REGISTRY.chapter_of(manifest("tmaze", {"a": "obs", "b": "rew"}, memory="lstm")) is None
    assert ch4.CHAPTER.numbering(manifest("tmaze", {}, matching=True)) is ch4.MATCHING
    assert ch5.CHAPTER.numbering(manifest("tmaze", {}, observation="image")) is ch5.DIGIT
    assert ch5.CHAPTER.numbering(manifest("tmaze", {}, observation="bits")) is ch5.BIT


def test_a_run_without_a_manifest_is_skipped(tmp_path, capsys):
    run_dir = make_floor_run(tmp_path / "older")
    (run_dir / "records" / "run.json").unlink()
    outcome = runner.analyze_run(run_dir)
    assert outcome.status == "skipped: no records/run.json"
    assert not (run_dir / "analysis").exists()
    assert "skipped, no records/run.json" in capsys.readouterr().out


def test_prediction_error_title_fits_when_all_episodes_have_one_length():
    """One episode length gives one column per split: a figure 3.1 inches wide, narrower than its
    title unless the title is wrapped to it."""
    from ferl.analysis import figures as figs

    errors = np.random.default_rng(0).random((5, 1, 4))
    title = "Fig. 4.5: prediction errors of the `joint` predictor, mean over 10 runs (table4_1_matching)"
    fig = figs.prediction_errors(errors, errors, np.array([3]), np.arange(5), 3, "cross entropy", title)
    fig.canvas.draw()
    box, frame = fig._suptitle.get_window_extent(), fig.bbox
    assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and box.y1 <= frame.y1, (box, frame)
    assert fig._suptitle.get_text().replace("\n", " ") == title


def test_ferl_alone_gives_the_generic_analysis_and_takes_a_plug_in(tmp_path, monkeypatch):
    """ferl's analysis without reproduction/ (an empty registry): a digit-floor run gets the generic
    figures only, no claim and no dissertation; a registry with an environment analysis and a chapter
    of its own (a plug-in's) adds its section, its figure numbers and its judged claim."""
    run_dir = make_floor_run(tmp_path / "floor")
    generic_figures = set(generic.analyze(load_run(run_dir), Numbering(), tmp_path).figures)
    monkeypatch.setattr(runner, "REGISTRY", dispatch.Registry())
    outcome = runner.analyze_run(run_dir)
    report = (run_dir / "analysis" / "report.md").read_text()
    assert outcome.status == "analyzed" and outcome.results == []
    assert {name for name, _ in outcome.figures} == generic_figures
    assert "## Claims" not in report  # no chapter is registered: no claims section at all
    assert "dissertation" not in report and "Fig. 3." not in report

    def floor_analysis(run, num, out):
        return run, RunAnalysis("the floor, by a plug-in", sections=[("Plug-in", [f"{run.experiment}"])])

    two_runs = Claim(
        "Two runs were trained.",
        "§9.9",
        lambda run: Measured(len(run.summary["seeds"]), "runs"),
        lambda n: HELD if n == 2 else NOT_HELD,
    )
    chapter = Chapter(
        "a toy model",
        lambda m: m.env_kind == "digit_floor",
        lambda m: Numbering(learning_curves="Fig. 9.1"),
        [two_runs],
    )
    monkeypatch.setattr(
        runner,
        "REGISTRY",
        dispatch.Registry(reference="toy paper", environments={"digit_floor": floor_analysis}, chapters=[chapter]),
    )
    outcome = runner.analyze_run(run_dir)
    report = (run_dir / "analysis" / "report.md").read_text()
    assert [(r.claim, r.verdict) for r in outcome.results] == [(two_runs, HELD)]
    assert report.startswith("# the floor, by a plug-in\n") and "\n## Plug-in\n" in report
    assert "- **toy paper**: a toy model" in report and "| Two runs were trained. | §9.9 |" in report
    assert dict(outcome.figures)["learning_curves"].startswith("Fig. 9.1: ")


def test_the_workers_of_a_parallel_analysis_see_the_registered_plug_ins(tmp_path):
    """From runner.POOL_MIN_RUNS runs on, runs are analysed in worker processes, whose registry
    starts empty: each imports the registered plug-ins (here `reproduction`) and judges chapter 3's
    claims as the parent process does."""
    found = [make_floor_run(tmp_path / f"run_{k}", n_runs=2, steps=200) for k in range(runner.POOL_MIN_RUNS)]
    outcomes = runner.analyze_runs(found)
    serial = runner.analyze_run(found[0])
    assert [o.status for o in outcomes] == ["analyzed"] * len(found)
    assert serial.results and all(r.claim in ch3.CLAIMS for r in serial.results)
    for outcome in outcomes:
        assert [r.claim.text for r in outcome.results] == [r.claim.text for r in serial.results]


def test_a_failed_run_is_one_write_to_stderr(tmp_path, monkeypatch):
    """The pool's workers share stderr, which writes through: a run's error line must reach it in
    one write, or another worker's line can land between the line and its newline."""
    writes: list[str] = []

    class Recorder:
        def write(self, text: str) -> int:
            writes.append(text)
            return len(text)

        def flush(self) -> None:
            pass

    (tmp_path / "summary.json").write_text("[]\n")  # damaged: a JSON array, not an object
    monkeypatch.setattr("sys.stderr", Recorder())
    outcome = runner._safe_analyze_run(tmp_path)
    assert outcome.status.startswith("failed: ValueError: summary.json is damaged")
    assert writes == [
        f"analyze.py: error: {tmp_path}: ValueError: summary.json is damaged (a JSON list, not an object)\n"
    ]


@pytest.mark.parametrize("enabled", [True, False])
def test_a_runs_analysis_frees_its_figures_and_leaves_the_collector_as_it_found_it(tmp_path, enabled):
    """The collector is paused while a run is analysed and run once at the end
    (runner._collected_once): afterwards no figure of the run is left waiting to be collected,
    and the collector is on or off as before."""
    import gc

    from matplotlib.figure import Figure

    run = make_floor_run(tmp_path / "run", n_runs=2, steps=200)
    before = {id(o) for o in gc.get_objects() if isinstance(o, Figure)}
    was_enabled = gc.isenabled()
    (gc.enable if enabled else gc.disable)()
    try:
        outcome = runner._safe_analyze_run(run, force=True)
        assert gc.isenabled() is enabled
        left = [o for o in gc.get_objects() if isinstance(o, Figure) and id(o) not in before]
    finally:
        (gc.enable if was_enabled else gc.disable)()
    assert outcome.status == "analyzed" and len(outcome.figures) >= 5
    assert left == []
