"""The free-energy family side by side: does the free-energy value form help when the memory is
learnt for reward? (docs/beyond.md, "The free-energy family side by side").

Agents (the rows): FERL as each task's experiment sets it (its memory learnt to predict the next
observation); FERL trained online with the actor's TD error also stepping the predictors' memory
(``trainer.td_to_memory``, λ = ``TD_TO_MEMORY``); the recurrent Q-learner (``actor=recurrent_q
predictor=none``: a GRU core learnt for reward) with each value head, ``linear`` (DRQN),
``free_energy`` (Q = −F, the dissertation's RBM on the core's h_t), ``expected_energy`` and
``scaled_free_energy``; and, where sb3-contrib is installed, RecurrentPPO on the tasks where
``make baselines`` and ``make suites`` ran it.

Tasks (the columns): the matching maze, the pixel maze, the passive T-maze at L = 50, POPGym's
four Easy tasks and MiniGrid's MemoryS7. On a task every agent gets the same episodes.

Two stages, each in its own folder under ``out``:

* ``tune``: every ferl agent gets the baselines' Optuna budget (``hparams_search=matching_optuna``:
  24 trials, 8 random then TPE, sampler seed 0; 2 runs × ``TUNE_EPISODES`` episodes a trial) over
  the actor's step size and β's end on the tuning task, the regular T-maze at corridor 5, which is
  no test task. Adam's step size (the recurrent Q-learner) has its own range, as in the baselines'
  search. ``tune/<agent>/optimization_results.yaml`` holds each agent's best values.
* ``test``: 10 runs of every agent on every task with its tuned values, ``--jobs`` at a time, then
  ``analyze.py`` on ``test/``: its report's "Agents side by side" section has a table, the finding
  of which agent leads and a learning-curve figure per task.

A study or job that has finished is not run again, so an interrupted stage continues where it
stopped when given the same folder: a study's finished trials are kept in its ``study.db`` and its
interrupted trial runs again (docs/sweeps.md, "The study database"); ``optimization_results.yaml``
is written when the whole study is over.

    python baselines/family.py outputs/family/NAME [--stage tune|test|all] [--jobs 2] [--only SUBSTRING,…]
"""

import sys
from pathlib import Path

import suites
import yaml
from side_by_side import ROOT, arguments, run_commands, run_table
from side_by_side import ppo_jobs as baselines_ppo_jobs

TD_TO_MEMORY = 1.0  # λ: the value that moved the memory as far as the replay's own steps (docs/beyond.md)
ALONE = ["trainer=algorithm1", "predictor=none"]  # the actor phase alone: the core is the actor's own
HEADS = ("linear", "free_energy", "expected_energy", "scaled_free_energy")
AGENTS = {
    "ferl": [],
    "ferl_td": ["trainer=online", f"trainer.td_to_memory={TD_TO_MEMORY}"],
    **{f"rq_{head}": [*ALONE, "actor=recurrent_q", f"actor.head={head}"] for head in HEADS},
}
ADAM_RANGE = "actor.lr.value=tag(log, interval(0.0003, 0.03))"  # the baselines' search for DRQN's Adam
TUNING_TASK = ["experiment=table4_1_regular", "env.corridor_length=5", "env.max_steps=14"]
TUNE_EPISODES = 3000
# task → (train.py overrides, episodes per run); the passive maze's T_max = 51 episode runs eagerly:
# compiling it takes longer than the job (docs/performance.md)
TASKS = {
    "matching": (["experiment=table4_1_matching"], 10000),
    "pixel": (["experiment=table5_1_pixel"], 10000),
    "passive50": (["experiment=passive_tmaze", "env.corridor_length=50", "compile=false"], 10000),
    **{e.split("_", 1)[1]: ([f"experiment={e}"], episodes) for e, (episodes, _) in suites.EPISODES.items()},
}


def tune_command(agent: str, out: Path) -> list[str]:
    """One agent's Optuna study on the tuning task: a train.py multirun into ``out/tune/<agent>``."""
    ranges = [ADAM_RANGE] if agent.startswith("rq_") else []
    return [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        "hparams_search=matching_optuna",
        *TUNING_TASK,
        *AGENTS[agent],
        *ranges,
        "n_runs=2",
        f"trainer.n_episodes={TUNE_EPISODES}",
        f"hydra.sweeper.study_name=family_{agent}",
        f"hydra.sweep.dir={out / 'tune' / agent}",
    ]


def study_results(agent: str, out: Path) -> Path:
    """Where an agent's finished study leaves its best values (the sweeper writes it at the end only)."""
    return out / "tune" / agent / "optimization_results.yaml"


def tuned(agent: str, out: Path) -> list[str]:
    """The overrides an agent's finished study chose."""
    results = study_results(agent, out)
    if not results.exists():
        sys.exit(f"family: {results} is missing: run --stage tune first")
    return [f"{key}={value}" for key, value in yaml.safe_load(results.read_text())["best_params"].items()]


def train_jobs(choose=lambda agent: []) -> dict[str, list[str]]:
    """Job name ``<task>/<agent>`` → train.py overrides, each agent's tuned values (``choose``) last."""
    return {
        f"{task}/{agent}": [*overrides, *AGENTS[agent], f"trainer.n_episodes={episodes}", *choose(agent)]
        for task, (overrides, episodes) in TASKS.items()
        for agent in AGENTS
    }


def ppo_jobs() -> dict[str, list[str]]:
    """RecurrentPPO where it ran before: the matching maze (make baselines) and the suites."""
    matching = {name: args for name, args in baselines_ppo_jobs().items() if name == "ppo/matching"}
    return matching | suites.ppo_jobs()


def tune(out: Path, jobs: int, only: str) -> int:
    """Every agent's study not yet finished, ``jobs`` studies at a time; 1 if any failed."""
    todo = {
        agent: tune_command(agent, out)
        for agent in AGENTS
        if any(part in agent for part in only.split(",")) and not study_results(agent, out).exists()
    }
    return 1 if run_commands(todo, out / "tune", jobs, what="studies") else 0


def main() -> int:
    args = arguments(__doc__, stages=("tune", "test", "all"))
    if args.stage in ("tune", "all") and tune(args.out, args.jobs, args.only):
        return 1
    if args.stage == "tune":
        return 0
    trains = train_jobs(lambda agent: tuned(agent, args.out))
    return run_table(args.out / "test", trains, ppo_jobs(), args.jobs, args.only)


if __name__ == "__main__":
    sys.exit(main())
