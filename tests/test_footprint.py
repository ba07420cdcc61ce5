"""Runs too large for the machine (issue 24, item 4): the memory a run needs is estimated from its
config before any of its tensors exists (ferl/run/footprint.py), and a run over the free memory is
refused in one line naming n_runs, the estimate and the limit, with nothing written.

The estimate is checked against the bytes malloc actually hands out during whole runs (glibc's
mallinfo2, sampled in the run's process), an independent measurement of the same thing."""

import ctypes
import json
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from conftest import ROOT, SHORT_ALGORITHM1, run_train, validated_config
from ferl.config.params import ConfigError
from ferl.interfaces import TrainerBase
from ferl.run import footprint
from ferl.run.footprint import check_memory, estimate, host_free

GOLDEN = json.loads((Path(__file__).parent / "golden" / "reduced_scale.json").read_text())
ONLINE = [
    "experiment=table4_1_regular",
    "trainer=online",
    "trainer.n_episodes=30",
    "trainer.replay_sample=8",
    "trainer.log_every=10",
    "trainer.td_sample_every=10",
    "trainer.final_window=10",
]
MAZE = [
    "experiment=table4_1_regular",
    *SHORT_ALGORITHM1,
]


# ---- the refusal ----------------------------------------------------------------------------------
@pytest.mark.parametrize("experiment", [None, "table4_1_regular"])
def test_a_huge_n_runs_is_refused_in_one_line_and_leaves_nothing(tmp_path, experiment):
    """The user's case of issue 24: ``python train.py n_runs=50000000`` (the digit floor)."""
    out = tmp_path / "out"
    args = [f"experiment={experiment}"] if experiment else []
    result = run_train(*args, "n_runs=50000000", f"hydra.run.dir={out / 'run'}")
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1, result.stderr[-3000:]
    assert lines[0].startswith("ferl: error: n_runs=50000000 needs about ")
    assert " a run + " in lines[0] and " free (" in lines[0] and "at most n_runs=" in lines[0]
    assert "Traceback" not in result.stderr + result.stdout
    assert not out.exists()


def test_the_refusal_names_estimate_and_limit(monkeypatch):
    monkeypatch.setattr(footprint, "host_free", lambda: (10**6, "MemAvailable"))
    monkeypatch.setattr(footprint, "estimate", lambda cfg, device: footprint.Footprint(200_000, 30_000))
    cfg = OmegaConf.create({"n_runs": 50, "device": "cpu", "memory_check": True})
    with pytest.raises(ConfigError) as e:
        check_memory(cfg)
    assert str(e.value) == (
        "n_runs=50 needs about 1.7 MB of memory (30.0 kB a run + 200.0 kB fixed, estimated "
        "from set-ups with n_runs=1 and 2), more than the 1.0 MB free (MemAvailable): by this "
        "estimate at most n_runs=26 fit; memory_check=false skips this check"
    )
    cfg.n_runs = 26
    check_memory(cfg)  # 200 kB + 26 × 30 kB = 980 kB: fits


def test_memory_check_false_skips_the_estimate(monkeypatch):
    monkeypatch.setattr(footprint, "estimate", lambda *a: pytest.fail("estimated although memory_check=false"))
    check_memory(OmegaConf.create({"n_runs": 10**12, "device": "cpu", "memory_check": False}))
    with pytest.raises(ConfigError, match=r"^memory_check="):
        validated_config(["memory_check=sometimes"])


@pytest.mark.parametrize(
    "overrides", [["experiment=ch3_floor"], ["experiment=table4_1_regular"], ["experiment=table5_1_pixel"], ONLINE[:2]]
)
def test_the_default_configs_pass_and_their_estimate_grows_with_n_runs(overrides):
    cfg = validated_config(overrides)
    check_memory(cfg)
    fp = estimate(cfg, torch.device("cpu"))
    assert fp.host_per_run > 0 and fp.device_fixed == fp.device_per_run == 0
    assert fp.host(cfg.n_runs) < host_free()[0]


# ---- what the estimate counts ----------------------------------------------------------------------
class HookTrainer(TrainerBase):
    """A trainer as a user may write one: weights (R × 1000 float32), a view of them, a fixed table;
    records allocated as it starts (R × 500 float32) and 1 MB a run it says it takes later."""

    def setup(self, cfg, device):
        self.job = self
        self.R = cfg.n_runs
        self.weights = torch.zeros(self.R, 1000, device=device)
        self.first = self.weights[0]  # a view: the same storage, counted once
        self.table = torch.zeros(250, device=device)
        self.lookup = lambda i: self.table[i]  # reached through a closure as well

    def starting_state(self) -> list:
        return [{"records": np.zeros((self.R, 500), np.float32), "weights_again": self.weights}]

    def run_bytes(self) -> int:
        return self.R * 10**6


def test_the_estimate_counts_each_storage_once_fresh_state_and_the_hook():
    cfg = OmegaConf.create(
        {"trainer": {"_target_": f"{__name__}.HookTrainer"}, "n_runs": 7, "device": "cpu", "seed": 0}
    )
    fp = estimate(cfg, torch.device("cpu"))
    assert fp == footprint.Footprint(host_fixed=1000, host_per_run=4000 + 2000 + 10**6)
    assert fp.host(7) == 1000 + 7 * 1_006_000


def test_host_free_is_mem_available_or_the_cgroup_limit_below_it(tmp_path):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:       16000000 kB\nMemFree:         1000000 kB\nMemAvailable:    8000000 kB\n")
    cgroup = tmp_path / "cgroup"
    cgroup.mkdir()
    assert host_free(meminfo, cgroup) == (8_192_000_000, "MemAvailable")
    (cgroup / "memory.max").write_text("max\n")
    (cgroup / "memory.current").write_text("1000\n")
    assert host_free(meminfo, cgroup) == (8_192_000_000, "MemAvailable")
    (cgroup / "memory.max").write_text("3000000000\n")
    assert host_free(meminfo, cgroup) == (2_999_999_000, "cgroup memory.max − memory.current")


# ---- the numbers do not change ----------------------------------------------------------------------
def test_the_estimate_leaves_the_global_random_states_and_the_config():
    cfg = validated_config(["experiment=table4_1_regular"])
    before = OmegaConf.to_container(cfg)
    torch.manual_seed(5), np.random.seed(5), random.seed(5)
    expected = (torch.rand(3), np.random.rand(3), random.random())
    torch.manual_seed(5), np.random.seed(5), random.seed(5)
    estimate(cfg, torch.device("cpu"))
    drawn = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(drawn[0], expected[0]) and (drawn[1] == expected[1]).all() and drawn[2] == expected[2]
    assert OmegaConf.to_container(cfg) == before


def test_a_checked_run_through_train_py_keeps_its_golden_numbers(tmp_path):
    golden = GOLDEN["ch3_floor"]
    run_dir = tmp_path / "run"
    result = run_train(*golden["overrides"], "memory_check=true", f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads((run_dir / "summary.json").read_text())["metrics"] == golden["metrics"]


# ---- the estimate against the memory runs take ------------------------------------------------------
HEAP = """
import ctypes, json, sys, tempfile, threading, time
sys.path.insert(0, "tests")
from conftest import train_job, validated_config

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
def allocated():
    info = libc.mallinfo2()
    return info.uordblks + info.hblkhd  # bytes malloc has handed out and not taken back

cfg = validated_config(sys.argv[1:])
peak, done = [0], []
def sample():
    while not done:
        peak[0] = max(peak[0], allocated())
        time.sleep(0.002)
base = allocated()
sampler = threading.Thread(target=sample)
sampler.start()
with tempfile.TemporaryDirectory() as tmp:
    train_job(cfg, tmp + "/run")
done.append(True)
sampler.join()
print(json.dumps(peak[0] - base))
"""


def has_mallinfo2() -> bool:
    try:
        return hasattr(ctypes.CDLL("libc.so.6"), "mallinfo2")
    except OSError:
        return False


def measured_peak(overrides: list) -> int:
    """Peak bytes malloc handed out during the whole run (data, set-up, every phase, records), over
    what the process held before it."""
    result = subprocess.run(
        [sys.executable, "-c", HEAP, *overrides, "compile=false"], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return int(result.stdout.split()[-1])


def compare(overrides: list, small: int = 2, large: int = 200) -> tuple[float, float]:
    """(measured / estimated bytes per run, measured / estimated bytes at ``large`` runs)."""
    peaks = {n: measured_peak([*overrides, f"n_runs={n}"]) for n in (small, large)}
    fp = estimate(validated_config(overrides), torch.device("cpu"))
    slope = (peaks[large] - peaks[small]) / (large - small)
    print(
        f"{' '.join(overrides[:2])}: per run measured {slope:.0f} B, estimated {fp.host_per_run} B; at {large} runs "
        f"measured {peaks[large]} B, estimated {fp.host(large)} B"
    )
    return slope / fp.host_per_run, peaks[large] / fp.host(large)


@pytest.mark.skipif(not has_mallinfo2(), reason="measured with glibc's mallinfo2")
@pytest.mark.parametrize("overrides", [ONLINE], ids=["online_maze"])
def test_the_estimate_is_within_a_factor_of_the_memory_runs_take(overrides):
    """Per run within a factor 2 either way; in all, at 200 runs, within a factor 3. (The digit
    floor is not held to it: its test phase's activations are not in the estimate, and a fresh
    environment measured 2.5× per run and 3.5× in all at 200 runs, where another had 0.7–1.4×.)"""
    per_run, total = compare(overrides)
    assert 0.5 <= per_run <= 2, per_run
    assert 0.5 <= total <= 3, total


# What phases allocate while they run, beyond what they hold when they start, is in the estimate where
# a phase reports it (``run_bytes(job)``): Algorithm 1's collected episodes and training tensors, the
# floor tests' activations. Algorithm 1's is an upper bound: balancing keeps n per length, at most
# n_sample episodes in all (here 48 of 300), so its estimate may be a few times what a run takes, and
# never less.
GAPS = {
    "algorithm1_maze": (MAZE, 200),
    "floor_default_tests": (
        ["experiment=ch3_floor", "trainer.steps=300", "trainer.log_every=100", "trainer.checkpoint_every=100"],
        20,
    ),
}


@pytest.mark.skipif(not has_mallinfo2(), reason="measured with glibc's mallinfo2")
@pytest.mark.parametrize("case", list(GAPS))
def test_the_estimate_counts_what_phases_allocate_while_running(case):
    """Per run, the estimate is at least 0.8× what runs take (not less: 0.04× for the maze and
    0.05× for the floor before the phases reported it) and at most 4× (the maze's upper bound)."""
    overrides, large = GAPS[case]
    per_run, _ = compare(overrides, large=large)
    assert 0.25 <= per_run <= 1.25, per_run
