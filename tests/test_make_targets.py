"""The make targets' sweeps (Makefile): `make beyond-full`'s curves, read from a dry run
(`make -n`), and `make suites`' RecurrentPPO rows taken from the newest `make suites-reference`
(docs/beyond.md)."""

import json
import re
import subprocess
import sys

from conftest import ROOT
from synthetic_runs import make_toy_run

sys.path.insert(0, str(ROOT / "baselines"))
import reference
import side_by_side
import suites

from ferl.analysis import runner

ALL = "elman,lstm,gru,esn,transformer"


def dry_run(*args: str) -> str:
    """What `make -n` would run (the venv taken as set up: its stamps not remade)."""
    stamps = ["-o", ".venv/.installed", "-o", ".venv/.installed-suites", "-o", ".venv/.installed-baselines"]
    done = subprocess.run(["make", "-n", *stamps, *args], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def curves(text: str) -> dict[str, tuple[list[int], str]]:
    """Each curve of the beyond recipe: its corridors and its sweep's overrides (spaces collapsed)."""
    found = re.findall(r'for c in ([\d ]*); do.*?sweep (\w+) corridor_\$c "(.*?)"', text, re.S)
    return {name: ([int(c) for c in corridors.split()], " ".join(o.split())) for corridors, name, o in found}


def test_beyond_full_sweeps_the_full_memory_curves():
    text = dry_run("beyond-full")
    got = curves(text)
    assert got["passive_curve"][0] == [500, 200, 100, 50, 20, 10]
    assert f"predictor.joint.memory={ALL}" in got["passive_curve"][1]
    assert "trainer.n_episodes=10000" in got["passive_curve"][1]
    for active in ("memory_length", "exploration_curve"):  # without and with directed exploration
        assert got[active][0] == [50, 20, 10, 5], active
        assert f"predictor.joint.memory={ALL}" in got[active][1]
    assert "exploration=ez_greedy" in got["exploration_curve"][1]
    assert "exploration=" not in got["memory_length"][1]
    assert 'if [ -n "" ]' in text  # no sample-efficiency sweeps
    assert "ferl.run.sweepdir beyond-full" in text and "--resume" not in text
    assert "--lanes 2" in text  # every curve's jobs in one queue, REPRO_JOBS at a time


def test_beyond_keeps_its_defaults_and_the_command_line_wins():
    got = curves(dry_run("beyond"))
    assert got["passive_curve"][0] == [20, 10] and "predictor.joint.memory=lstm,gru " in got["passive_curve"][1]
    assert got["exploration_curve"][0] == [10, 5] and got["memory_length"][0] == [20, 10, 5, 3]
    text = dry_run("beyond-full", "BEYOND_PASSIVE_CORRIDORS=20 10", "RESUME=outputs/beyond_full/x")
    assert curves(text)["passive_curve"][0] == [20, 10]
    assert 'ferl.run.sweepdir beyond-full "outputs/beyond_full/x"' in text
    assert text.count("ferl.run.together --resume") == 1  # the recipe's one sweep() function


def test_suites_no_longer_runs_ppo_and_the_reference_does():
    assert "--reference" not in dry_run("suites") and "--reference" in dry_run("suites-reference")
    assert not any(name.startswith("ppo/") for name in suites.train_jobs())


def fake_reference(folder, started, commit, jobs):
    """A make suites-reference folder: its sweep.json and finished (toy) PPO job folders."""
    folder.mkdir(parents=True)
    (folder / "sweep.json").write_text(json.dumps({"target": "suites-reference", "started": started, "commit": commit}))
    for job in jobs:
        make_toy_run(folder / job)
    return folder


def run_suites(tmp_path, monkeypatch, references):
    """`baselines/suites.py OUT` with its jobs done already (none to run) and analyze.py left out."""
    out = tmp_path / "suites"
    make_toy_run(out / "repeat_previous_easy_ferl")
    monkeypatch.setattr(suites, "REFERENCES", references)
    monkeypatch.setattr(suites, "train_jobs", lambda: {})
    analyzed = []
    monkeypatch.setattr(
        side_by_side.subprocess, "run", lambda cmd, **k: analyzed.append(cmd) or subprocess.CompletedProcess(cmd, 0)
    )
    monkeypatch.setattr(sys, "argv", ["suites.py", str(out)])
    assert suites.main() == 0
    assert analyzed and analyzed[0][-1] == str(out)  # the analysis ran after the reference was copied in
    return out


def test_suites_reads_the_newest_reference_and_names_its_date_and_commit(tmp_path, monkeypatch, capsys):
    refs = tmp_path / "suites_reference"
    fake_reference(refs / "2026-12-01_10-00-00", "2026-12-01 10:00:00 UTC", "aaaa111", ["ppo_repeat_previous_easy"])
    newest = fake_reference(
        refs / "2026-12-05_10-00-00",
        "2026-12-05 10:00:00 UTC",
        "bbbb222",
        ["ppo_repeat_previous_easy", "ppo_count_recall_easy"],
    )
    unfinished = refs / "2026-12-06_10-00-00"  # newer, but its job has no summary yet: not a result
    unfinished.mkdir(parents=True)
    (unfinished / "sweep.json").write_text(
        json.dumps({"target": "suites-reference", "started": "2026-12-06 10:00:00 UTC"})
    )
    (unfinished / "ppo_repeat_previous_easy" / "checkpoints").mkdir(parents=True)

    out = run_suites(tmp_path, monkeypatch, refs)
    note = (out / "report_notes.md").read_text().strip()
    assert str(newest) in note and "2026-12-05 10:00:00 UTC" in note and "bbbb222" in note
    assert note in capsys.readouterr().out
    for job in ("ppo_repeat_previous_easy", "ppo_count_recall_easy"):
        assert (out / job / "summary.json").read_bytes() == (newest / job / "summary.json").read_bytes()
    runner.analyze_sweep(out)  # the report prints the line
    assert note in (out / "analysis" / "report.md").read_text()

    later = fake_reference(
        refs / "2026-12-07_10-00-00", "2026-12-07 10:00:00 UTC", "cccc333", ["ppo_repeat_previous_easy"]
    )
    assert reference.copy_newest(out, refs).count("cccc333") == 1  # a resumed sweep takes the newer one
    assert sorted(p.name for p in out.glob("ppo_*")) == ["ppo_repeat_previous_easy"]
    assert (later / "ppo_repeat_previous_easy").is_dir() and (newest / "ppo_count_recall_easy").is_dir()  # sources kept


def test_without_a_reference_one_line_says_so_and_there_is_no_ppo_row(tmp_path, monkeypatch):
    out = run_suites(tmp_path, monkeypatch, tmp_path / "none_here")
    note = (out / "report_notes.md").read_text().splitlines()
    assert len(note) == 1 and "no reference" in note[0] and "no RecurrentPPO row" in note[0]
    assert not list(out.glob("ppo_*"))


def test_the_reference_runs_ppo_alone_without_analysis_and_restarts_an_interrupted_ppo_job(
    tmp_path, monkeypatch, capsys
):
    out = tmp_path / "suites_reference" / "2026-12-06_10-00-00"
    make_toy_run(out / "ppo_repeat_previous_easy")  # finished: kept
    (out / "ppo_count_recall_easy" / "checkpoints").mkdir(parents=True)  # interrupted: PPO cannot resume
    ppos = {"ppo/repeat_previous_easy": ["--steps", "1"], "ppo/count_recall_easy": ["--steps", "1"]}
    monkeypatch.setattr(suites, "ppo_jobs", lambda: ppos)
    ran, analyzed = {}, []
    monkeypatch.setattr(side_by_side, "run_commands", lambda todo, *a, **k: ran.update(todo) or [])
    monkeypatch.setattr(side_by_side.subprocess, "run", lambda cmd, **k: analyzed.append(cmd))
    monkeypatch.setattr(sys, "argv", ["suites.py", str(out), "--reference"])
    assert suites.main() == 0
    assert list(ran) == ["ppo/count_recall_easy"] and "recurrent_ppo.py" in " ".join(ran["ppo/count_recall_easy"])
    assert not analyzed  # the reference has no report of its own
    assert (out / "ppo_count_recall_easy.interrupted" / "checkpoints").is_dir()  # kept, out of the way
    assert "1 jobs done (kept), 1 to do, 0 of them resumed" in capsys.readouterr().out
    monkeypatch.setattr(suites, "ppo_jobs", lambda: {})  # sb3-contrib missing: ppo_jobs said so
    assert suites.main() == 1
