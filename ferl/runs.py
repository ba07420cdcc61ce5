"""Read run directories back into pandas: configs, summary.json metrics and TensorBoard scalars.

    from ferl import runs
    r = runs.load("outputs/multirun/2026-01-01_12-00-00")   # a run, or any folder of runs
    r.configs    # one row per run: run, run_dir, overrides, the flattened resolved config
    r.metrics    # one row per run × seed: run, run_dir, experiment, task, seed, every metric
    r.scalars    # long: run, run_dir, tag, step, value, wall_time (TensorBoard's own reader)
    r.table()    # metrics joined with the config: one row per run × seed

A run directory is one holding ``summary.json`` (docs/records.md); ``run`` is its path relative to
the folder given ("." for the run itself), ``run_dir`` its absolute path. Nested config keys are
flattened with dots as in TensorBoard's HParams tab (``actor.n_hidden``), per-level metrics as
``ferl.stats.flat_metrics`` names them (``greedy_accuracy/0.125``). ``python -m ferl.runs DIR``
prints each run's metrics (mean ± s.d. over its runs, ``ferl.stats``) and the scalar tags.
"""

import argparse
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import pandas as pd
from omegaconf import OmegaConf

from ferl import stats

SUMMARY = "summary.json"


def find_runs(path) -> list[Path]:
    """The run directories at or below ``path`` (folders holding summary.json), sorted."""
    path = Path(path)
    if (path / SUMMARY).is_file():
        return [path]
    return sorted(p.parent for p in path.rglob(SUMMARY))


def _flatten(node, prefix: str = "") -> dict:
    """A nested config as ``{"actor.n_hidden": 20}``."""
    flat = {}
    for key, value in node.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = _hashable(value)
    return flat


def _hashable(value):
    """Lists as tuples, so that config columns can be grouped on."""
    return tuple(_hashable(v) for v in value) if isinstance(value, list) else value


def load_config(run_dir) -> dict:
    """The run's resolved config (``.hydra/config.yaml``), flattened: ``{"actor.n_hidden": 20}``,
    lists as tuples. Hydra saves it unresolved; ``${hydra:…}`` (e.g. ``name``) is read from
    ``.hydra/hydra.yaml``, and an entry that cannot be resolved keeps its text."""
    hydra_dir = Path(run_dir) / ".hydra"
    text = re.sub(r"\$\{hydra:", "${hydra.", (hydra_dir / "config.yaml").read_text())
    cfg = OmegaConf.create(text)
    keys = list(cfg.keys())
    if (hydra_dir / "hydra.yaml").is_file():
        OmegaConf.set_struct(cfg, False)
        cfg.hydra = OmegaConf.load(hydra_dir / "hydra.yaml").hydra
    resolved = {}
    for key in keys:
        try:
            node = cfg[key]
            resolved[key] = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        except Exception:  # noqa: BLE001 — an interpolation of something not saved with the run
            resolved[key] = cast(dict, OmegaConf.to_container(cfg, resolve=False))[key]
    return _flatten(resolved)


def load_overrides(run_dir) -> str:
    """The command-line overrides of the run (``.hydra/overrides.yaml``), space-separated."""
    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    return " ".join(OmegaConf.load(path)) if path.is_file() else ""


def load_summary(run_dir) -> dict:
    """A run's summary.json; ValueError naming the file when it is not a JSON object."""
    try:
        summary = json.loads((Path(run_dir) / SUMMARY).read_text())
    except ValueError as e:
        raise ValueError(f"{SUMMARY} is damaged ({e})") from None
    if not isinstance(summary, dict):
        raise ValueError(f"{SUMMARY} is damaged (a JSON {type(summary).__name__}, not an object)")
    return summary


def _names(run_dir: Path, root: Path) -> dict:
    return {"run": run_dir.relative_to(root).as_posix() if run_dir != root else ".", "run_dir": str(run_dir.resolve())}


def configs(path) -> pd.DataFrame:
    """One row per run: run, run_dir, overrides and the flattened resolved config."""
    root = Path(path)
    rows = []
    for run_dir in find_runs(root):
        row = {**_names(run_dir, root), "overrides": load_overrides(run_dir)}
        if (run_dir / ".hydra" / "config.yaml").is_file():
            row.update(load_config(run_dir))
        rows.append(row)
    return pd.DataFrame(rows)


def metrics(path) -> pd.DataFrame:
    """One row per run × seed: run, run_dir, experiment, task, seed, every summary.json metric
    (a per-level metric as ``<name>/<level>``; null → NaN), wall_time_s and agent_steps_per_s."""
    root = Path(path)
    rows = []
    for run_dir in find_runs(root):
        summary = load_summary(run_dir)
        per_seed = stats.flat_metrics(summary["metrics"])
        for i, seed in enumerate(summary["seeds"]):
            rows.append(
                {
                    **_names(run_dir, root),
                    "experiment": summary["experiment"],
                    "task": summary["task"],
                    "seed": seed,
                    **{name: _number(values[i]) for name, values in per_seed.items()},
                    "wall_time_s": summary["wall_time_s"],
                    "agent_steps_per_s": summary["agent_steps_per_s"],
                }
            )
    return pd.DataFrame(rows)


def _number(value):
    return float("nan") if value is None else value


SCALAR_COLUMNS = ["run", "run_dir", "tag", "step", "value", "wall_time"]


def scalars(path, tags=None) -> pd.DataFrame:
    """Every TensorBoard scalar of the runs' ``tb/`` logs, long: run, run_dir, tag, step, value,
    wall_time; ``tags`` (a collection or a regular expression) keeps only those. Read with
    TensorBoard's EventAccumulator, no downsampling; a step logged twice (a resumed run repeats
    the steps after its last checkpoint) keeps its last value."""
    root = Path(path)
    wanted = re.compile(tags) if isinstance(tags, str) else (set(tags) if tags is not None else None)
    frames = []
    for run_dir in find_runs(root):
        if not (run_dir / "tb").is_dir():
            continue
        # imported here: the reader brings TensorBoard (and torch) in, which only scalars need
        from tensorboard.backend.event_processing.event_accumulator import SCALARS, EventAccumulator

        events = EventAccumulator(str(run_dir / "tb"), size_guidance={SCALARS: 0})
        events.Reload()
        for tag in events.Tags()[SCALARS]:
            if wanted is not None and not (wanted.search(tag) if isinstance(wanted, re.Pattern) else tag in wanted):
                continue
            points = events.Scalars(tag)
            frames.append(
                pd.DataFrame(
                    {
                        **_names(run_dir, root),
                        "tag": tag,
                        "step": [p.step for p in points],
                        "value": [p.value for p in points],
                        "wall_time": [p.wall_time for p in points],
                    }
                )
            )
    if not frames:
        return pd.DataFrame(columns=SCALAR_COLUMNS)
    out = pd.concat(frames, ignore_index=True)
    out = out.sort_values(["run", "tag", "wall_time"], kind="stable")
    out = out.drop_duplicates(["run", "tag", "step"], keep="last").sort_values(["run", "tag", "step"], kind="stable")
    return out[SCALAR_COLUMNS].reset_index(drop=True)


@dataclass
class Runs:
    """A run or sweep read back as DataFrames: configs, metrics (a row per run × seed), TensorBoard
    scalars (docs/usage.md, "TensorBoard and reading runs back")."""

    configs: pd.DataFrame
    metrics: pd.DataFrame
    scalars: pd.DataFrame

    def table(self) -> pd.DataFrame:
        """Metrics joined with each run's config: one row per run × seed."""
        config = self.configs.drop(
            columns=[c for c in ("experiment", "task") if c in self.configs and c in self.metrics]
        )
        return self.metrics.merge(config, on=["run", "run_dir"], how="left", suffixes=("", "_config"))


def load(path, tags=None) -> Runs:
    """Configs, metrics and scalars of the run or runs at ``path`` (FileNotFoundError if none)."""
    if not find_runs(path):
        raise FileNotFoundError(f"no run directories (folders with {SUMMARY}) at or below {path}")
    return Runs(configs(path), metrics(path), scalars(path, tags))


JOB_COLUMNS = ["run_dir", "seed", "experiment", "task", "wall_time_s", "agent_steps_per_s"]


def summary_table(metrics_frame: pd.DataFrame) -> pd.DataFrame:
    """One row per run directory × summary.json metric: mean ± s.d. over its runs and their
    number (``ferl.stats``; runs without a value left out). The job's wall time and speed are
    one number per job, not per run: they are left out."""
    values = metrics_frame.drop(columns=JOB_COLUMNS)
    rows = []
    for run, group in values.groupby("run", sort=False):
        for metric in group.columns.drop("run"):
            mean, sd, n = stats.mean_sd(group[metric].to_numpy())
            rows.append({"run": run, "metric": metric, "mean": mean, "sd": sd, "n_runs": n})
    return pd.DataFrame(rows, columns=["run", "metric", "mean", "sd", "n_runs"])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description="Print the runs at DIR: metrics (mean ± s.d. over seeds) and scalar tags."
    )
    parser.add_argument("path", help="a run directory or any folder of runs")
    args = parser.parse_args(argv)
    try:
        r = load(args.path)
    except FileNotFoundError as e:
        raise SystemExit(f"ferl.runs: error: {e}") from None
    print(summary_table(r.metrics).to_string())
    tags = (
        r.scalars.groupby("tag")["step"].agg(["count", "max"]).rename(columns={"count": "points", "max": "last_step"})
    )
    print(f"\nscalar tags ({len(tags)}):\n{tags.to_string()}")


if __name__ == "__main__":
    main()
