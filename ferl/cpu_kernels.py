"""The same CPU kernels on every x86 CPU with AVX2, so that a run's numbers do not depend on
whether the CPU also has AVX-512 (docs/reliability.md, "Determinism across machines").

PyTorch and oneMKL pick their CPU kernels by the instructions a CPU has:

* ATen's sigmoid and softplus (registered with ``ALSO_REGISTER_AVX512_DISPATCH``) compute a
  contiguous block of n numbers 2·(vector width) at a time with Sleef's formula and the rest with
  the scalar one: the last n mod 16 with AVX2, n mod 32 with AVX-512. The two formulas differ in
  the last bit for a few per cent of inputs (``benchmarks/determinism.py``);
* inductor generates AVX-512 code (and AMX where there is some) for the fast path;
* oneMKL's sgemm takes its AVX-512 kernels on an Intel CPU (on AMD it runs its Zen kernel either way).

A learning run amplifies one bit into another trajectory: ``table5_1_pixel`` (eager) ended at a
correct-goal rate of 0.811 with the AVX2 kernels and 0.855 with the AVX-512 ones on one machine,
its predictors first parting in the last run, the one in the tail. So where the CPU has AVX-512,
ferl asks both libraries for their AVX2 kernels before either picks one (PyTorch reads
``ATEN_CPU_CAPABILITY`` at its first dispatched kernel, oneMKL ``MKL_ENABLE_INSTRUCTIONS`` at its
first call). A variable the user has set is kept: ``ATEN_CPU_CAPABILITY=avx512`` brings the AVX-512
kernels back.
"""

import os
import platform
from pathlib import Path

PINS = {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}


def has_avx512(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether the CPU's flags (Linux's /proc/cpuinfo) include avx512f; False where unreadable."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return False
    flags = next((line.split(":", 1)[1].split() for line in lines if line.startswith("flags")), [])
    return "avx512f" in flags


def pin_avx2(environ=os.environ, cpuinfo: Path = Path("/proc/cpuinfo"), machine: str | None = None) -> dict:
    """Set the ``PINS`` the user has not set, on an x86 CPU with AVX-512; returns those set."""
    if (machine or platform.machine()) not in ("x86_64", "AMD64") or not has_avx512(cpuinfo):
        return {}
    pinned = {key: value for key, value in PINS.items() if key not in environ}
    environ.update(pinned)
    return pinned
