"""How much memory a run needs, checked against the machine before any of the run's tensors exists.

The estimate runs the config's own code, so a user's component needs nothing added: the trainer of
``cfg.trainer`` is set up (its ``setup``, as train.py does it, eager) with n_runs = 1 and with
n_runs = 2, the data loaded once for both. What a set-up trainer holds — every tensor and NumPy
array reachable from it, each storage once: data, weights, tiles, reservoirs, test sets, blocks of
random numbers — plus what it allocates as it starts (``Trainer.starting_state``: its phases'
``fresh_state``, records of every step or episode, replay, episode tables) gives bytes per run (the
difference of the two probes) and fixed bytes (the rest), and the run needs fixed + n_runs × per
run. What it allocates later while it runs (collected episodes, training batches, test
activations) is added as the trainer says (``Trainer.run_bytes``: a phased trainer's largest
``Phase.run_bytes``, which includes what earlier phases handed the phase; 0 by default).

The limit is the memory free now: MemAvailable of /proc/meminfo (lowered to what the cgroup still
allows, in a container), and on CUDA the device's free memory for the tensors. A run over it is
refused with one line naming n_runs, the estimate and the limit; ``memory_check=false`` skips it.

The probes draw only from their own generators; the global random states (torch, NumPy, random)
are saved and restored around them, so the run's numbers do not change.
"""

import random
from collections import deque
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass
from io import StringIO
from pathlib import Path
from types import BuiltinFunctionType, FunctionType, MethodType, ModuleType

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import Container, OmegaConf

from ferl.config.hydra_glue import resolve_device
from ferl.config.params import ConfigError
from ferl.config.validate import resolved

PROBES = (1, 2)  # n_runs of the two set-ups the estimate extrapolates from
SKIP = (
    str,
    bytes,
    int,
    float,
    bool,
    complex,
    type(None),
    type,
    ModuleType,
    BuiltinFunctionType,
    Container,
    torch.device,
    torch.dtype,
    torch.Generator,
    range,
)


@dataclass(frozen=True)
class Footprint:
    """Bytes a run needs: fixed + n_runs × per_run, on the host and on a CUDA device."""

    host_fixed: int
    host_per_run: int
    device_fixed: int = 0
    device_per_run: int = 0

    def host(self, n_runs: int) -> int:
        return self.host_fixed + n_runs * self.host_per_run

    def device(self, n_runs: int) -> int:
        return self.device_fixed + n_runs * self.device_per_run


def check_memory(cfg) -> None:
    """ConfigError (one line) when the run of ``cfg`` would need more memory than is free."""
    if not cfg.get("memory_check", True):
        return
    device = resolve_device(cfg.device)
    n_runs = int(cfg.n_runs)
    footprint = estimate(cfg, device)
    if footprint is None:  # the set-up itself fails: the run's own set-up reports why
        return
    needs = [("", footprint.host_fixed, footprint.host_per_run, host_free())]
    if device.type == "cuda":
        needs.append(
            (
                f" on {device}",
                footprint.device_fixed,
                footprint.device_per_run,
                (torch.cuda.mem_get_info(device)[0], "torch.cuda.mem_get_info"),
            )
        )
    for where, fixed, per_run, (free, source) in needs:
        if fixed + n_runs * per_run > free:
            raise ConfigError(refusal(n_runs, where, fixed, per_run, free, source))


def refusal(n_runs: int, where: str, fixed: int, per_run: int, free: int, source: str) -> str:
    """The one line that refuses the run."""
    total = fixed + n_runs * per_run
    most = (free - fixed) // per_run if per_run else 0
    advice = (
        f"by this estimate at most n_runs={most} fit"
        if most >= 1
        else "not even n_runs=1 fits: the config's other sizes (data, steps, episodes, layers) are too large"
    )
    return (
        f"n_runs={n_runs} needs about {size(total)} of memory{where} ({size(per_run)} a run + {size(fixed)} "
        f"fixed, estimated from set-ups with n_runs=1 and 2), more than the {size(free)} free ({source}): "
        f"{advice}; memory_check=false skips this check"
    )


def size(n: float) -> str:
    """Bytes in decimal units: 936.8 kB, 46.8 TB."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


# ---- the estimate ---------------------------------------------------------------------------------
def estimate(cfg, device: torch.device) -> Footprint | None:
    """Fixed and per-run bytes from the set-ups at n_runs = 1 and 2 (module docstring), or None
    when a set-up fails (then the run's own set-up fails too, and says why)."""
    values = resolved(cfg)
    if isinstance(values.get("data"), dict):
        values["data"] = {"_target_": f"{__name__}.LoadedOnce", "node": values["data"], "_recursive_": False}
    try:
        with probing(device):
            held = [probe(values, n, device) for n in PROBES]
    except Exception:  # noqa: BLE001 — the same error comes again, in the run, where it is reported
        return None
    (host1, device1), (host2, device2) = held
    host_per_run, device_per_run = max(0, host2 - host1), max(0, device2 - device1)
    return Footprint(max(0, host1 - host_per_run), host_per_run, max(0, device1 - device_per_run), device_per_run)


def probe(values: dict, n_runs: int, device: torch.device) -> tuple[int, int]:
    """(host bytes, device bytes) that the trainer of ``values`` with ``n_runs`` holds once set
    up and once its phases have started."""
    cfg = OmegaConf.create({**values, "n_runs": n_runs, "compile": False})
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, device)
    storages = Storages()
    storages.add(trainer)
    with torch.no_grad():
        storages.add(trainer.starting_state())
    extra = int(trainer.run_bytes())  # allocated where the run computes
    return (storages.host, storages.device + extra) if device.type == "cuda" else (storages.host + extra, 0)


class Storages:
    """The memory behind every tensor and array reachable from the objects added, each once."""

    def __init__(self) -> None:
        self.seen: dict[tuple[bool, int], int] = {}  # (on a CUDA device, start address) → bytes
        self.visited: set[int] = set()  # ids of the objects walked, kept alive by the roots
        self.roots: list = []

    @property
    def host(self) -> int:
        return sum(n for (on_device, _), n in self.seen.items() if not on_device)

    @property
    def device(self) -> int:
        return sum(n for (on_device, _), n in self.seen.items() if on_device)

    def count(self, address: int, nbytes: int, on_device: bool) -> None:
        if address and nbytes > self.seen.get((on_device, address), 0):
            self.seen[(on_device, address)] = nbytes

    def add(self, root) -> None:
        self.roots.append(root)
        visited, stack = self.visited, [root]
        while stack:
            x = stack.pop()
            if isinstance(x, SKIP) or id(x) in visited:
                continue
            visited.add(id(x))
            if isinstance(x, torch.Tensor):
                self.tensor(x)
            elif isinstance(x, np.ndarray):
                base = x
                while isinstance(base.base, np.ndarray):
                    base = base.base
                if base.dtype != object:
                    self.count(base.__array_interface__["data"][0], base.nbytes, False)
            elif isinstance(x, dict):
                stack.extend(x.values())
            elif isinstance(x, (list, tuple, set, frozenset, deque)):
                stack.extend(x)
            elif isinstance(x, FunctionType):
                stack.extend(c.cell_contents for c in x.__closure__ or () if cell_filled(c))
            elif isinstance(x, MethodType):
                stack.append(x.__self__)
            else:
                stack.extend(getattr(x, "__dict__", {}).values())
                stack.extend(getattr(x, name) for name in getattr(type(x), "__slots__", ()) if hasattr(x, name))

    def tensor(self, t: torch.Tensor) -> None:
        try:
            storage = t.untyped_storage()
            self.count(storage.data_ptr(), storage.nbytes(), t.device.type == "cuda")
        except (RuntimeError, NotImplementedError):  # sparse, meta or other storage-less tensors
            pass
        if t.grad is not None:
            self.tensor(t.grad)


def cell_filled(cell) -> bool:
    try:
        _ = cell.cell_contents  # an empty cell raises
    except ValueError:
        return False
    return True


class LoadedOnce:
    """The probes' data node: the config's own data component, loaded by the first probe and
    handed to the second (its bytes are the same in both: fixed)."""

    shared: dict | None = None  # during ``estimate``: the component and what it loaded

    def __init__(self, node):
        self.node = node

    def component(self):
        if "component" not in self.shared:
            self.shared["component"] = instantiate(self.node)
        return self.shared["component"]

    def load(self):
        if "data" not in self.shared:
            self.shared["data"] = self.component().load()
        return self.shared["data"]

    def __getattr__(self, name):  # any other use of the data component reaches the real one
        if name in ("node", "shared"):
            raise AttributeError(name)
        return getattr(self.component(), name)


@contextmanager
def probing(device: torch.device):
    """Around the probes: their data shared, nothing printed, and torch's (the CUDA device's
    too), NumPy's and Python's global random states as they were before."""
    devices = [device] if device.type == "cuda" else []
    states = (
        torch.get_rng_state(),
        [torch.cuda.get_rng_state(d) for d in devices],
        np.random.get_state(),
        random.getstate(),
    )
    LoadedOnce.shared = {}
    try:
        with redirect_stdout(StringIO()), redirect_stderr(StringIO()):
            yield
    finally:
        LoadedOnce.shared = None
        cpu, cuda, numpy_state, python_state = states
        torch.set_rng_state(cpu)
        for d, state in zip(devices, cuda):
            torch.cuda.set_rng_state(state, d)
        np.random.set_state(numpy_state)
        random.setstate(python_state)
        if devices:
            torch.cuda.empty_cache()


# ---- the limit ------------------------------------------------------------------------------------
def host_free(meminfo: Path = Path("/proc/meminfo"), cgroup: Path = Path("/sys/fs/cgroup")) -> tuple[int, str]:
    """(bytes free for a new process's memory, where that number comes from)."""
    free, source = None, "MemAvailable"
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                free = int(line.split()[1]) * 1024
    except OSError:
        pass
    if free is None:
        try:
            import psutil

            free, source = psutil.virtual_memory().available, "psutil"
        except ImportError:
            return 1 << 62, "unknown"
    try:
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            left = int(limit) - int((cgroup / "memory.current").read_text())
            if left < free:
                free, source = left, "cgroup memory.max − memory.current"
    except (OSError, ValueError):
        pass
    return free, source
