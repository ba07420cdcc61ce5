"""Where the limit is: the arithmetic each phase of a run must do, the machine's rate, the fraction achieved.

    python benchmarks/limits.py SWEEP_DIR [--seconds 2]

For every run of SWEEP_DIR (a ``make reproduce`` sweep's ``experiments/``, or any folder of runs),
from its own records (``records/run.json`` sizes, ``episodes.npz`` / ``steps.npz`` steps,
``summary.json`` ``phase_time_s``) and its config, with the collected training sequences counted
by re-running its collect phase (a second or so):

* useful FLOPs of each phase, counted per run and summed over runs (the multiply-adds of the
  equations, not the padding a compiled chunk adds):
  - actor, per agent-step: Wᵀs and the rank-one update of W_sh, 4·S·H, plus the memories'
    recurrence 2·M² per predictor (§3.2, Eq. 4.3);
  - predictors, per SGD step on a sequence of T actions (In = Y + A inputs, O outputs):
    T·(4·M·In + 6·M²) + (T+1)·6·M·O (BPTT written out: forward, output deltas, ∂m, weight
    gradients), plus the forward passes of the Eq. 4.7 error measurements;
  - preprocessor, per image and sweep of CD-k: (2k + 3)·2·V·H;
* bytes the actor must move per agent-step if its weights did not stay in cache: W_sh read and
  written once, 8·S·H (its update fused with the next forward pass);
* the machine's rate: fp32 matrix products (1024², one thread) and streamed bytes (64 MiB arrays).

Prints a table (achieved GFLOP/s and fraction of the matmul rate per phase) and merges it into
benchmarks/results.json under "limits".
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import bench_job, phase  # noqa: E402
from benchmarks.report import save_results  # noqa: E402


def machine_rate(seconds: float) -> dict:
    """fp32 GFLOP/s of 1024² matrix products and GB/s of a streamed a + b → c, one thread."""
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        torch.mm(a, b)
        n += 1
    flops = 2 * 1024**3 * n / (time.perf_counter() - start)
    x, y, z = (torch.empty(1 << 24) for _ in range(3))
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        torch.add(x, y, out=z)
        n += 1
    return {"matmul_gflops": flops / 1e9, "stream_gbs": 3 * 4 * (1 << 24) * n / (time.perf_counter() - start) / 1e9}


def bptt_flops(T: np.ndarray, M: int, In: int, n_out: int) -> float:
    """One pattern-mode SGD step per sequence of T actions (the module docstring), summed."""
    return float(np.sum(T * (4 * M * In + 6 * M * M) + (T + 1) * 6 * M * n_out))


def outputs(p: dict, Y: int) -> int:
    reward = {"bits": 4, "linear": 1, "none": 0}[p["reward_output"]]
    return (Y if p["predicts_observation"] else 0) + reward


def run_flops(run: Path) -> dict:
    """FLOPs per phase of one run, and the actor's bytes per agent-step (module docstring)."""
    manifest = json.loads((run / "records" / "run.json").read_text())
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    R, env, actor, predictors = cfg.n_runs, manifest["env"], manifest["actor"], manifest["predictors"]
    pre = manifest["preprocessor"]
    Y = pre["n_hidden"] if pre else env["observation_size"]
    S = Y + sum(p["memory_size"] for p in predictors.values())
    H, A = actor["n_hidden"], env["n_actions"]
    if (run / "records" / "episodes.npz").is_file():
        with np.load(run / "records" / "episodes.npz") as ep:
            agent_steps = int(ep["steps"].sum())
    else:
        agent_steps = R * cfg.trainer.steps
    per_step = 4 * S * H + sum(2 * p["memory_size"] ** 2 for p in predictors.values())
    flops = {"actor": agent_steps * per_step}
    if pre:
        sweeps = pre["sweeps"] if isinstance(pre["sweeps"], int) else sum(pre["sweeps"])
        images = 1000  # the embedded MNIST training images (data=mnist_embedded)
        flops["preprocessor"] = R * sweeps * images * (2 * pre["cd_k"] + 3) * 2 * pre["n_visible"] * pre["n_hidden"]
    if predictors:
        flops["predictors"] = predictor_flops(manifest["experiment"], cfg, predictors, Y, A)
    return {"experiment": manifest["experiment"], "runs": R, "flops": flops, "actor_bytes_per_step": 8 * S * H}


def predictor_flops(experiment: str, cfg, predictors: dict, Y: int, A: int) -> float:
    """Every predictor's BPTT over n_epoch epochs of its training sequences (counted by running the
    collect phase of the run's config), and the Eq. 4.7 error passes (forward only, a third)."""
    overrides = [
        f"experiment={experiment}",
        f"n_runs={cfg.n_runs}",
        f"seed={cfg.seed}",
        *(f"trainer.{k}={cfg.trainer[k]}" for k in ("n_sample", "l_training", "n_epoch", "error_every")),
    ]
    with bench_job(overrides, "cpu") as (trainer, job):
        collect = [p for p in trainer.phases if p.name == "collect"]
        if not collect:  # online training: its replay steps are not counted here
            return float("nan")
        collect[0].run(job, None)
        data = job.outputs.episodes
        T_max_train = job.env.optimal_steps + phase(trainer, "predictors").l_training - 1
        train = data.train.lengths.cpu().numpy()
        trained = train[train <= T_max_train]
        every = np.concatenate([train.ravel(), data.test.lengths.cpu().numpy().ravel()])
    total = 0.0
    for p in predictors.values():
        M, n_out = p["memory_size"], outputs(p, Y)
        total += cfg.trainer.n_epoch * bptt_flops(trained, M, Y + A, n_out)
        total += (cfg.trainer.n_epoch // cfg.trainer.error_every + 1) * bptt_flops(every, M, Y + A, n_out) / 3
    return total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path)
    parser.add_argument("--seconds", type=float, default=2.0, help="timing of each machine-rate probe")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    rate = machine_rate(args.seconds)
    print(
        f"machine, one thread: {rate['matmul_gflops']:.1f} GFLOP/s (fp32 1024² matmul), "
        f"{rate['stream_gbs']:.1f} GB/s (streamed add); load average {os.getloadavg()[0]:.2f}"
    )
    print(f"{'experiment':22s} {'phase':12s} {'GFLOP':>9s} {'seconds':>8s} {'GFLOP/s':>8s} {'of matmul':>9s}")
    rows = []
    for run in sorted(p.parent for p in args.sweep.glob("*/summary.json")):
        summary = json.loads((run / "summary.json").read_text())
        counted = run_flops(run)
        for name, flops in counted["flops"].items():
            seconds = summary.get("phase_time_s", {}).get(name, float("nan"))
            achieved = flops / seconds / 1e9
            rows.append(
                {
                    "experiment": counted["experiment"],
                    "phase": name,
                    "gflop": flops / 1e9,
                    "seconds": seconds,
                    "gflops": achieved,
                    "fraction": achieved / rate["matmul_gflops"],
                    "actor_bytes_per_step": counted["actor_bytes_per_step"],
                }
            )
            print(
                f"{counted['experiment']:22s} {name:12s} {flops / 1e9:9.2f} {seconds:8.1f} {achieved:8.3f} "
                f"{achieved / rate['matmul_gflops']:9.2%}"
            )
    save_results(args.out, "limits", "cpu", sweep=str(args.sweep), machine_rate=rate, rows=rows)


if __name__ == "__main__":
    main()
