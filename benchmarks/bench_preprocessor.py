"""Wall time of the RBM preprocessor's training (§5.3.2: CD-3, 20 hidden, 600 sweeps).

    python benchmarks/bench_preprocessor.py [--sweeps 600] [--runs 10] [--images 1000] [--device cpu] [--threads 1]

Trains on the embedded subset's training images (1 000; the dissertation's 60 000 cost about
60× as much per sweep) with the default config and prints the time, the time per sweep and the
final reconstruction error of every run.
"""

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ferl.data import MnistEmbedded  # noqa: E402
from ferl.preprocessors.rbm import RBMPreprocessor  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweeps", type=int, default=600)
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--images", type=int, default=1000, help="training images (tiled if more than 1 000)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads on CPU")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    train = MnistEmbedded().load().train_images
    images = train.repeat(-(-args.images // len(train)), 1)[: args.images].to(args.device)
    model = RBMPreprocessor(args.runs, sweeps=args.sweeps).to(args.device)
    start = time.perf_counter()
    errors = model.train(images, progress=False)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    print(
        f"{args.sweeps} sweeps × {args.images} images × {args.runs} runs on {args.device} "
        f"({args.threads} thread(s)): {seconds:.1f} s, {seconds / args.sweeps * 1000:.1f} ms/sweep"
    )
    print("final reconstruction error per run:", " ".join(f"{e:.4f}" for e in errors[:, -1]))


if __name__ == "__main__":
    main()
