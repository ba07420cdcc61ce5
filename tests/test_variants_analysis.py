"""The sweep report's "Agents side by side" section (reproduction/variants.py) on a real
miniature sweep: the digit floor with the dissertation's actor and with the expected-energy
actor, the regular T-maze with and without a predictor, and a matching T-maze that one agent ran
(no table). Rows are checked against summary.json."""

import csv

import numpy as np
import pytest

from conftest import TINY, train_sweep
from ferl.analysis.records import Manifest
from reproduction.scope import dissertation_components

MAZE = [
    "n_runs=2",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=60",
    "trainer.final_window=20",
    "trainer.log_every=20",
]
RECURRENT_Q = ["trainer=algorithm1", "predictor=none", "actor=recurrent_q"]
RANKED = ("solved", "final_correct_goal_rate", "final_discounted_return")


def mean_sem(values):
    return np.mean(values), np.std(values, ddof=1) / np.sqrt(len(values))


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("variants")
    jobs = {
        "floor_fe": ["experiment=ch3_floor", *TINY],
        "floor_ee": ["experiment=ch3_floor", *TINY, "actor.q=expected_energy"],
        "maze": ["experiment=table4_1_regular", *MAZE],
        "maze_memoryless": ["experiment=table4_1_regular", *MAZE, "predictor=none"],
        "maze_mlp_q": ["experiment=table4_1_regular", *MAZE, "actor=mlp_q"],
        "maze_oracle": ["experiment=table4_1_regular", *MAZE, "actor=oracle", "predictor=none"],
        **{
            f"maze_{head}": ["experiment=table4_1_regular", *MAZE, *RECURRENT_Q, f"actor.head={head}"]
            for head in ("linear", "free_energy")
        },
        "matching": ["experiment=table4_1_matching", *MAZE],
    }
    return root, train_sweep(root, jobs)


def test_one_table_per_task_with_every_agent(sweep):
    root, summaries = sweep
    with open(root / "analysis" / "agents_side_by_side.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["agent"] for r in rows} == {
        "dissertation agent",
        "actor.q=expected_energy",
        "predictor=none",
        "actor=mlp_q",
        "oracle, actor=tabular_q, predictor=none",
        "actor=drqn, predictor=none",
        "actor=recurrent_q, actor.head=free_energy, predictor=none",
    }
    # the oracle's true-state view is the same task; the matching maze, run by one agent, has no table
    assert {r["task"] for r in rows} == {"digit_floor: ch3_floor", "tmaze: table4_1_regular"}
    for name, agent in (("floor_fe", "dissertation agent"), ("floor_ee", "actor.q=expected_energy")):
        row = next(r for r in rows if r["agent"] == agent and r["metric"] == "reward_per_step_last10pct")
        values = summaries[name]["metrics"]["reward_per_step_last10pct"]
        assert float(row["mean"]) == pytest.approx(np.mean(values), rel=1e-5)
        assert float(row["sem"]) == pytest.approx(np.std(values, ddof=1) / np.sqrt(len(values)), rel=1e-5)
        assert int(row["n"]) == 2
    report = (root / "analysis" / "report.md").read_text()
    assert "## Agents side by side (findings of ours, §5.4)" in report
    assert (root / "analysis" / "agents_task2.png").is_file() and "agents_task3" not in report


def test_only_the_dissertation_components_are_judged_by_its_claims(sweep):
    root, _ = sweep
    assert dissertation_components(Manifest.load(root / "floor_fe"))
    assert not dissertation_components(Manifest.load(root / "floor_ee"))
    claims = (root / "floor_ee" / "analysis" / "report.md").read_text()
    assert "## Claims" not in claims and "no chapter's model matches this run" in claims


def test_the_finding_names_the_leader_among_the_agents_that_see_what_the_agent_sees(sweep):
    """The leader by (solved, correct-goal rate, return), the oracle aside, from summary.json."""
    root, summaries = sweep
    agents = {
        "maze": "dissertation agent",
        "maze_memoryless": "predictor=none",
        "maze_mlp_q": "actor=mlp_q",
        "maze_linear": "actor=drqn, predictor=none",
        "maze_free_energy": "actor=recurrent_q, actor.head=free_energy, predictor=none",
    }

    def key(name):
        return tuple(np.mean(summaries[name]["metrics"][m]) for m in RANKED)

    best = max(agents, key=key)
    report = (root / "analysis" / "report.md").read_text()
    line = next(x for x in report.splitlines() if x.startswith("**Best: ") and "table4_1_regular" in x)
    assert line.startswith(f"**Best: {agents[best]} (")
    assert (" FERL (dissertation agent " in line) == (best != "maze")
    assert "Ceiling (oracle on the true state)" in line
    assert not dissertation_components(Manifest.load(root / "maze_oracle"))
    assert not dissertation_components(Manifest.load(root / "maze_mlp_q"))


def test_the_free_energy_head_is_set_against_the_linear_head_on_the_same_core(sweep):
    """The head line's difference and its s.e.m. from summary.json: the first ranking metric on
    which the two heads differ; the family line names the better of FERL and the free-energy head."""
    root, summaries = sweep
    fe, lin = (summaries[f"maze_{head}"]["metrics"] for head in ("free_energy", "linear"))
    metric = next((m for m in RANKED if np.mean(fe[m]) != np.mean(lin[m])), RANKED[0])
    (f, f_sem), (c, c_sem) = mean_sem(fe[metric]), mean_sem(lin[metric])
    report = (root / "analysis" / "report.md").read_text()
    line = next(x for x in report.splitlines() if x.startswith("**Free-energy head against linear head** (gru core)"))
    assert f"{metric} " in line and f"{f - c:+.3f} ± {np.hypot(f_sem, c_sem):.3f}" in line
    leads = "neither" if abs(f - c) <= 2 * np.hypot(f_sem, c_sem) else ("free-energy" if f > c else "linear")
    assert {"neither": "neither leads", "free-energy": "the free-energy head leads", "linear": "the linear head leads"}[
        leads
    ] in line
    family = next(x for x in report.splitlines() if x.startswith("**Free-energy family:**"))
    ours = ("maze", "maze_memoryless", "maze_free_energy")  # the free-energy actor, or the free-energy head
    best = max(ours, key=lambda n: tuple(np.mean(summaries[n]["metrics"][m]) for m in RANKED))
    label = {"maze": "dissertation agent", "maze_memoryless": "predictor=none", "maze_free_energy": "actor=recurrent_q"}
    assert family.startswith(f"**Free-energy family:** its best, {label[best]}")


def test_a_random_policy_is_not_labelled_as_memoryless_ferl():
    """β = 0 throughout (run.json's actor.beta) is its own agent: without it, a β = 0 run and
    memoryless FERL were both `predictor=none`. A run recorded before `beta` keeps its label."""
    from reproduction.variants import RANDOM_POLICY, agent

    def memoryless(**actor):
        env = {"kind": "tmaze", "episodic": True}
        trainer = {"kind": "phased"}
        return Manifest("tmaze", "x", trainer, env, None, {}, {"kind": "free_energy", **actor})

    assert agent(memoryless(beta={"start": 0.0, "end": 10.0})) == "predictor=none"
    assert agent(memoryless()) == "predictor=none"
    assert agent(memoryless(beta={"start": 0.0, "end": 0.0})) == f"predictor=none, {RANDOM_POLICY}"
    assert RANDOM_POLICY == "β=0 (random policy)"


def test_means_equal_but_for_float32_rounding_name_no_leader():
    """A return of 1 in every final episode of every run, summed in float32 (0.99999994 against
    1.0, both s.e.m. 0): the finding compares on the first metric, finds no difference and names
    no leader; a real difference on a later metric is the one compared."""
    from reproduction.variants import difference, verdict

    ones = {"solved": (1.0, 0.0, 10), "final_return": (1.0, 0.0, 10)}
    rounded = {"solved": (1.0, 0.0, 10), "final_return": (float(np.float32(0.99999994)), 0.0, 10)}
    metric, diff, sem = difference(ones, rounded)
    assert (metric, diff, sem) == ("solved", 0.0, 0.0)
    assert verdict(diff, sem, "a", "b") == "within two s.e.m.: neither leads"
    behind = {"solved": (1.0, 0.0, 10), "final_return": (0.9, 0.03, 10)}
    metric, diff, sem = difference(ones, behind)
    assert metric == "final_return" and diff == pytest.approx(0.1) and sem == pytest.approx(0.03)
    assert verdict(diff, sem, "a", "b") == "a leads"
