"""Sweep analysis (issue 4/7): aggregation, the noise grid, claim thresholds, the README block,
and a smoke sweep through `train.py -m` and `analyze.py`."""

import copy
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import reproduction
from ferl.analysis import runner
from ferl.analysis import sweep as sw
from ferl.analysis.claims import HELD, NOT_HELD, PARTLY, Claim, ClaimResult, Measured, evaluate
from ferl.analysis.report import RunOutcome
from reproduction import ch3, ch4, noise_grid, published
from reproduction.floor import FloorRun
from reproduction.sweep_claims import SWEEP_CLAIMS
from reproduction.tmaze import TMazeRun
from synthetic_runs import load_run, make_floor_run, make_tmaze_run, make_toy_run

REPO = Path(__file__).resolve().parents[1]
LEVELS = ["0", "0.5", "1"]


def fake_job(
    run_dir: Path,
    experiment: str,
    metrics: dict,
    overrides=(),
    facts=None,
    verdict: str | None = None,
    wall: float = 1.0,
) -> sw.Job:
    """A job directory holding only summary.json, Hydra's overrides and records/run.json with
    the parts' parameters in `facts` ({"env": {"noise": 0.5}})."""
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / "records").mkdir()
    summary = {
        "experiment": experiment,
        "task": "digit_floor",
        "metrics": metrics,
        "wall_time_s": wall,
        "agent_steps_per_s": 100.0,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary))
    (run_dir / ".hydra" / "overrides.yaml").write_text(
        yaml.safe_dump([f"experiment={experiment}", *overrides, "hydra/launcher=joblib"])
    )
    (run_dir / "records" / "run.json").write_text(
        json.dumps({"task": "digit_floor", "experiment": experiment, **(facts or {})})
    )
    results = []
    if verdict is not None:
        claim = Claim("pairs cluster", ch3.SAME_ACTION_PAIRS_SOURCE, lambda run: None, lambda v: v)
        results = [ClaimResult(claim, Measured(verdict, verdict), verdict)]
    return sw.Job(RunOutcome(run_dir, experiment, "digit_floor", "analyzed", results=results), summary)


def noise_job(root: Path, k: int, train_noise: float, acc: dict) -> sw.Job:
    return fake_job(
        root / f"{k}",
        "floor",
        {"reward_per_step_last10pct": [1.0, 2.0], "greedy_accuracy": acc},
        overrides=[f"env.noise={train_noise}"],
        facts={"env": {"noise": train_noise}},
    )


def test_aggregate_is_mean_and_sem_over_runs(tmp_path):
    a = fake_job(
        tmp_path / "a", "floor", {"reward_per_step_last10pct": [1.0, 2.0, 6.0], "greedy_accuracy": {"0.5": [0.5, 0.7]}}
    )
    b = fake_job(
        tmp_path / "b",
        "maze",
        {"solved": [1, 0, 1, 1], "final": [2.0, float("nan")]},
        overrides=["env.corridor_length=6"],
        wall=5.0,
    )
    rows = {(r.experiment, r.variant, r.metric): r for r in sw.aggregate([a, b])}

    reward = rows["floor", sw.BASE_SETTING, "reward_per_step_last10pct"]
    assert (reward.mean, reward.n) == (3.0, 3)
    assert reward.sem == pytest.approx(math.sqrt(7.0) / math.sqrt(3))  # s.d. √7 (ddof 1)
    acc = rows["floor", sw.BASE_SETTING, "greedy_accuracy/0.5"]
    assert acc.mean == pytest.approx(0.6) and acc.sem == pytest.approx(0.1)
    solved = rows["maze", "env.corridor_length=6", "solved"]
    assert solved.mean == 0.75 and solved.sem == pytest.approx(0.25)
    diverged = rows["maze", "env.corridor_length=6", "final"]  # a NaN run is left out, n shows it
    assert (diverged.mean, diverged.n) == (2.0, 1) and math.isnan(diverged.sem)
    assert rows["maze", "env.corridor_length=6", "wall_time_s"].mean == 5.0

    tables = sw.experiment_tables(sw.aggregate([a, b]))
    assert set(tables) == {"floor", "maze"}
    assert "| solved | 0.75 ± 0.25 |" in tables["maze"]
    assert "| reward_per_step_last10pct | 3 ± 1.5 |" in tables["floor"]


def test_a_sweep_of_ones_own_task_is_a_report_without_the_dissertation(tmp_path):
    """A sweep whose runs no chapter speaks to (a task of one's own) is a plain "Report": no claims
    section, its job without overrides not "as in the dissertation"; a dissertation run in the
    sweep makes it the reproduction report again, that job "as in the dissertation"."""
    own = make_toy_run(tmp_path / "own" / "0_toy_experiment")
    runner.analyze_sweep(own.parent)
    report = (own.parent / "analysis" / "report.md").read_text()
    assert report.startswith(f"# Report: sweep `{own.parent}`")
    assert "## Claims" not in report and "**claims**" not in report
    assert "dissertation" not in report and f"`{sw.BASE_SETTING}`" in report

    make_floor_run(tmp_path / "own" / "1_ch3_floor")
    runner.analyze_sweep(own.parent)
    report = (own.parent / "analysis" / "report.md").read_text()
    assert report.startswith(f"# Reproduction report: sweep `{own.parent}`")
    assert "## Claims of the dissertation" in report
    assert "`as in the dissertation` — [1_ch3_floor]" in report and "`no overrides` — [0_toy_experiment]" in report


def test_noise_grid_from_jobs_that_differ_only_in_training_noise(tmp_path):
    truth = np.array([[0.9, 0.8, 0.3], [0.7, 0.7, 0.4]])  # rows: training noise 0, 0.5
    jobs = [
        noise_job(tmp_path, k, noise, {lvl: [truth[k, j] - 0.1, truth[k, j] + 0.1] for j, lvl in enumerate(LEVELS)})
        for k, noise in enumerate([0.0, 0.5])
    ]
    # A job with another override too belongs to another grid (here: a single level, no grid).
    jobs.append(
        fake_job(
            tmp_path / "x",
            "floor",
            {"greedy_accuracy": {"0": [0.0]}},
            overrides=["env.noise=1.0", "actor.n_hidden=40"],
            facts={"env": {"noise": 1.0}},
        )
    )
    [grid] = noise_grid.noise_grids(sw.Sweep(tmp_path, jobs))
    np.testing.assert_allclose(grid.train, [0.0, 0.5])
    np.testing.assert_allclose(grid.test, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(grid.mean, truth)
    np.testing.assert_allclose(grid.sem, 0.1)


@pytest.mark.parametrize(
    "verdicts, expected",
    [
        ({10: HELD, 20: HELD, 40: HELD}, HELD),
        ({10: PARTLY, 20: HELD, 40: HELD}, PARTLY),
        ({10: NOT_HELD, 20: HELD, 40: HELD}, NOT_HELD),
        ({10: NOT_HELD, 20: NOT_HELD}, NOT_HELD),
    ],
)
def test_hidden_size_claim_flips_with_the_verdicts_per_size(tmp_path, verdicts, expected):
    jobs = [
        fake_job(
            tmp_path / str(n),
            "coding",
            {},
            overrides=[f"actor.n_hidden={n}"],
            facts={"actor": {"n_hidden": n}},
            verdict=v,
        )
        for n, v in verdicts.items()
    ]
    [result] = evaluate(SWEEP_CLAIMS, sw.Sweep(tmp_path, jobs))
    assert result.verdict == expected
    assert all(f"{n} hidden: {v}" in result.measured.text for n, v in verdicts.items())


def test_claims_are_judged_on_the_job_with_fewest_overrides(tmp_path):
    jobs = [
        fake_job(
            tmp_path / "variant",
            "coding",
            {},
            overrides=["actor.n_hidden=40"],
            facts={"actor": {"n_hidden": 40}},
            verdict=NOT_HELD,
        ),
        fake_job(tmp_path / "main", "coding", {}, facts={"actor": {"n_hidden": 20}}, verdict=HELD),
    ]
    rows = sw.reproduction_rows(jobs, evaluate(SWEEP_CLAIMS, sw.Sweep(tmp_path, jobs)), reproduction.CLAIM_ORDER)
    [row] = [r for r in rows if r.job is not None]
    [across] = [r for r in rows if r.job is None]
    assert row.job.run_dir.name == "main" and row.result.verdict == HELD
    assert [(j.variant, r.verdict) for j, r in row.others] == [("actor.n_hidden=40", NOT_HELD)]
    assert across.job is None and across.result.verdict == NOT_HELD


def test_claims_keep_the_publication_order_when_jobs_return_copies_of_them(tmp_path):
    """A job analysed in a worker process returns copies of the registered claims (pickled back),
    a kept analysis the registered claims themselves: either way the report lists its claims,
    the across-jobs ones among them, in the publication's order (CLAIM_ORDER)."""
    order = reproduction.CLAIM_ORDER
    position = {(c.text, c.source): k for k, c in enumerate(order)}
    first, last = copy.deepcopy(order[0]), copy.deepcopy(order[-1])
    jobs = [fake_job(tmp_path / "a", "coding", {}), fake_job(tmp_path / "b", "coding", {})]
    for job, claim in zip(jobs, (last, first)):  # the last claim's job first
        job.outcome.results.append(ClaimResult(claim, Measured("m", "m"), HELD))
    across = SWEEP_CLAIMS[0]
    rows = sw.reproduction_rows(jobs, [ClaimResult(across, Measured("m", "m"), HELD)], order)
    ranks = [position[(r.result.claim.text, r.result.claim.source)] for r in rows]
    assert first is not order[0] and len(rows) == 3 and ranks == sorted(ranks)
    assert ranks[0] == 0 and ranks[-1] == len(order) - 1


def _rewrite_summary(run_dir: Path, **metrics) -> None:
    path = run_dir / "summary.json"
    summary = json.loads(path.read_text())
    summary["metrics"].update(metrics)
    path.write_text(json.dumps(summary))


def _verdict(results, source: str) -> str:
    return next(r.verdict for r in results if r.claim.source == source)


@pytest.mark.parametrize("reward, expected", [(6.5, HELD), (6.3, PARTLY), (3.9, NOT_HELD)])
def test_near_optimal_claim_flips_at_0_8_of_the_optimum(tmp_path, reward, expected):
    run_dir = make_floor_run(tmp_path / "run")
    _rewrite_summary(run_dir, reward_per_step_last10pct=[reward, reward])  # optimum 8
    results = evaluate(ch3.CLAIMS, FloorRun.load(load_run(run_dir)))
    assert _verdict(results, "§3.5.1, Fig. 3.4, fn. 4") == expected


@pytest.mark.parametrize(
    "solved, expected",
    [([1] * 10, HELD), ([1] * 9 + [0], PARTLY), ([1] * 8 + [0] * 2, PARTLY), ([1] * 7 + [0] * 3, NOT_HELD)],
)
def test_solved_claim_flips_at_all_runs_and_at_8_in_10(tmp_path, solved, expected):
    run_dir = make_tmaze_run(tmp_path / "run", matching=False)
    _rewrite_summary(run_dir, solved=solved)
    results = evaluate(ch4.CLAIMS, TMazeRun.load(load_run(run_dir)))
    assert _verdict(results, "§4.3.1, Fig. 4.6") == expected


def test_generated_blocks_are_replaced_and_nothing_else(tmp_path):
    jobs = [fake_job(tmp_path / "job", "coding", {}, facts={"actor": {"n_hidden": 20}}, verdict=PARTLY)]
    rows = sw.reproduction_rows(jobs, [], reproduction.CLAIM_ORDER)
    (tmp_path / "docs").mkdir()
    readme, table = tmp_path / "README.md", tmp_path / "docs" / "reproduction.md"
    card, claims = published.SCORECARD, published.TABLE
    readme.write_text(f"# title\n\nbefore\n{card[0]}\nold card\n{card[1]}\nafter\n")
    table.write_text(f"# all\n{claims[0]}\nold table\n{claims[1]}\nend\n")
    published.update_pages([readme, table], rows, {"training wall time": 12.0}, tmp_path / "report.md")
    text = readme.read_text()
    assert text.startswith("# title\n\nbefore\n") and text.endswith(f"{card[1]}\nafter\n")
    assert "old card" not in text and "training wall time 12 s" in text
    assert "[reproduction.md](docs/reproduction.md)" in text
    assert "| Ch. 3: digit floor | 1 | 0 | 1 | 0 |" in text and "| **all** | **1** | **0** | **1** | **0** |" in text
    text = table.read_text()
    assert text.startswith("# all\n") and text.endswith(f"{claims[1]}\nend\n") and "old table" not in text
    assert "| pairs cluster |" in text and "**partly**" in text


@pytest.mark.parametrize(
    "source, expected",
    [
        ("§3.5.1, Fig. 3.4", "3"),
        ("§4.3.2, Fig. 4.14; §4.3.3", "4"),
        ("§5.3.2, Observation preprocessor", "5"),
        ("Fig. 9", "?"),
    ],
)
def test_a_claim_counts_for_the_chapter_of_its_first_section(source, expected):
    assert published.chapter(source) == expected


def run(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


def test_smoke_sweep_through_train_and_analyze(tmp_path):
    sweep = tmp_path / "sweep"
    tiny = ["trainer.steps=200", "n_runs=2", "trainer.test_per_class=5", "env.patches=1"]
    result = run(
        "train.py", "-m", "experiment=ch3_floor,ch3_coding_cw", *tiny, f"hydra.sweep.dir={sweep / 'experiments'}"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    result = run(
        "train.py", "-m", "experiment=ch3_floor", "env.noise=0.0,0.5", *tiny, f"hydra.sweep.dir={sweep / 'noise_grid'}"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    readme = tmp_path / "README.md"
    readme.write_text("{}\n{}\n".format(*published.TABLE))

    result = run("analyze.py", str(sweep), "--readme", str(readme))
    assert result.returncode == 0, result.stderr[-2000:]
    out = sweep / "analysis"
    report = (out / "report.md").read_text()
    jobs = sorted(p.parent for p in sweep.glob("*/*/summary.json"))
    assert len(jobs) == 4
    for job in jobs:
        assert (job / "analysis" / "report.md").is_file()
        assert f"({Path('..', job.relative_to(sweep), 'analysis', 'learning_curves.png')})" in report
    assert "### ch3_floor" in report and "### ch3_coding_cw" in report
    assert (out / "fig3_6_noise_grid_ch3_floor.png").is_file()
    grid = (out / "fig3_6_noise_grid_ch3_floor.csv").read_text().splitlines()
    assert len(grid) == 1 + 3 * 9  # training 0, 0.125 (the experiment's own), 0.5 × 9 test levels
    claims = json.loads((out / "claims.json").read_text())
    assert len({(c["claim"], c["source"]) for c in claims}) == len(claims) >= 10
    assert all(c["verdict"] in (HELD, PARTLY, NOT_HELD) and c["measured"] for c in claims)
    assert "| claim | source | measured | verdict |" in readme.read_text()
    metrics = (out / "metrics.csv").read_text()
    assert f"ch3_coding_cw,{' '.join(tiny)},reward_per_step_last10pct," in metrics
    assert f"ch3_floor,env.noise=0.5 {' '.join(tiny)},greedy_accuracy/0.5," in metrics
