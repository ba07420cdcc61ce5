"""A multirun job's folder (conf/config.yaml's ``hydra.sweep.subdir``, docs/usage.md "Sweeps"):
``<job number>_<experiment>``, then the job's overrides as Hydra's ``hydra.job.override_dirname``
writes them, e.g. ``2_table4_1_regular+predictor.joint.memory-lstm``. The number keeps the jobs
in Hydra's order (``1_…`` never starts ``10_…``'s name, the ``_`` follows the number); the overrides
say which setting each job ran without opening its ``.hydra/overrides.yaml``.

``hydra.job.config.override_dirname`` in conf/config.yaml leaves out the keys that do not change
what a job trains or that every job shares by construction (the seed, ``resume``, the device and
threads; ``experiment``, already in the name) and joins ``key-value`` pairs with ``+``: ``=`` and
``,`` in a folder's name would make ``hydra.run.dir=<folder>`` an override Hydra refuses unquoted
(a resumed job is started so, ``ferl.run.together``).

A resolver (``ferl.job_folder``), not the plain interpolation: a value may hold a ``/`` (a path),
which would nest folders, or brackets and quotes, which Hydra's grammar refuses unquoted; and many
overrides would pass a file name's 255 bytes. The name keeps ``[A-Za-z0-9._+-]`` (any other run of
characters becomes one ``_``) and at most ``MAX_OVERRIDES`` characters of overrides, the rest
replaced by a digest of them, so that two long settings still get two names.
"""

from __future__ import annotations

import hashlib
import re

from omegaconf import OmegaConf

MAX_OVERRIDES = 80  # characters of overrides in a folder's name: well below 255 with any experiment name
UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")
DIGEST = 8  # hex digits of sha1 that stand for the overrides cut off


def job_folder(number, name, overrides: str = "") -> str:
    """``<number>_<name>[+<overrides>]`` (module doc); ``overrides`` as ``override_dirname``."""
    tail = UNSAFE.sub("_", str(overrides or ""))
    if len(tail) > MAX_OVERRIDES:
        digest = hashlib.sha1(str(overrides).encode()).hexdigest()[:DIGEST]
        tail = f"{tail[: MAX_OVERRIDES - DIGEST - 1]}.{digest}"
    return f"{number}_{name}" + (f"+{tail}" if tail else "")


# conf/config.yaml and conf/experiment/none.yaml: hydra.sweep.subdir. Registered wherever a job's
# folder is named: train.py and every process that runs its jobs import ferl.config.hydra_glue, and
# Hydra's progress callback (ferl.run.progress) imports this module too.
OmegaConf.register_new_resolver("ferl.job_folder", job_folder, replace=True)
