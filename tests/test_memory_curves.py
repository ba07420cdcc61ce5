"""The memory curves (reproduction/curves.py) against numbers known by construction: a synthetic
sweep of passive and active T-maze runs whose final-window outcomes are fixed per run (solved
share, success rate, share that got to the choice, each line's limit and its cause), the passive
maze's "on schedule" rule against the environment itself, and `make beyond`'s curve sweeps run
with a stub for Python (what each train.py call gets from the Makefile's variables)."""

import csv
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import ROOT
from ferl.analysis.report import RunOutcome
from ferl.analysis.sweep import Job
from ferl.trainers.episodes import discount_factors, discounted_return
from reproduction import curves
from test_passive_tmaze import all_sequences, passive, roll

WINDOW, EARLY, GOAL, GAMMA = 20, 7, 5.0, 0.95


@pytest.mark.parametrize("L", [2, 3])
def test_passive_on_schedule_iff_the_return_is_not_negative(L):
    """Every action sequence of the real passive maze: the recorded discounted return is ≥ 0
    exactly when the first L actions all moved toward the junction (N), and every episode that
    ends in the cued goal is one of those."""
    actions = all_sequences(L)
    env = passive(len(actions), L, goal=GOAL)
    cues = torch.randint(2, (len(actions),), generator=torch.Generator().manual_seed(L))
    rewards = roll(env, cues, actions)[1]  # (R, L + 1)
    G = discounted_return(discount_factors(GAMMA, L + 1), rewards.T).numpy()
    on_schedule = (actions[:, :L] == 0).all(1).numpy()
    got = curves.got_to_choice({"discounted_return": G[:, None], "terminal_reward": None}, {"passive": True})
    np.testing.assert_array_equal(got[:, 0], on_schedule)
    assert on_schedule[env.correct.numpy()].all() and 0 < on_schedule.sum() < len(actions)


def test_passive_late_slip_on_a_long_corridor_still_counts():
    """L = 200: one step off schedule at the last corridor step costs −g/L·γ^(L−1) ≈ −10⁻⁶, still < 0."""
    L = 200
    actions = torch.zeros(2, L + 1, dtype=torch.long)
    actions[:, L] = 1  # E from the junction: a goal
    actions[1, L - 1] = 2  # run 1 steps back (S) at the L-th action
    rewards = roll(passive(2, L, goal=GOAL), torch.tensor([1, 1]), actions)[1]
    G = discounted_return(discount_factors(GAMMA, L + 1), rewards.T).numpy()
    got = curves.got_to_choice({"discounted_return": G[:, None], "terminal_reward": None}, {"passive": True})
    assert got[:, 0].tolist() == [True, False] and G[1] < 0


def episode_records(counts: np.ndarray, passive: bool, L: int, rng) -> dict:
    """Episodes (R, EARLY + WINDOW) whose final window has, per run, counts[r] = (correct, wrong
    choice, never got there) episodes in a random order; the EARLY ones before it never got there."""
    kinds = np.stack([rng.permutation(np.repeat([0, 1, 2], c)) for c in counts])  # (R, WINDOW)
    kinds = np.concatenate([np.full((len(counts), EARLY), 2), kinds], 1)
    if passive:  # correct: γ^L g; wrong goal / stayed: 0; behind: a penalty, nothing after
        ret = np.choose(kinds, [GAMMA**L * GOAL, 0.0, -GOAL / L * GAMMA ** (L - 1)])
        terminal = np.where(kinds == 0, GOAL, 0.0)
    else:  # correct: +g; wrong goal: −g; time out on the corridor: the step reward
        ret = np.choose(kinds, [1.0, -1.0, -2.0])
        terminal = np.choose(kinds, [GOAL, -GOAL, -0.1])
    return {
        "discounted_return": ret.astype(np.float32),
        "terminal_reward": terminal.astype(np.float32),
        "correct_goal": kinds == 0,
        "final_window": np.int64(WINDOW),
    }


def make_job(root: Path, name: str, design: dict, rng) -> Job:
    """A synthetic online T-maze job (records/run.json, episodes.npz) and its summary; its outcome
    per run is design["counts"] (R, 3) and its solved runs the first design["solved"]."""
    run_dir = root / name
    (run_dir / "records").mkdir(parents=True)
    counts = design["counts"]
    manifest = {
        "task": "tmaze",
        "experiment": "whatever_the_name",  # the curves read the facts below, never the name
        "trainer": {"kind": design.get("trainer", "online"), "final_window": WINDOW},
        "env": {
            "kind": "tmaze",
            "passive": design["passive"],
            "matching": design.get("matching", False),
            "corridor_length": design["corridor"],
            "goal_reward": GOAL,
        },
        "predictors": {"joint": {"kind": design["memory"]}},
        "actor": {"kind": "free_energy"},
    }
    if design["memory"].startswith("recurrent_q "):  # an actor with its own memory, no predictor
        core = design["memory"].split()[1]
        manifest |= {"predictors": {}, "actor": {"kind": "recurrent_q", "memory": core, "head": "linear"}}
    if design["exploration"] != "none":
        manifest["exploration"] = {"kind": design["exploration"]}
    (run_dir / "records" / "run.json").write_text(json.dumps(manifest))
    np.savez(
        run_dir / "records" / "episodes.npz", **episode_records(counts, design["passive"], design["corridor"], rng)
    )
    solved = [r < design["solved"] for r in range(len(counts))]
    summary = {"experiment": "x", "metrics": {"solved": solved, "final_correct_goal_rate": list(counts[:, 0] / WINDOW)}}
    negative = not design["passive"] and design["corridor"] >= NEGATIVE_OPTIMUM_FROM
    summary["optimal"] = {"discounted_return": -1.284 if negative else 1.8}
    return Job(RunOutcome(run_dir, "x", "tmaze", "analyzed"), summary)


def outcomes(rng, n_runs: int, reach: float) -> np.ndarray:
    """(R, 3) counts (correct, wrong, never) per run over WINDOW episodes, about ``reach`` got there."""
    got = rng.binomial(WINDOW, reach, n_runs)
    correct = rng.binomial(got, 0.7)
    return np.stack([correct, got - correct, WINDOW - got], 1)


# (passive, memory, exploration) → corridor → (solved runs of 5, share that gets to the choice)
DESIGN = {
    (True, "lstm", "none"): {10: (5, 0.95), 20: (4, 0.9), 50: (1, 0.9)},  # limit 20: memory
    (True, "gru", "none"): {10: (3, 0.9), 20: (4, 0.9), 50: (0, 0.1)},  # limit 20 (10 failed): exploration
    (True, "elman", "none"): {10: (0, 0.2), 20: (0, 0.0)},  # none: exploration at 10
    (False, "gru", "none"): {5: (5, 1.0)},  # limit 5, nothing failed
    (False, "gru", "ez_greedy"): {5: (4, 0.95), 10: (2, 0.8)},  # limit 5: memory
    (True, "recurrent_q lstm", "none"): {50: (5, 1.0), 100: (2, 0.9)},  # its own memory, phased: limit 50
    (False, "lstm", "ez_greedy"): {10: (5, 1.0), 50: (0, 0.9)},  # 50: a negative optimum, no limit set there
}
NEGATIVE_OPTIMUM_FROM = 50  # the active maze's optimal return is negative from this corridor on (as at γ 0.98)
LIMITS = {
    (True, "lstm", "none"): (20, 50, "memory"),
    (True, "gru", "none"): (20, 50, "exploration"),
    (True, "elman", "none"): (None, 10, "exploration"),
    (False, "gru", "none"): (5, None, None),
    (False, "gru", "ez_greedy"): (5, 10, "memory"),
    (True, "recurrent_q lstm", "none"): (50, 100, "memory"),
    (False, "lstm", "ez_greedy"): (10, None, None),
}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root, rng = tmp_path_factory.mktemp("curves"), np.random.default_rng(0)
    designs = [
        {"passive": p, "memory": m, "exploration": x, "corridor": c, "solved": s, "counts": outcomes(rng, 5, reach)}
        for (p, m, x), points in DESIGN.items()
        for c, (s, reach) in points.items()
    ]
    # not on either curve: a matching maze and a phased passive job
    others = [
        {**designs[0], "matching": True, "passive": False},
        {**designs[0], "trainer": "phased"},
    ]
    for d in designs:  # the recurrent Q-learner learns its memory under a phased trainer
        d["trainer"] = "phased" if d["memory"].startswith("recurrent_q") else "online"
    jobs = [make_job(root, f"job{i}", d, rng) for i, d in enumerate(designs + others)]
    out, figures, data_files = root / "analysis", {}, []
    out.mkdir()
    lines = curves.report(jobs, out, figures, data_files)
    return designs, out, figures, data_files, lines, jobs


def rows(path: Path) -> list[list[str]]:
    with open(path) as f:
        return list(csv.reader(f))[1:]


@pytest.mark.parametrize("curve", [curves.PASSIVE, curves.ACTIVE])
def test_curve_numbers_match_the_design(synthetic, curve):
    designs, out, figures, data_files, _, _ = synthetic
    mine = sorted(
        (d for d in designs if d["passive"] == curve.passive),
        key=lambda d: (d["memory"], d["exploration"] != "none", d["corridor"]),
    )
    got = rows(out / f"{curve.name}.csv")
    assert [(r[0], r[1], int(r[2])) for r in got] == [(d["memory"], d["exploration"], d["corridor"]) for d in mine]
    for r, d in zip(got, mine):
        correct, wrong, _ = d["counts"].T
        reached = correct + wrong
        assert (int(r[3]), int(r[4])) == (d["solved"], 5)
        assert float(r[5]) == pytest.approx(np.mean(correct / WINDOW), abs=1e-5)  # success rate
        assert float(r[7]) == pytest.approx(np.mean(reached / WINDOW), abs=1e-5)  # got to the choice
        given = [c / n for c, n in zip(correct, reached) if n]  # none: the elman line at 20 never gets there
        assert float(r[9]) == pytest.approx(np.mean(given), abs=1e-5) if given else np.isnan(float(r[9]))
    assert curve.name in figures and f"{curve.name}.csv" in data_files


def test_each_lines_limit_and_its_cause(synthetic):
    _, _, _, _, lines, jobs = synthetic
    for curve in (curves.PASSIVE, curves.ACTIVE):
        for (memory, exploration), mine in curves.lines_of(curves.curve_points(jobs, curve)).items():
            lim = curves.limit(mine)
            want = LIMITS[(curve.passive, memory, exploration)]
            assert (lim.longest, lim.failed and lim.failed.corridor, lim.cause) == want
    text = "\n".join(lines)
    assert "**lstm**: limit 20 (" in text and "limited by **memory**" in text
    assert "**elman**: limit none (" in text and "**gru + ez_greedy**: limit 5 (" in text
    assert "**recurrent_q lstm**: limit 50 (" in text
    assert "**lstm + ez_greedy**: limit 10 (" in text and "`solved` cannot be met at 50" in text
    assert text.count("cannot be met") == 2  # the line's words and its table row at 50, nowhere else
    assert "no per-length success numbers" in text  # Ni et al.: said, not drawn


def test_the_solved_share_rule_is_eight_in_ten():
    """≥ 80 % of the runs: 8/10 and 4/5 are within a limit, 7/10 and 3/5 are not."""
    point = lambda solved, n: curves.CurvePoint("m", "none", 1, solved, n, (0, 0), (0, 0), (0, 0), None)  # noqa: E731
    assert [point(*x).ok for x in ((8, 10), (7, 10), (4, 5), (3, 5))] == [True, False, True, False]


# a stub Python: records its arguments; as ``ferl.run.sweepdir`` it names the sweep folder
STUB = """#!/bin/sh
printf '%s\t' "$@" >> "$CALLS" && echo >> "$CALLS"
if [ "$2" = ferl.run.sweepdir ]; then mkdir -p sweep && echo sweep; fi
"""


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_make_beyond_runs_each_curve_from_its_variables(tmp_path):
    """`make beyond` with a stub Python: the sweep folder named (``ferl.run.sweepdir``), then one
    queue (``ferl.run.together --lanes``) of one sweep per corridor of each list, the recurrent
    Q-learner's first, with its memories, exploration, episodes and runs (fewer from
    BEYOND_LONG_FROM on), then analyze.py."""
    stub = tmp_path / "py"
    stub.write_text(STUB)
    stub.chmod(0o755)
    overrides = {
        "PY": str(stub),
        "STAMP": "",
        "BEYOND_EFFICIENCY": "",
        "BEYOND_CORRIDORS": "5 3",
        "MEMORIES": "gru",
        "BEYOND_EXPLORE_CORRIDORS": "7",
        "BEYOND_EXPLORE_MEMORIES": "lstm,gru",
        "BEYOND_EXPLORATION": "ez_greedy,count_bonus",
        "BEYOND_PASSIVE_CORRIDORS": "10 300",
        "BEYOND_PASSIVE_MEMORIES": "elman,esn",
        "BEYOND_PASSIVE_EPISODES": "123",
        "BEYOND_EPISODES": "45",
        "BEYOND_RUNS": "3",
        "BEYOND_LONG_RUNS": "2",
        "BEYOND_Q_CORRIDORS": "60",
        "BEYOND_Q_MEMORIES": "gru",
        "BEYOND_Q_EPISODES": "77",
        "BEYOND_Q_BETA": "9",
    }
    make = ["make", "-s", "-f", str(ROOT / "Makefile"), "beyond", *(f"{k}={v}" for k, v in overrides.items())]
    env = {**os.environ, "CALLS": str(tmp_path / "calls")}
    done = subprocess.run(make, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    calls = [line.rstrip("\t").split("\t") for line in (tmp_path / "calls").read_text().splitlines()]
    active = "experiment=table4_1_regular trainer=online trainer.n_episodes=45 trainer.replay_sample=16 n_runs=3"
    want = [
        {*active.split(), "predictor.joint.memory=gru", f"env.corridor_length={c}", f"env.max_steps={2 * c + 4}"}
        for c in (5, 3)
    ]
    want.append(
        {
            *active.split(),
            "predictor.joint.memory=lstm,gru",
            "exploration=ez_greedy,count_bonus",
            "env.corridor_length=7",
            "env.max_steps=18",
        }
    )
    want += [
        {
            "experiment=passive_tmaze",
            "predictor.joint.memory=elman,esn",
            f"env.corridor_length={c}",
            "trainer.n_episodes=123",
            f"n_runs={runs}",
        }
        for c, runs in ((10, 3), (300, 2))  # BEYOND_LONG_FROM = 200: fewer runs at 300
    ]
    want.append(
        {
            *[
                "experiment=passive_tmaze",
                "trainer=algorithm1",
                "predictor=none",
                "actor=recurrent_q",
                "actor.head=linear",
            ],
            *["actor.memory=gru", "actor.beta.end=9", "env.corridor_length=60", "trainer.n_episodes=77", "n_runs=3"],
        }
    )
    assert set(calls[0]) >= {"-m", "ferl.run.sweepdir", "beyond"}
    assert len(calls) == 3 and "analyze.py" in calls[2] and "sweep" in calls[2]
    assert calls[1][:5] == ["-m", "ferl.run.together", "--lanes", "2", "sweep"]
    specs = [spec.split() for spec in calls[1][5:]]
    assert [(name, jobs) for name, jobs, *_ in specs] == [
        (name, "1")
        for name in (
            "passive_q_curve/corridor_60",
            "passive_curve/corridor_10",
            "passive_curve/corridor_300",
            "memory_length/corridor_5",
            "memory_length/corridor_3",
            "exploration_curve/corridor_7",
        )
    ]
    q, *rest = [set(overrides) for _, _, *overrides in specs]
    assert [q, *rest] == [want[-1], *want[3:5], *want[:3]]
