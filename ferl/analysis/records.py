"""A run directory as the analysis sees it: what produced it (``records/run.json``), its
``summary.json`` and its records (docs/records.md).

Every decision of the analysis is taken on the facts of ``records/run.json`` — the task, the
environment's kind and observations, the trainer's phases and parameters, the preprocessor and
each predictor's kind — never on experiment names or config ``_target_``s. A predictor's *role*
follows from what it predicts:

* ``joint``: the observation and the reward bits together (Algorithm 1, Eq. 4.8);
* ``observation``: the observation only (Algorithm 2's observation predictor, Eq. 5.1);
* ``reward``: a scalar reward only (Algorithm 2's reward predictor, Eq. 5.2).

Any other predictor has no role: it gets the generic figures and no chapter's claims.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ferl.analysis.io import load_npz
from ferl.runs import load_summary
from ferl.stats import FINAL_WINDOW

MANIFEST = Path("records") / "run.json"
JOINT, OBSERVATION, REWARD = "joint", "observation", "reward"


def predictor_role(facts: dict) -> str | None:
    """The dissertation's role of a predictor from its recorded facts (module doc)."""
    observation, reward = bool(facts.get("predicts_observation")), facts.get("reward_output")
    if observation and reward == "bits":
        return JOINT
    if observation and reward == "none":
        return OBSERVATION
    if not observation and reward == "linear":
        return REWARD
    return None


@dataclass(frozen=True)
class Manifest:
    """``records/run.json`` (docs/records.md): what produced the run."""

    task: str
    experiment: str
    trainer: dict
    env: dict
    preprocessor: dict | None
    predictors: dict[str, dict]
    actor: dict
    exploration: dict = field(default_factory=dict)  # a directed exploration's facts; {} for none

    @classmethod
    def load(cls, run_dir: Path) -> Manifest | None:
        """The run's manifest; None for a run without one (written before it existed)."""
        path = Path(run_dir) / MANIFEST
        if not path.is_file():
            return None
        try:
            facts = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(f"{MANIFEST} is damaged ({e})") from None
        if not isinstance(facts, dict):
            raise ValueError(f"{MANIFEST} is damaged (a JSON {type(facts).__name__}, not an object)")
        return cls(
            str(facts.get("task")),
            str(facts.get("experiment")),
            facts.get("trainer") or {},
            facts.get("env") or {},
            facts.get("preprocessor"),
            facts.get("predictors") or {},
            facts.get("actor") or {},
            facts.get("exploration") or {},
        )

    @property
    def env_kind(self) -> str:
        return str(self.env.get("kind"))

    @property
    def episodic(self) -> bool:
        return bool(self.env.get("episodic"))

    @property
    def image_observations(self) -> bool:
        """Observations are images (the digit mazes of §4.3.3 and §5.3.2, the digit floor)."""
        return self.env.get("observation") == "image"

    @cached_property
    def roles(self) -> dict[str, str | None]:
        """Predictor name → its role (module doc), in the order of run.json."""
        return {name: predictor_role(facts) for name, facts in self.predictors.items()}


def recorded_window(episodes: dict | None, manifest: Manifest) -> int:
    """The run's ``trainer.final_window``: the episodes behind its final metrics, as recorded in
    `episodes.npz` (or, by runs before it was, in run.json); ``ferl.stats.FINAL_WINDOW`` (200) for
    a run that recorded neither."""
    value = (episodes or {}).get("final_window", manifest.trainer.get("final_window"))
    return FINAL_WINDOW if value is None else int(value)


@dataclass(frozen=True)
class PredictorErrors:
    """One predictor's records of ``predictor.npz``: Eq. (4.7)–(4.8) errors per epoch, step-length
    T and step t (Figs. 4.5/4.10, 5.2/5.17)."""

    name: str
    role: str | None
    lengths: np.ndarray  # (nT,) step-lengths T with data
    epochs: np.ndarray  # (E,) epochs at which the errors were measured, 0 = before training
    train: np.ndarray  # (R, E, nT, Tmax+1), NaN for t > T
    test: np.ndarray
    trained_max: int  # longest trained step-length

    @property
    def n_runs(self) -> int:
        return self.train.shape[0]

    def errors(self, split: str) -> np.ndarray:
        return self.train if split == "train" else self.test


@dataclass
class Run:
    """One run directory: its manifest, summary and records, each records file read once."""

    run_dir: Path
    summary: dict
    manifest: Manifest
    files: dict = field(default_factory=dict, init=False, repr=False)  # records read so far

    @classmethod
    def load(cls, run_dir: Path, manifest: Manifest) -> Run:
        return cls(Path(run_dir), load_summary(run_dir), manifest)

    def records(self, name: str) -> dict[str, np.ndarray] | None:
        """``records/<name>.npz`` as arrays; None where the run has no such file."""
        if name not in self.files:
            path = self.run_dir / "records" / f"{name}.npz"
            self.files[name] = self.checked(path, load_npz(path)) if path.is_file() else None
        return self.files[name]

    def probes(self) -> dict[str, np.ndarray] | None:
        """``records/probe.npz``, the activations at the environment's probe states (docs/records.md),
        or ``records/junction.npz``, its name in runs recorded before it was neutral."""
        found = self.records("probe")
        return found if found is not None else self.records("junction")

    def required(self, name: str) -> dict[str, np.ndarray]:
        """``records/<name>.npz``, which this analysis cannot do without: FileNotFoundError naming
        the file where the run has none (removed, or the run was cut before it wrote it)."""
        found = self.records(name)
        if found is None:
            raise FileNotFoundError(f"records/{name}.npz is missing: the analysis of this run needs it")
        return found

    def checked(self, path: Path, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``arrays`` without ``per_run``, once each array it names has summary.json's run count
        as its first axis (files written before ``per_run`` existed go unchecked)."""
        runs = len(self.summary.get("seeds", ()))
        shapes = {k: arrays[k].shape if k in arrays else "missing" for k in arrays.pop("per_run", ())}
        wrong = [f"{k} {shape}" for k, shape in shapes.items() if shape == "missing" or shape[:1] != (runs,)]
        if wrong:
            raise ValueError(
                f"{path.name} does not belong to this run: summary.json has {runs} runs, but {', '.join(wrong)}"
            )
        return arrays

    @property
    def experiment(self) -> str:
        return str(self.summary.get("experiment", self.manifest.experiment))

    @property
    def task(self) -> str:
        return str(self.summary.get("task", self.manifest.task))

    @property
    def l_training(self) -> int | None:
        """L_training of Algorithms 1–2: the predictors train on T_min … T_min + L_training − 1."""
        value = self.manifest.trainer.get("l_training")
        return None if value is None else int(value)

    @cached_property
    def final_window(self) -> int:
        """The episodes behind the run's final metrics, which its episodic moving averages use too
        (``recorded_window``)."""
        return recorded_window(self.records("episodes"), self.manifest)

    @cached_property
    def predictors(self) -> list[PredictorErrors]:
        """The predictors named in run.json that have records, in its order."""
        found = self.records("predictor") or {}
        out = []
        for name, role in self.manifest.roles.items():
            if f"{name}_error_train" not in found:
                continue
            lengths = found[f"{name}_lengths"].astype(np.int64)
            # Without L_training every recorded length counts as trained.
            trained_max = int(lengths.max()) if self.l_training is None else int(lengths.min()) + self.l_training - 1
            out.append(
                PredictorErrors(
                    name,
                    role,
                    lengths,
                    found[f"{name}_epochs"].astype(np.int64),
                    found[f"{name}_error_train"].astype(np.float64),
                    found[f"{name}_error_test"].astype(np.float64),
                    trained_max,
                )
            )
        return out

    def metric(self, name: str) -> np.ndarray:
        """A summary.json metric as float per run (null → NaN)."""
        return np.asarray([np.nan if v is None else v for v in self.summary["metrics"][name]], dtype=np.float64)
