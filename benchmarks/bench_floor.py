"""Agent-steps per second of the digit-floor actor phase: batched torch vs the NumPy reference.

    python benchmarks/bench_floor.py [--steps 2000] [--runs 1 10 100 1000] [--device cpu]

Each configuration steps at least MIN_AGENT_STEPS agent-steps (up to MAX_STEPS steps), so small
batches are timed over ~1 s of stepping, not a tenth of one; the NumPy reference runs MAX_STEPS.

Both sides run the same algorithm (§3.2–3.5, SARSA(0) on the default floor) in one invocation;
agent-steps/s = environment steps summed over runs / wall time of the step loop. The torch side
runs eagerly and with `compile=true` (on a CPU by groups of trainer.compile_group_runs runs);
each actor phase runs twice and the second is timed, so the compiled rate excludes compilation,
whose time (the first run's extra seconds) is reported beside it: warm once inductor's on-disk
cache holds the graphs, cold with TORCHINDUCTOR_CACHE_DIR=$(mktemp -d). Prints a table and writes
benchmarks/results.json.
"""

import argparse
import os
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import bench_job, phase  # noqa: E402
from benchmarks.numpy_reference import run_numpy_reference  # noqa: E402
from benchmarks.report import save_results, speedup_table  # noqa: E402
from ferl.data import MnistEmbedded  # noqa: E402

MIN_AGENT_STEPS = 200_000
MAX_STEPS = 20_000  # a multiple of the 16-step chunk
GROUP_RUNS = OmegaConf.load(ROOT / "conf" / "trainer" / "digit_floor.yaml").compile_group_runs


def torch_actor_phase(runs: int, steps: int, device: str, compiled: bool) -> dict:
    """Agent-steps/s of the online TD phase (ferl/trainers/continuing_td.py; the TD phase only, as in
    summary.json), timed on a second pass over the same job; and the seconds the first pass took
    beyond the second."""
    overrides = [
        f"n_runs={runs}",
        f"trainer.steps={steps}",
        "trainer.test_per_class=1",
        f"trainer.log_every={steps}",
        f"trainer.checkpoint_every={steps}",
        "experiment=ch3_floor",
        f"compile={str(compiled).lower()}",
    ]
    with bench_job(overrides, device) as (trainer, job):
        online = phase(trainer, "continuing_td")
        state = online.fresh_state(job)
        seconds = []
        for _ in range(2):
            state["step"] = 0
            start = time.perf_counter()
            online.train(job, state)
            if device == "cuda":
                torch.cuda.synchronize()
            seconds.append(time.perf_counter() - start)
    return {
        "runs": runs,
        "steps": steps,
        "compile": compiled,
        "agent_steps_per_s": runs * steps / seconds[1],
        "first_pass_extra_s": seconds[0] - seconds[1],
    }


def steps_for(runs: int, steps: int) -> int:
    """Steps to time ``runs`` runs for: at least ``steps``, and MIN_AGENT_STEPS over the batch."""
    return max(steps, min(MAX_STEPS, MIN_AGENT_STEPS // runs))


def numpy_reference(steps: int) -> float:
    split = MnistEmbedded().load()
    images = {c: split.train_images[split.train_labels == c].numpy() for c in range(10)}
    return run_numpy_reference(images, steps=steps, seed=0, init_std=0.1)["steps_per_s"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 10, 100, 1000])
    parser.add_argument("--compile", choices=["both", "false", "true"], default="both")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    reference = numpy_reference(max(args.steps, MAX_STEPS))
    modes = {"both": [False, True], "false": [False], "true": [True]}[args.compile]
    rows = [torch_actor_phase(r, steps_for(r, args.steps), args.device, c) for r in args.runs for c in modes]
    print(
        f"digit floor actor phase, ≥ {args.steps} steps and ≥ {MIN_AGENT_STEPS} agent-steps, device={args.device}, torch threads={args.threads}, "
        f"compile=true by groups of {GROUP_RUNS} runs on a CPU, load average {os.getloadavg()[0]:.2f}"
    )
    print(f"NumPy per-step reference (1 run): {reference:10.0f} agent-steps/s")
    speedup_table(
        rows,
        "agent_steps_per_s",
        reference,
        [
            ("runs", "runs", "d"),
            ("steps", "steps", "d"),
            ("compile", "compile", "d"),
            ("1st-pass +s", "first_pass_extra_s", ".1f"),
        ],
    )
    save_results(
        args.out,
        "floor_actor",
        args.device,
        steps=args.steps,
        numpy_reference_steps_per_s=reference,
        compile_group_runs=GROUP_RUNS,
        torch=rows,
    )


if __name__ == "__main__":
    main()
