"""What every benchmark prints and keeps: the torch rows beside the NumPy reference, and its entry
of benchmarks/results.json (one key per benchmark, so that running one keeps the others)."""

import json
import os
import platform
from pathlib import Path

import torch


def speedup_table(rows: list[dict], rate: str, reference: float, columns: list[tuple[str, str, str]]) -> None:
    """Add `speedup_vs_numpy` (rate ÷ reference) to every row and print the rows; `columns` are
    (header, row key, format spec) before the rate and speed-up columns."""
    columns = [
        *columns,
        (rate.replace("_per_s", "/s").replace("_", "-"), rate, ".0f"),
        ("× NumPy", "speedup_vs_numpy", ".2f"),
    ]
    widths = [max(8, len(header) + 1) for header, _, _ in columns]
    print(" ".join(f"{header:>{w}}" for (header, _, _), w in zip(columns, widths)))
    for row in rows:
        row["speedup_vs_numpy"] = row[rate] / reference
        print(" ".join(f"{row[key]:>{w}{spec}}" for (_, key, spec), w in zip(columns, widths)))


def save_results(path, key: str, device: str, **entry) -> None:
    """Merge this benchmark's entry, with the machine it ran on, into results.json under `key`."""
    path = Path(path)
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[key] = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "load_average_1min": os.getloadavg()[0],
        "device": device,
        **entry,
    }
    path.write_text(json.dumps(results, indent=2) + "\n")
