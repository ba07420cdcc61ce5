"""ferl's agents on third-party POMDPs (docs/beyond.md, "Outside POMDPs"; `make suites`): every agent on every environment
of the suites, ``--jobs`` at a time, then ``analyze.py`` on the folder; its report's "Agents side
by side" section has one table and one learning-curve figure per environment.

Environments (experiments of conf/experiment/, each through ``env=gymnasium``): POPGym's RepeatPreviousEasy,
CountRecallEasy, AutoencodeEasy and MineSweeperEasy (Morad et al., ICLR 2023) and MiniGrid's
MemoryS7 (Chevalier-Boisvert et al. 2023). Agents: FERL trained online (§5.4) on an LSTM predictor
(the experiments' own config), the same with the MLP Q-network (``actor=mlp_q``), memoryless FERL
(``predictor=none``) and DRQN (``actor=drqn predictor=none``), both under Algorithm 1's actor
phase alone. Every agent gets the same number of episodes (``EPISODES``). There is no oracle: a
third-party environment does not expose its state.

RecurrentPPO (sb3-contrib, ``.[baselines]``) on the same encoded observations, at POPGym's own
discount 0.99, for the environment steps the ferl agents took (3 runs on MiniGrid, ``PPO_RUNS``:
the budget), is a reference of its own (``--reference``, `make suites-reference`): a sweep of ferl's
agents copies the newest reference's jobs in before its analysis, and its report names that
reference's folder, date and commit (``reference.py``).

    python baselines/suites.py outputs/suites/NAME [--jobs 2] [--only SUBSTRING,…]
    python baselines/suites.py outputs/suites_reference/NAME --reference [--jobs 2]
"""

import importlib.util
import sys

import reference
from side_by_side import ROOT, arguments, run_table

REFERENCES = ROOT / "outputs" / "suites_reference"  # make suites-reference's sweeps

# experiment → (episodes per run, environment steps per episode for PPO's budget: the fixed
# episode length, or MiniGrid's mean over the ferl agents' episodes at this budget, rounded)
EPISODES = {
    "popgym_repeat_previous_easy": (1000, 51),
    "popgym_count_recall_easy": (1000, 51),
    "popgym_autoencode_easy": (500, 103),
    "popgym_minesweeper_easy": (1000, 8),
    "minigrid_memory_s7": (200, 200),
}
# RecurrentPPO's runs (one after another in one process, ~390 steps/s on POPGym, ~100 on MiniGrid):
# 10 runs of MiniGrid's 40 000 steps alone would take ~65 min, beyond make suites' 90
PPO_RUNS = {"minigrid_memory_s7": 3}
ALONE = ["trainer=algorithm1"]  # the actor phase alone: no predictor to train (trainer=online needs one)
PPO_GAMMA = 0.99  # POPGym's PPO (popgym/baselines/ppo.py)


def train_jobs() -> dict[str, list[str]]:
    """Job name → train.py overrides, the longest environments first."""
    jobs = {}
    for experiment, (episodes, _) in sorted(EPISODES.items(), key=lambda kv: -kv[1][0] * kv[1][1]):
        task, run = experiment.split("_", 1)[1], [f"experiment={experiment}", f"trainer.n_episodes={episodes}"]
        jobs |= {
            f"{task}/ferl": run,
            f"{task}/mlp_q": [*run, "actor=mlp_q"],
            f"{task}/memoryless": [*run, *ALONE, "predictor=none"],
            f"{task}/drqn": [*run, *ALONE, "actor=drqn", "predictor=none"],
        }
    return jobs


def ppo_jobs() -> dict[str, list[str]]:
    """RecurrentPPO on each environment, where sb3-contrib is installed."""
    if importlib.util.find_spec("sb3_contrib") is None:
        print("sb3-contrib is not installed (pip install -e '.[baselines]'): no RecurrentPPO reference")
        return {}
    from hydra import compose, initialize_config_dir

    jobs = {}
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        for experiment, (episodes, steps) in EPISODES.items():
            env = compose("config", overrides=[f"experiment={experiment}"]).env
            jobs[f"ppo/{experiment.split('_', 1)[1]}"] = [
                "--env-id",
                env.id,
                "--runs",
                str(PPO_RUNS.get(experiment, 10)),
                "--steps",
                str(episodes * steps),
                "--gamma",
                str(PPO_GAMMA),
                "--experiment",
                experiment,
                *(["--optimal-return", str(env.optimal_return)] if env.optimal_return is not None else []),
                *(["--success-threshold", str(env.success_threshold)] if env.success_threshold is not None else []),
            ]
    return jobs


def main() -> int:
    args = arguments(__doc__, flags={"--reference": "RecurrentPPO's reference alone (make suites-reference)"})
    if args.reference:
        ppos = ppo_jobs()
        return run_table(args.out, {}, ppos, args.jobs, args.only, first=0, analyze=False) if ppos else 1
    copy_reference = lambda out: reference.copy_newest(out, REFERENCES)  # noqa: E731
    return run_table(args.out, train_jobs(), {}, args.jobs, args.only, first=0, before_analysis=copy_reference)


if __name__ == "__main__":
    sys.exit(main())
