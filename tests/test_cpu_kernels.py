"""ferl asks for the AVX2 kernels on CPUs with AVX-512 (ferl/cpu_kernels.py): the rule, and on
such a CPU the kernel that made table5_1_pixel's numbers depend on the machine."""

import os
import subprocess
import sys

import pytest

from conftest import ROOT
from ferl.cpu_kernels import PINS, has_avx512, pin_avx2

FLAGS = "processor\t: 0\nflags\t\t: fpu sse2 avx avx2 {extra}\n\n"


def cpuinfo(path, extra: str):
    path.write_text(FLAGS.format(extra=extra))
    return path


def test_the_pins_are_set_only_with_avx512_on_x86_and_never_over_the_users(tmp_path):
    avx512, avx2 = cpuinfo(tmp_path / "avx512", "avx512f avx512bw"), cpuinfo(tmp_path / "avx2", "fma")
    env = {}
    assert pin_avx2(env, avx512, "x86_64") == PINS and env == PINS
    env = {"ATEN_CPU_CAPABILITY": "avx512"}
    assert pin_avx2(env, avx512, "x86_64") == {"MKL_ENABLE_INSTRUCTIONS": "AVX2"}
    assert env["ATEN_CPU_CAPABILITY"] == "avx512"
    for args in ((avx2, "x86_64"), (avx512, "aarch64"), (tmp_path / "missing", "x86_64")):
        env = {}
        assert pin_avx2(env, *args) == {} and env == {}


SIGMOID = """
import sys
{first}
import torch
g = torch.Generator().manual_seed(0)
x = (torch.rand(20, generator=g) - 0.5) * 16  # n mod 32 = 20 >= 16: AVX-512 computes the first 16 otherwise
print(torch.backends.cpu.get_cpu_capability(), *torch.sigmoid(x).view(torch.int32).tolist())
"""


def sigmoid_bits(first: str, **env) -> tuple[str, list]:
    environ = {k: v for k, v in os.environ.items() if k not in PINS}
    out = subprocess.run(
        [sys.executable, "-c", SIGMOID.format(first=first)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**environ, **env},
        check=True,
    ).stdout.split()
    return out[0], out[1:]


@pytest.mark.skipif(not has_avx512(), reason="shown on a CPU with AVX-512")
def test_with_ferl_imported_sigmoid_has_the_bits_of_an_avx2_cpu():
    pinned = sigmoid_bits("import ferl")
    avx2 = sigmoid_bits("", ATEN_CPU_CAPABILITY="avx2")
    avx512 = sigmoid_bits("", ATEN_CPU_CAPABILITY="avx512")
    assert pinned == avx2 and pinned[0] == "AVX2" and avx512[0] == "AVX512"
    differ = sum(a != b for a, b in zip(avx2[1], avx512[1]))
    assert 0 < differ <= 16, differ  # the kernel the pin is for: only the tail, only a few


def test_inductor_keeps_a_cache_per_vector_isa(tmp_path):
    """Inductor's cache key leaves the ISA out, and a cache filled under another ISA ended in "double
    free or corruption" (docs/reliability.md): ferl's default cache folder is named after the ISA."""
    code = "from ferl.compiled import cache_dir, vector_isa; print(cache_dir(), vector_isa())"
    environ = {k: v for k, v in os.environ.items() if k not in ("TORCHINDUCTOR_CACHE_DIR", *PINS)}
    folders = {}
    for capability in ("avx2", "default"):
        out = subprocess.run(
            [sys.executable, "-c", code],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            env={**environ, "HOME": str(tmp_path), "ATEN_CPU_CAPABILITY": capability},
        ).stdout.split()
        folders[capability] = out
    assert folders["avx2"] == [str(tmp_path / ".cache" / "ferl" / "inductor" / "avx2"), "avx2"]
    assert folders["default"][0] == str(tmp_path / ".cache" / "ferl" / "inductor" / folders["default"][1])
    assert folders["default"][1] != "avx2"


def test_the_discounted_return_is_the_exact_sum_in_step_order_whatever_blas_runs():
    """The recorded return (``discounted_return``) against a float64 NumPy sum written out step by
    step, and unchanged when the rewards pass through another BLAS call first (a matmul by the
    identity, whose kernel choice used to decide the return's ninth digit)."""
    import functools
    import operator

    import numpy as np
    import torch

    from ferl.trainers.episodes import discount_factors, discounted_return

    gamma, steps = 0.95, 37
    rewards = torch.tensor(
        np.random.default_rng(0).choice([-5.0, -1.0, -0.1, 5.0], size=(steps, 7)), dtype=torch.float32
    )
    factors = discount_factors(gamma, steps)
    assert factors == [functools.reduce(operator.mul, [gamma] * t, 1.0) for t in range(steps)]  # 1·γ·γ·…, in order
    expected = np.zeros(7)
    for t in range(steps):
        expected = expected + factors[t] * rewards[t].numpy().astype(np.float64)
    got = discounted_return(factors, rewards)
    assert got.dtype == torch.float32
    assert np.array_equal(got.numpy(), expected.astype(np.float32))
    assert torch.equal(discounted_return(factors, torch.eye(steps) @ rewards), got)
    assert np.allclose(got.numpy(), (gamma ** np.arange(steps)) @ rewards.numpy().astype(np.float64), rtol=1e-6)


def test_a_vector_isa_probe_that_loaded_is_remembered_and_a_failed_one_is_not(tmp_path, monkeypatch):
    """``remember_isa_probes``: inductor's probe (a fresh process loading the library) runs once for
    a library that loads, then a file beside it answers; a library that failed is probed every time."""
    from torch._inductor.cpu_vec_isa import VecISA

    import ferl.compiled

    calls = []
    monkeypatch.setattr(VecISA, "_probe_load", lambda isa, library: calls.append(library) or "good" in library)
    ferl.compiled.remember_isa_probes()
    good, bad = str(tmp_path / "good.so"), str(tmp_path / "bad.so")
    answers = [VecISA._probe_load(None, library) for library in (good, bad, good, bad, good)]
    assert answers == [True, False, True, False, True]
    assert calls == [good, bad, bad]
    assert (tmp_path / "good.so.loads").exists() and not (tmp_path / "bad.so.loads").exists()
    ferl.compiled.remember_isa_probes()  # installed once: no probe wrapped twice
    VecISA._probe_load(None, bad)
    assert calls == [good, bad, bad, bad]


def test_remembered_probes_pick_the_vector_isa_that_probing_picks():
    """With the probes remembered, a process picks the ISA that torch picks by probing alone: the
    first process may probe and remember, the second reads what was remembered."""
    probed = (  # torch's own probes (ferl imported for its kernel pin), named as vector_isa names them
        "import ferl; from torch._inductor.cpu_vec_isa import pick_vec_isa; isa = pick_vec_isa(); "
        "print('_'.join(str(isa).split()) if isa else 'none')"
    )
    ours = "from ferl.compiled import cache_dir, vector_isa; cache_dir(); print(vector_isa())"
    run = lambda code: subprocess.run(  # noqa: E731
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    picks = [run(ours), run(ours)]
    assert picks == [run(probed)] * 2
