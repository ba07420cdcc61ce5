"""A run's analysis is kept while its records and the code are unchanged (ferl/analysis/cache.py):
analysed again, an unchanged run is not redrawn, a changed one is, and the sweep's report reads the
kept runs exactly as it read them when they were drawn."""

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

import reproduction  # noqa: F401 — registers the dissertation's analyses, as analyze.py does
from ferl.analysis import cache, runner
from ferl.analysis.dispatch import REGISTRY
from synthetic_runs import make_floor_run, make_tmaze_run


def tree(folder: Path) -> dict[str, tuple[str, int]]:
    """Content hash and mtime of every file below ``folder``."""
    return {
        str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def report_without_wall_time(sweep: Path) -> list[str]:
    lines = (sweep / "analysis" / "report.md").read_text().splitlines()
    return [line for line in lines if "wall time" not in line and "wall_time" not in line]


@pytest.fixture
def sweep(tmp_path):
    root = tmp_path / "sweep"
    make_floor_run(root / "0", seed=1)
    make_tmaze_run(root / "1")
    return root


def test_every_registered_claim_is_found_again_by_its_source_and_text():
    """A kept analysis finds its judged claims by (source, text): each pair names one claim."""
    keys = [(c.source, c.text) for c in REGISTRY.all_claims]
    assert keys and len(keys) == len(set(keys))


def test_an_unchanged_run_is_kept_and_a_changed_one_analysed_again(sweep, capsys):
    assert runner.main([sweep]) == 0
    first = {run: tree(sweep / run / "analysis") for run in ("0", "1")}
    first_tb = tree(sweep / "0" / "tb" / "analysis")
    report = report_without_wall_time(sweep)
    capsys.readouterr()

    assert runner.main([sweep]) == 0  # nothing changed: both kept, file for file
    said = capsys.readouterr().out
    assert said.count("unchanged since its last analysis, kept") == 2, said
    assert {run: tree(sweep / run / "analysis") for run in ("0", "1")} == first
    assert tree(sweep / "0" / "tb" / "analysis") == first_tb
    assert report_without_wall_time(sweep) == report  # the kept runs' claims read as when drawn

    summary = sweep / "1" / "summary.json"  # one run's records change: it alone is drawn again
    data = json.loads(summary.read_text())
    data["wall_time_s"] = float(data.get("wall_time_s", 0)) + 1.0
    summary.write_text(json.dumps(data))
    assert runner.main([sweep]) == 0
    said = capsys.readouterr().out
    assert f"{sweep / '0'}: unchanged since its last analysis, kept" in said
    assert f"{sweep / '1'}: unchanged" not in said
    assert tree(sweep / "0" / "analysis") == first["0"]
    assert tree(sweep / "1" / "analysis") != first["1"]


def test_force_and_a_touched_folder_analyse_again(sweep, capsys):
    run = sweep / "0"
    assert runner.main([run]) == 0
    kept = tree(run / "analysis")
    assert runner.main([run], force=True) == 0
    assert "kept" not in capsys.readouterr().out
    redrawn = tree(run / "analysis")
    assert redrawn.keys() == kept.keys()
    assert any(redrawn[name][1] != kept[name][1] for name in kept)  # written anew

    (run / "analysis" / "learning_curves.png").unlink()  # a file gone: drawn again
    assert runner.main([run]) == 0
    assert "kept" not in capsys.readouterr().out
    assert (run / "analysis" / "learning_curves.png").is_file()

    (run / "analysis" / cache.DIGEST).unlink()  # an analysis cut short writes no digest
    assert runner.main([run]) == 0
    assert "kept" not in capsys.readouterr().out


def test_the_digest_follows_every_input(sweep):
    """summary.json, each records file and the code each change the digest; nothing else does."""
    run = sweep / "0"
    digest = cache.inputs_digest(run, REGISTRY)
    (run / "notes.txt").write_text("a file analysis does not read")
    assert cache.inputs_digest(run, REGISTRY) == digest
    records = sorted((run / "records").glob("*.npz"))
    assert records
    for path in records:
        saved = path.read_bytes()
        path.write_bytes(saved + b"\0")
        assert cache.inputs_digest(run, REGISTRY) != digest, path.name
        path.write_bytes(saved)
    assert cache.inputs_digest(run, REGISTRY) == digest
    other_code = dataclasses.replace(REGISTRY, modules=[*REGISTRY.modules, "json"])  # another plug-in's code
    assert cache.inputs_digest(run, other_code) != digest
    fewer_claims = dataclasses.replace(REGISTRY, chapters=REGISTRY.chapters[1:])  # another registry
    assert cache.inputs_digest(run, fewer_claims) != digest


def test_a_kept_outcome_equals_the_drawn_one(sweep):
    run = sweep / "1"
    drawn = runner.analyze_run(run)
    kept = runner.analyze_run(run)
    assert kept is not drawn
    assert (kept.experiment, kept.task, kept.status, kept.verdicts, kept.figures) == (
        drawn.experiment,
        drawn.task,
        drawn.status,
        drawn.verdicts,
        drawn.figures,
    )
    assert [(r.claim, r.measured.text, r.verdict) for r in kept.results] == [
        (r.claim, r.measured.text, r.verdict) for r in drawn.results
    ]
    assert drawn.results and np.all([r.claim in REGISTRY.all_claims for r in kept.results])


def test_a_run_never_analysed_is_not_hashed_to_be_kept(sweep, monkeypatch):
    """Without a digest file there is nothing to keep: the records are not read for it (the
    sweep's parent process asks this of every run before its pool starts)."""

    def hashed(*_):
        raise AssertionError("records hashed for a run without an analysis")

    monkeypatch.setattr(cache, "inputs_digest", hashed)
    assert runner._kept(sweep / "0") is None
