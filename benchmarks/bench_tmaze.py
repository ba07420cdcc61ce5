"""Agent-steps per second of the T-maze actor phase: batched torch vs the NumPy reference.

    python benchmarks/bench_tmaze.py [--episodes 500] [--runs 1 10 100 1000] [--device cpu] [--threads 1] [--eager]

The torch side is the actor phase of ``ferl/trainers/actor_episodes.py`` itself (ActorEpisodes.run,
experiment table4_1_matching: matching T-maze, T_min = 3, joint Elman predictor whose memory is
stepped every step, FERL actor, SARSA(0)), with the predictor left at its random initialisation:
the forward passes cost the same whether or not it was trained.  agent-steps/s is the trainer's
own figure (summary.json ``agent_steps_per_s``): environment steps summed over runs / wall time
of the episode loop, the compiled graph's first call (its compilation, or its load from the
cache) left out; runs wait in lockstep for the slowest episode of the batch, and that waiting is
part of the time (a compiled episode always plays T_max steps, the ended ones masked).
``--eager``: the eager path, which stops when every run has ended.  Large batches play fewer episodes (``--episodes`` × 10 / runs, at least
``--min-episodes``) to keep the benchmark short; the β schedule is compressed accordingly.
With 1000 runs a few seeds trip the divergence guard in their first episodes (stderr lines
"ferl: run … diverged"); the guard freezes them and the timing goes on unchanged.

The NumPy side (benchmarks/numpy_tmaze_reference.py) is the same algorithm for one run with one
Python iteration per step, measured in the same invocation.  Prints a table and merges it into
benchmarks/results.json under "tmaze_actor" ("tmaze_actor_eager" with ``--eager``; other entries
are kept).
"""

import os

os.environ.setdefault("TQDM_DISABLE", "1")  # the trainer's progress bar; tqdm reads TQDM_* when imported

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import bench_job, phase  # noqa: E402
from benchmarks.numpy_tmaze_reference import run_numpy_tmaze_reference  # noqa: E402
from benchmarks.report import save_results, speedup_table  # noqa: E402

EXPERIMENT = "table4_1_matching"


def episodes_for(runs: int, episodes: int, min_episodes: int) -> int:
    return max(min_episodes, min(episodes, episodes * 10 // runs))


def torch_actor_phase(runs: int, episodes: int, device: str, fused: bool) -> dict:
    """The actor phase (ferl/trainers/actor_episodes.py) with a random joint predictor; the
    trainer's agent-steps/s."""
    overrides = [
        f"experiment={EXPERIMENT}",
        f"compile={str(fused).lower()}",
        f"n_runs={runs}",
        f"trainer.n_episodes={episodes}",
        f"trainer.log_every={episodes}",
        f"trainer.checkpoint_every={episodes}",
        f"trainer.td_sample_every={episodes}",
        f"trainer.final_window={episodes}",
    ]
    with bench_job(overrides, device) as (trainer, job):
        phase(trainer, "actor").run(job, None)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
    steps, seconds = job.progress["agent_steps"], job.progress["actor_time"]
    return {
        "runs": runs,
        "episodes": episodes,
        "agent_steps": steps,
        "wall_time_s": seconds,
        "agent_steps_per_s": steps / seconds,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=500, help="episodes per run for runs ≤ 10")
    parser.add_argument("--min-episodes", type=int, default=20)
    parser.add_argument("--numpy-episodes", type=int, default=2000)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 10, 100, 1000])
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--eager", action="store_true", help="the eager path (default: compiled episodes, the fast path)"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (config cpu_threads)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    reference = run_numpy_tmaze_reference(args.numpy_episodes, seed=0)
    torch_actor_phase(1, 3, args.device, not args.eager)  # warm-up: first-call costs of torch and the trainer
    rows = [
        torch_actor_phase(r, episodes_for(r, args.episodes, args.min_episodes), args.device, not args.eager)
        for r in args.runs
    ]
    ref_rate = reference["steps_per_s"]
    print(
        f"T-maze actor phase ({EXPERIMENT}, joint predictor forward each step), "
        f"{'eager' if args.eager else 'one compiled graph an episode'}, device={args.device}, "
        f"torch threads={args.threads}, load average {load:.2f} on {os.cpu_count()} CPUs"
    )
    print(
        f"NumPy per-step reference (1 run, {args.numpy_episodes} episodes, {reference['agent_steps']} steps): "
        f"{ref_rate:10.0f} agent-steps/s"
    )
    speedup_table(
        rows,
        "agent_steps_per_s",
        ref_rate,
        [("runs", "runs", "d"), ("episodes", "episodes", "d"), ("agent-steps", "agent_steps", "d")],
    )
    save_results(
        args.out,
        "tmaze_actor" + "_eager" * args.eager,
        args.device,
        experiment=EXPERIMENT,
        predictor="random (untrained) joint",
        numpy_reference={
            "episodes": args.numpy_episodes,
            "agent_steps": reference["agent_steps"],
            "agent_steps_per_s": ref_rate,
        },
        torch=rows,
    )


if __name__ == "__main__":
    main()
