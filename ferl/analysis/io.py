"""Reading records and writing the analysis' files: the helpers every analysis module shares.

Numbers go to CSV with six significant digits (``fmt``), lists to JSON (``write_json``), and text
into markdown table cells through ``cell``, which escapes the cell separator.
"""

from __future__ import annotations

import csv
import zipfile
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from ferl.run.jsonio import strict_dumps


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of a records file (docs/records.md), read at once, no pickles."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{Path(path).name} is damaged ({type(e).__name__}: {e})") from None


def fmt(x) -> str:
    """A number as CSV text: six significant digits (the records are float32 or coarser)."""
    return f"{x:.6g}"


def write_csv(path: Path, header: Sequence[str], rows: Iterable) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def write_numbers(path: Path, header: Sequence[str], index: np.ndarray, columns: np.ndarray) -> None:
    """A CSV table of integers ``index`` (n,) beside ``columns`` (n, k), the numbers as ``fmt``
    writes them: ``write_csv``'s file, formatted a row at a time (long curves have ~10⁵ numbers)."""
    line = ",".join(["%d"] + ["%.6g"] * columns.shape[1]) + "\r\n"  # csv.writer's line end
    with path.open("w", newline="") as f:
        csv.writer(f).writerow(header)
        f.writelines(line % (i, *row) for i, row in zip(np.asarray(index).tolist(), np.asarray(columns).tolist()))


def write_json(path: Path, value) -> None:
    path.write_text(strict_dumps(value, indent=2, ensure_ascii=False) + "\n")


def cell(text: str) -> str:
    """Text for one markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def table_lines(header: Sequence[str], rows: Iterable[Sequence]) -> list[str]:
    """A markdown table: the header row, the rule, one line per row (cells escaped)."""
    lines = [f"| {' | '.join(map(cell, header))} |", f"|{' --- |' * len(header)}"]
    return lines + [f"| {' | '.join(map(cell, row))} |" for row in rows]
