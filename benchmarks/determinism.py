"""Why the same eager run can end with other numbers on a CPU with AVX-512 (docs/reliability.md, "Determinism across machines").

    python benchmarks/determinism.py                     # the kernels and settings, ~2 min
    python benchmarks/determinism.py --emulate-avx512 experiment=table5_1_pixel [override ...]
                                                         # an eager run as an AVX-512 CPU computes it

What it shows (docs/reliability.md, "Determinism across machines"):

1. Tails. PyTorch runs most CPU kernels with its AVX2 code on an AVX-512 CPU as well
   (REGISTER_DISPATCH registers no AVX-512 kernel, aten/src/ATen/native/DispatchStub.h, and the
   dispatcher falls back to AVX2). Kernels registered with ALSO_REGISTER_AVX512_DISPATCH do run
   AVX-512 code; of those, ferl's eager runs call sigmoid and softplus, where it matters:
   cpu_kernel_vec (aten/src/ATen/native/cpu/Loops.h) computes a contiguous run of n elements
   2·Vec::size() at a time with the vector formula (Sleef's expf, log1pf) and the rest with the
   scalar one (glibc's expf, log1pf): the last n mod 16 elements with AVX2, the last n mod 32
   with AVX-512. The two formulas disagree in the last bit for a few per cent of inputs, so when
   n mod 32 >= 16 an AVX-512 CPU can return other bits for 16 of the elements. Shown here for
   AVX2: the last n mod 16 elements equal glibc's formula, the others are Sleef's.
2. Settings, each in a child process with its environment set before torch starts (PyTorch reads
   ATEN_CPU_CAPABILITY, oneMKL reads MKL_CBWR at their first use), compared bitwise with
   ``avx2``: products of the RBM fit's shapes, a sigmoid and a sum on inputs from torch.rand
   (the same on every build), the RBM's initial weights and its weights after --sweeps sweeps of
   CD-3, with the fit's time. ``ferl`` is what ferl chooses (AVX2 kernels where the CPU has
   AVX-512, ferl/cpu_kernels.py); ``avx512`` PyTorch's and oneMKL's AVX-512 kernels; ``scalar``
   (ATEN_CPU_CAPABILITY=default) is what a CPU without AVX2 runs; ``mkl_compatible`` pins oneMKL's
   SSE2 branch; ``deterministic`` sets torch.use_deterministic_algorithms; ``float64_fit`` fits in
   float64 (initial weights drawn in float64 too) and ``float64_fit_scalar`` is compared with it.
3. --emulate-avx512: a whole eager run in process on this (AVX2) CPU with sigmoid's and softplus's
   elements [32·floor(n/32), 16·floor(n/16)) recomputed with glibc's formula, i.e. what an AVX-512
   CPU computes, assuming Sleef's AVX2 and AVX-512 code agree lane by lane (the same algorithm).
   The matrix products need no emulation on AMD: oneMKL runs its generic branch with the Zen
   kernel on every AMD CPU with AVX2 (checked under gdb: MKL's feature word with every AVX-512 bit
   set still selects mkl_blas_def_sgemm_kernel_0_zen). Prints the summary's metrics.
"""

import argparse
import collections
import ctypes
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ferl.cpu_kernels import PINS

ROOT = Path(__file__).resolve().parents[1]
AVX2, SCALAR = {"ATEN_CPU_CAPABILITY": "avx2"}, {"ATEN_CPU_CAPABILITY": "default"}
MODE = "FERL_DETERMINISM_MODE"  # how the child fits: float64, deterministic (or the default)
SETTINGS = {
    "avx2": AVX2,
    "ferl": {},
    "avx512": {"ATEN_CPU_CAPABILITY": "avx512", "MKL_ENABLE_INSTRUCTIONS": "AVX512"},
    "scalar": SCALAR,
    "mkl_compatible": {**AVX2, "MKL_CBWR": "COMPATIBLE"},
    "deterministic": {**AVX2, MODE: "deterministic"},
    "float64_fit": {**AVX2, MODE: "float64"},
    "float64_fit_scalar": {**SCALAR, MODE: "float64"},
}
REFERENCE = {"float64_fit_scalar": "float64_fit"}  # what a setting is compared with (else avx2)

LIBM = ctypes.CDLL("libm.so.6")
for _name in ("expf", "log1pf"):
    getattr(LIBM, _name).argtypes, getattr(LIBM, _name).restype = [ctypes.c_float], ctypes.c_float
F32 = np.float32


def sigmoid_scalar(a: np.ndarray) -> np.ndarray:
    """ATen's scalar sigmoid of float32 numbers: 1 / (1 + std::exp(-a)) with glibc's expf."""
    return np.array([F32(1) / (F32(1) + F32(LIBM.expf(float(-x)))) for x in a], dtype=F32)


def softplus_scalar(a: np.ndarray, beta=1.0, threshold=20.0) -> np.ndarray:
    """ATen's scalar softplus: a·β > threshold ? a : log1p(exp(a·β)) / β, with glibc's functions."""
    beta, threshold = F32(beta), F32(threshold)
    return np.array(
        [x if x * beta > threshold else F32(F32(LIBM.log1pf(LIBM.expf(float(x * beta)))) / beta) for x in a], dtype=F32
    )


def memory_order(t: torch.Tensor):
    """A dense tensor's elements as a 1-D view in memory order (TensorIterator's order), or None."""
    p = t.permute(sorted(range(t.dim()), key=lambda d: -t.stride(d)))
    return p.view(-1) if p.is_contiguous() else None


class AVX512Tails(torch.utils._python_dispatch.TorchDispatchMode):
    """sigmoid and softplus (float32) as PyTorch's AVX-512 kernels compute them (finding 1);
    ``counts`` says how often a call was changed and how many elements got other bits."""

    def __init__(self):
        super().__init__()
        self.counts = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        scalar = {torch.ops.aten.sigmoid.default: sigmoid_scalar, torch.ops.aten.softplus.default: softplus_scalar}
        if func in scalar and out.dtype == torch.float32 and out.numel() % 32 >= 16:
            x, n = args[0], out.numel()
            src, dst = memory_order(x), memory_order(out)
            if src is None or x.stride() != out.stride():
                raise NotImplementedError(f"{func}: layout {tuple(x.shape)} {x.stride()}")
            lo, hi = 32 * (n // 32), 16 * (n // 16)
            fixed = scalar[func](src[lo:hi].numpy(), *args[1:3])
            self.counts[f"{func.__name__} calls changed"] += 1
            self.counts[f"{func.__name__} elements with other bits"] += int((dst[lo:hi].numpy() != fixed).sum())
            dst[lo:hi] = torch.from_numpy(fixed)
        elif func in (torch.ops.aten.sigmoid_.default, torch.ops.aten.sigmoid.out, torch.ops.aten.softplus.out):
            raise NotImplementedError(f"{func} is not emulated")
        return out


def tails() -> None:
    """Finding 1 on this machine: which elements of a sigmoid / softplus are glibc's."""
    cap = torch.backends.cpu.get_cpu_capability()
    print(
        f"1. sigmoid / softplus of n float32 numbers (capability {cap}): the last n mod 16 (AVX2) or "
        f"n mod 32 (AVX512) computed with glibc's formula, the rest with Sleef's"
    )
    g = torch.Generator().manual_seed(0)
    for n in (20, 35, 200, 7000):
        x = (torch.rand(n, generator=g) - 0.5) * 16
        for name, op, scalar in (
            ("sigmoid", torch.sigmoid, sigmoid_scalar),
            ("softplus", torch.nn.functional.softplus, softplus_scalar),
        ):
            got, glibc = op(x).numpy(), scalar(x.numpy())
            width = {"AVX2": 16, "AVX512": 32}.get(cap, 1)  # 2 × the vector's float32 lanes
            vec = width * (n // width)
            lo = 32 * (n // 32)
            print(
                f"   {name:8s} n={n:5d}: tail == glibc: {np.array_equal(got[vec:], glibc[vec:])}; "
                f"Sleef part differs from glibc in {int((got[:vec] != glibc[:vec]).sum())}/{vec}; "
                f"elements an AVX-512 CPU computes otherwise: {int((got[lo:vec] != glibc[lo:vec]).sum())}"
            )


def child(out: Path, sweeps: int, runs: int) -> None:
    """One setting of finding 2: the tensors to compare and the fit's time, saved to out (npz + json)."""
    sys.path.insert(0, str(ROOT))
    from ferl.data import MnistEmbedded
    from ferl.preprocessors.rbm import RBMPreprocessor

    torch.set_num_threads(1)
    mode = os.environ.get(MODE)
    torch.use_deterministic_algorithms(mode == "deterministic")
    g = torch.Generator().manual_seed(3)
    v, w = torch.rand(runs, 100, 784, generator=g), (torch.rand(runs, 784, 20, generator=g) - 0.5) * 0.1
    h = torch.rand(runs, 100, 20, generator=g)
    tensors = {
        "bmm v·W (R,100,784)(R,784,20)": torch.bmm(v, w),
        "bmm vᵀ·h (R,784,100)(R,100,20)": torch.bmm(v.mT, h),
        "baddbmm h·Wᵀ (R,100,20)(R,20,784)": torch.baddbmm(v[:, :1], h, w.mT),
        "sigmoid (R,100,784)": torch.sigmoid(v * 20 - 10),
        "sum over 784": v.sum(-1),
    }
    images = MnistEmbedded().load().train_images
    model = RBMPreprocessor(runs, sweeps=sweeps, seed=3)
    if mode == "float64":
        model, images = model.double(), images.double()
        model.W.copy_(
            torch.stack(
                [
                    torch.randn(784, 20, generator=torch.Generator().manual_seed(3 + r), dtype=torch.float64)
                    for r in range(runs)
                ]
            )
            * 0.01
        )
    tensors["RBM W before the fit"] = model.W.float().clone()
    start = time.perf_counter()
    model.train(images, progress=False)
    seconds = time.perf_counter() - start
    tensors[f"RBM W after {sweeps} sweeps"] = model.W.float()
    np.savez(out, **{k: t.detach().numpy() for k, t in tensors.items()})
    out.with_suffix(".json").write_text(
        json.dumps({"capability": torch.backends.cpu.get_cpu_capability(), "fit_s": seconds})
    )


def settings(sweeps: int, runs: int) -> None:
    """Finding 2: every setting in a child process, compared bitwise."""
    with tempfile.TemporaryDirectory() as tmp:
        results = {}
        for name, env in SETTINGS.items():
            out = Path(tmp) / f"{name}.npz"
            subprocess.run(
                [sys.executable, __file__, "--child", str(out), "--sweeps", str(sweeps), "--runs", str(runs)],
                check=True,
                env={
                    **{k: v for k, v in os.environ.items() if k not in (*PINS, "MKL_CBWR", MODE)},
                    "OMP_NUM_THREADS": "1",
                    "MKL_NUM_THREADS": "1",
                    **env,
                },
            )
            results[name] = (dict(np.load(out)), json.loads(out.with_suffix(".json").read_text()))
    print(
        f"\n2. settings: differing elements / all, largest difference; RBM: {runs} runs, CD-3 on 1 000 "
        f"images, {sweeps} sweeps"
    )
    for name, (tensors, info) in results.items():
        ref = results[REFERENCE.get(name, "avx2")][0]
        env = " ".join(f"{k}={v}" for k, v in SETTINGS[name].items())
        print(
            f"   {name} against {REFERENCE.get(name, 'avx2')} ({env or 'nothing set'}; capability "
            f"{info['capability']}; fit {info['fit_s']:.2f} s)"
        )
        for key, t in tensors.items():
            differ = int((t != ref[key]).sum())
            print(f"      {key:36s} {differ:7d} / {t.size:<7d} {float(np.abs(t - ref[key]).max()):.3g}")


def emulate(overrides: list) -> None:
    """Finding 3: one eager run (compile=false), in process, with AVX-512's sigmoid and softplus."""
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import compose_config, train_job

    mode = AVX512Tails()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = compose_config(overrides)
        if "cache_dir" in (cfg.get("preprocessor") or {}):  # fitted under the emulation, not loaded
            cfg.preprocessor.cache_dir = f"{tmp}/cache"
        with mode:
            summary = train_job(cfg, Path(tmp) / "run")
    print(dict(mode.counts))
    print(json.dumps(summary["metrics"]))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sweeps", type=int, default=30)
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument(
        "--emulate-avx512",
        nargs=argparse.REMAINDER,
        metavar="OVERRIDE",
        help="train.py overrides of one eager run to emulate (its RBM is fitted, not loaded)",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(Path(args.child), args.sweeps, args.runs)
    if args.emulate_avx512 is not None:
        return emulate(args.emulate_avx512)
    tails()
    settings(args.sweeps, args.runs)


if __name__ == "__main__":
    main()
