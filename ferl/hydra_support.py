"""Hydra glue of train.py: the joblib launcher's job count, the metric that main() returns to a
sweeper, the final summary table, and the config schemas in Hydra's ConfigStore.

Imported by train.py; joblib's worker processes import it too (main() refers to it), so the
resolver, the schemas and the warning filter below are in place wherever a job's config is composed.
"""
import math
import os
import warnings

from omegaconf import OmegaConf

from ferl.schema import SCHEMA_SUFFIX, register_schemas
from ferl.validate import ConfigError

# conf/hydra/launcher/{joblib,submitit_slurm}.yaml set our defaults on top of the plugins' configs
# of the same name, which Hydra merges with a deprecation notice meant for configs one owns.
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/\w+' is validated against ConfigStore schema")


def jobs_per_machine(cpu_threads) -> int:
    """Parallel jobs that fit this machine: cores // cpu_threads (at least 1), so that
    cpu_threads × n_jobs never exceeds the cores this process may run on."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // max(1, int(cpu_threads)))


# The config groups' schemas (ferl/schema.py), for a worker that composes its job's config anew.
register_schemas()

# conf/hydra/launcher/joblib.yaml: n_jobs: ${ferl.jobs_per_machine:${cpu_threads}}
OmegaConf.register_new_resolver("ferl.jobs_per_machine", jobs_per_machine, replace=True)


def condense_hydra_error(report: str) -> str:
    """Hydra's multi-line composition error as one line that starts with the full key when the
    error names one (a schema's type or enum check, ferl/schema.py; the schemas themselves are
    left out of the options a group offers):
    ``env.noise: Value 'abc' of type 'str' could not be converted to Float | Error merging override env.noise=abc``."""
    lines = [ln.strip() for ln in report.split("Config search path:")[0].splitlines()
             if ln.strip() and "HYDRA_FULL_ERROR" not in ln and not ln.strip().endswith(SCHEMA_SUFFIX)]
    key = next((ln.partition(":")[2].strip() for ln in lines if ln.startswith("full_key:")), "")
    rest = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "reference_type="))]
    if key:  # the cause first, then which override or file it came from
        rest = [ln for ln in rest if not ln.startswith(("Error merging", "In '"))] + \
               [ln for ln in rest if ln.startswith(("Error merging", "In '"))]
    return (f"{key}: " if key else "") + " | ".join(rest)


def flat_metrics(metrics: dict) -> dict[str, list]:
    """summary.json metrics as name → per-run values; a metric per test level (a mapping
    level → values, e.g. greedy_accuracy) becomes one entry per level, ``greedy_accuracy/0.125``."""
    flat = {}
    for name, values in metrics.items():
        if isinstance(values, dict):
            flat.update({f"{name}/{level}": v for level, v in values.items()})
        else:
            flat[name] = values
    return flat


def mean_sd(values: list) -> tuple[float, float, int]:
    """Mean and sample s.d. over runs, skipping null (unscorable) runs; NaN when none is left."""
    x = [float(v) for v in values if v is not None]
    if not x:
        return math.nan, math.nan, 0
    mean = sum(x) / len(x)
    sd = math.sqrt(sum((v - mean) ** 2 for v in x) / (len(x) - 1)) if len(x) > 1 else 0.0
    return mean, sd, len(x)


def optimized_value(summary: dict, metric: str | None) -> float | None:
    """What main() returns to a sweeper: the mean over runs of summary.json's ``metric``
    (None without one)."""
    if metric is None:
        return None
    flat = flat_metrics(summary["metrics"])
    if metric not in flat:
        raise ConfigError(f"optimized_metric={metric!r} is not allowed: this run's summary.json "
                          f"metrics are {', '.join(flat)}")
    return mean_sd(flat[metric])[0]


def summary_table(summary: dict) -> str:
    """The run's metrics, mean ± s.d. over runs, one line each; a metric's ``<name>_before``
    twin (the same test before training) goes into a second column."""
    flat = flat_metrics(summary["metrics"])
    before = {}
    for name in list(flat):
        head, _, level = name.partition("/")
        if head.endswith("_before") and (twin := head[: -len("_before")] + (f"/{level}" if level else "")) in flat:
            before[twin] = flat.pop(name)

    def cell(values):
        mean, sd, n = mean_sd(values)
        return "n/a" if n == 0 else f"{mean:.3f} ± {sd:.3f}"

    n_runs = len(summary["seeds"])
    rows = [(f"metric ({n_runs} run{'s' if n_runs != 1 else ''})", "mean ± s.d.", "before training" if before else "")]
    rows += [(name, cell(values), cell(before[name]) if name in before else "") for name, values in flat.items()]
    w0, w1 = (max(len(r[i]) for r in rows) for i in (0, 1))
    lines = [f"  {a:<{w0}}  {b:<{w1}}  {c}".rstrip() for a, b, c in rows]
    optimal = ", ".join(f"{k} {v:.4g}" for k, v in summary.get("optimal", {}).items())
    return "\n".join(lines + ([f"  optimal: {optimal}"] if optimal else []))
