"""Sequences per second of pattern-mode BPTT (§4.3.1): batched torch vs the NumPy reference.

    python benchmarks/bench_predictor.py [--epochs 2] [--sequences 0] [--runs 1 10 100] [--device cpu] [--threads 1] [--eager]

The data are those of the trainer (experiment table4_1_matching): N_sample random-policy episodes
per run collected, balanced and split by its collect phase, of which the training lengths
T_min … T_min + L_training − 1 (3 … 7 actions) are trained on.  The torch side times
PredictorBatch.train_epoch (the joint predictor, one SGD step per sequence for every run at once,
hand-written BPTT; in compiled chunks of steps, the fast path, unless ``--eager``) for
``--epochs`` epochs after one warm-up epoch (its compilation, or its load from the cache), over
the whole training set of each run (~230 sequences with the default N_sample) or over
``--sequences`` of them, each epoch in a fresh random order; sequences/s = sequences summed over
runs / wall time.  The NumPy side (benchmarks/numpy_tmaze_reference.py, hand-written BPTT) trains
one run on the same number of run 0's sequences of a 1-run batch, in the same invocation.  Prints
a table and merges it into benchmarks/results.json under "predictor_bptt" ("predictor_bptt_eager"
with ``--eager``; other entries are kept).
"""

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import bench_job, phase  # noqa: E402
from benchmarks.numpy_tmaze_reference import JOINT, run_numpy_bptt_reference  # noqa: E402
from benchmarks.report import save_results, speedup_table  # noqa: E402
from ferl.predictors.training import PredictorBatch  # noqa: E402
from ferl.trainers.episodes import episode_tensors  # noqa: E402

EXPERIMENT = "table4_1_matching"


def training_data(runs: int, device: str):
    """The joint predictor and its training tensors y, a, r, lengths (R, N, …), as the predictor
    phase (ferl/trainers/predictor_training.py) builds them from the collected episodes."""
    with bench_job([f"experiment={EXPERIMENT}", f"n_runs={runs}"], device) as (trainer, job):
        phase(trainer, "collect").run(job, None)
    training = phase(trainer, "predictors")
    train = job.outputs.episodes.train
    trainable = train.lengths[0] <= job.env.optimal_steps + training.l_training - 1
    fit = train.select(torch.nonzero(trainable).squeeze(1).expand(runs, -1))
    predictor = job.predictors["joint"]
    return predictor, episode_tensors(job, fit, predictor), job.generator


def per_run(sequences: int, available: int) -> int:
    return available if sequences <= 0 else min(sequences, available)


def torch_bptt(runs: int, epochs: int, sequences: int, device: str, fused: bool) -> dict:
    predictor, (y, a, r, lengths), generator = training_data(runs, device)
    n = per_run(sequences, y.shape[1])
    keep = lambda x: x[:, :n]  # noqa: E731  the sequences an epoch takes (a random order of them)
    batch = PredictorBatch([predictor], keep(y), keep(a), [keep(r)], keep(lengths))
    if fused:
        batch.fuse(torch.device(device))
    orders = [torch.rand(runs, n, generator=generator, device=y.device).argsort(1) for _ in range(epochs + 1)]
    batch.train_epoch([orders[0]])  # warm-up: autograd's or the compiled graph's first call
    start = time.perf_counter()
    for order in orders[1:]:
        batch.train_epoch([order])
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    wall = time.perf_counter() - start
    return {
        "runs": runs,
        "sequences_per_run": n,
        "epochs": epochs,
        "wall_time_s": wall,
        "sequences_per_s": runs * n * epochs / wall,
    }


def numpy_bptt(epochs: int, sequences: int, device: str) -> dict:
    """A random subset (all by default) of run 0's training sequences of a 1-run batch,
    unpadded, through the NumPy reference."""
    _, (y, a, r, lengths), _ = training_data(1, device)
    pick = np.random.default_rng(0).permutation(y.shape[1])[: per_run(sequences, y.shape[1])]
    seqs = []
    for i in pick.tolist():
        T = int(lengths[0, i])
        seqs.append(tuple(x[0, i, :k].double().cpu().numpy() for x, k in ((y, T + 1), (a, T), (r, T + 1))))
    out = run_numpy_bptt_reference(seqs, epochs=epochs, seed=0, hp=JOINT)
    return {
        "sequences": len(seqs),
        "epochs": epochs,
        "mean_length": float(np.mean([len(s[1]) for s in seqs])),
        "wall_time_s": out["wall_time_s"],
        "sequences_per_s": out["sequences_per_s"],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument(
        "--sequences", type=int, default=0, help="sequences per run and epoch (0: the whole training set)"
    )
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 10, 100])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--eager", action="store_true", help="the eager path (default: compiled chunks, the fast path)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (config cpu_threads)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load = os.getloadavg()[0]
    reference = numpy_bptt(args.epochs, args.sequences, args.device)
    rows = [torch_bptt(r, args.epochs, args.sequences, args.device, not args.eager) for r in args.runs]
    ref_rate = reference["sequences_per_s"]
    print(
        f"pattern-mode BPTT of the joint predictor ({EXPERIMENT} training set, lengths 3–7), "
        f"{'eager' if args.eager else 'compiled chunks of steps'}, device={args.device}, "
        f"torch threads={args.threads}, load average {load:.2f} on {os.cpu_count()} CPUs"
    )
    print(
        f"NumPy per-sequence reference (1 run, {reference['epochs']} × {reference['sequences']} sequences, "
        f"mean length {reference['mean_length']:.1f}): {ref_rate:10.0f} sequences/s"
    )
    speedup_table(rows, "sequences_per_s", ref_rate, [("runs", "runs", "d"), ("seq/run", "sequences_per_run", "d")])
    save_results(
        args.out,
        "predictor_bptt" + "_eager" * args.eager,
        args.device,
        experiment=EXPERIMENT,
        numpy_reference=reference,
        torch=rows,
    )


if __name__ == "__main__":
    main()
