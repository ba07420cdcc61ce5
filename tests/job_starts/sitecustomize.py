"""Test-only (tests/test_sweep_faults.py): the jobs' starts, counted across processes.

Where ``FERL_JOB_STARTS`` names a file and this folder is on ``PYTHONPATH``, Python imports this
module as each process starts (``site``'s ``sitecustomize``): the sweeps' launcher, Hydra's joblib
workers and every resumed job's ``train.py``. It wraps ``ferl.run.claim.claim`` as that module is
first imported, so that each claim that succeeds, a job that now owns its run directory and will
train in it, appends the directory to the file: one line each, written with O_APPEND so that
processes at work at once do not mix their lines. Without the variable it does nothing.
"""

import os
import sys

STARTS = os.environ.get("FERL_JOB_STARTS")


def _counted(claim):
    def counting(run_path, cfg, lock):
        claim(run_path, cfg, lock)
        fd = os.open(STARTS, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, f"{os.path.abspath(run_path)}\n".encode())
        finally:
            os.close(fd)

    return counting


class _WrapClaim:
    """A meta-path finder that loads ``ferl.run.claim`` as usual, then wraps its ``claim``."""

    def find_spec(self, name, path, target=None):
        if name != "ferl.run.claim":
            return None
        from importlib.machinery import PathFinder

        spec = PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            module.claim = _counted(module.claim)

        spec.loader.exec_module = exec_module
        return spec


if STARTS:
    sys.meta_path.insert(0, _WrapClaim())
