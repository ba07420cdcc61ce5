"""Each claim is judged on the job (experiment) that its section describes, named in the claim
(``Claim.experiment``), not on whichever job comes first in the sweep (docs/reproduction.md):
sweeps of synthetic runs in which two jobs could serve."""

from pathlib import Path

import pytest

import reproduction
from ferl.analysis import sweep as sw
from ferl.analysis.claims import evaluate
from ferl.analysis.report import RunOutcome
from ferl.runs import load_summary
from reproduction import ch3, ch4
from reproduction.floor import FloorRun
from reproduction.tmaze import TMazeRun
from synthetic_runs import load_run, make_floor_run, make_tmaze_run

REPO = Path(__file__).resolve().parents[1]
SECTION_353 = "§3.5.3"
INITIAL_SIGNAL = "§4.3.2, Fig. 4.14; §4.3.3"


def _job(run_dir: Path, claims, load) -> sw.Job:
    """A job of the sweep: the run's own claims judged on it, as its analysis does."""
    summary = load_summary(run_dir)
    results = evaluate(claims, load(load_run(run_dir)))
    outcome = RunOutcome(run_dir, summary["experiment"], summary["task"], "analyzed", results=results)
    return sw.Job(outcome, summary)


@pytest.fixture(scope="module")
def floor_jobs(tmp_path_factory) -> dict[str, sw.Job]:
    """ch3_floor and ch3_coding_cw, both without overrides: both judge every chapter-3 claim
    with reward, so the overrides cannot tell them apart."""
    root = tmp_path_factory.mktemp("floor_sweep")
    return {
        name: _job(make_floor_run(root / name, experiment=name, seed=k), ch3.CLAIMS, FloorRun.load)
        for k, name in enumerate(("ch3_floor", "ch3_coding_cw"))
    }


def _rows(jobs: list[sw.Job]) -> list[sw.ReportRow]:
    return sw.reproduction_rows(jobs, [], reproduction.CLAIM_ORDER)


@pytest.mark.parametrize("order", [("ch3_floor", "ch3_coding_cw"), ("ch3_coding_cw", "ch3_floor")])
def test_section_3_5_3_is_judged_on_its_coding_job_in_either_sweep_order(floor_jobs, order):
    rows = _rows([floor_jobs[name] for name in order])
    judged = {row.result.claim.source: row for row in rows}
    coding = [row for source, row in judged.items() if source.startswith(SECTION_353)]
    floor = [row for source, row in judged.items() if source.startswith(("§3.5.1", "§3.5.2"))]
    assert len(coding) >= 3 and len(floor) >= 3  # both kinds were judged by both jobs
    for row in coding:
        assert row.job is not None and row.job.experiment == "ch3_coding_cw", row.result.claim.source
        assert [j.experiment for j, _ in row.others] == ["ch3_floor"]
    for row in floor:
        assert row.job is not None and row.job.experiment == "ch3_floor", row.result.claim.source
        assert [j.experiment for j, _ in row.others] == ["ch3_coding_cw"]
    table = "\n".join(sw.claims_rows_markdown(rows, Path("."), links=False))
    assert "not the section's" not in table  # every claim was judged on its own job


def test_without_the_sections_job_the_claim_says_on_which_job_it_was_judged(floor_jobs):
    rows = _rows([floor_jobs["ch3_floor"]])
    coding = [row for row in rows if row.result.claim.source.startswith(SECTION_353)]
    assert coding and all(row.job is floor_jobs["ch3_floor"] for row in coding)
    cells = sw.claims_rows_markdown(coding, Path("."), links=False)[2:]
    assert all("`ch3_floor` (not the section's `ch3_coding_cw`" in cell for cell in cells)


def test_the_named_job_wins_over_one_with_fewer_overrides(floor_jobs, tmp_path):
    """A job of the section's experiment with an override still judges the claim before another
    experiment's job that runs as its YAML does."""
    varied = make_floor_run(tmp_path / "coding_40", experiment="ch3_coding_cw", seed=5)
    (varied / ".hydra" / "overrides.yaml").write_text("- experiment=ch3_coding_cw\n- actor.n_hidden=40\n")
    job = _job(varied, ch3.CLAIMS, FloorRun.load)
    rows = _rows([floor_jobs["ch3_floor"], job])
    row = next(row for row in rows if row.result.claim.source == ch3.SAME_ACTION_PAIRS_SOURCE)
    assert row.job is job and job.overrides == ("actor.n_hidden=40",)


def test_the_initial_signal_of_4_3_2_is_judged_on_the_matching_maze_not_the_digit_one(tmp_path):
    names = ("table4_2_digit", "table4_1_matching")  # the digit maze first, as the old order had it
    jobs = [_job(make_tmaze_run(tmp_path / n, experiment=n), ch4.CLAIMS, TMazeRun.load) for n in names]
    row = next(row for row in _rows(jobs) if row.result.claim.source == INITIAL_SIGNAL)
    assert row.job is jobs[1] and [j.experiment for j, _ in row.others] == ["table4_2_digit"]


def test_every_named_job_is_an_experiment_of_conf():
    experiments = {p.stem for p in (REPO / "conf" / "experiment").glob("*.yaml")}
    named = {claim.experiment for claim in reproduction.CLAIM_ORDER if claim.experiment}
    assert named and named <= experiments, named - experiments
    sweep_only = {claim.source for claim in reproduction.CLAIM_ORDER if not claim.experiment}
    assert sweep_only == {"§3.5.3, Fig. 3.13"}  # judged across jobs: no job of its own


@pytest.mark.parametrize(
    "source, job",
    [
        ("§3.5.1, Fig. 3.4, fn. 4", "ch3_floor"),
        ("§3.5.3, Fig. 3.10(a)–(c)", "ch3_coding_cw"),
        ("§3.5.3, Figs. 3.11(a)/(b), 3.13", "ch3_coding_cw"),
        ("§3.5.3 fn. 6, Figs. 3.10–3.11", "ch3_coding_cw"),
        ("§3.5.3, Fig. 3.11(c)", "ch3_coding_noreward"),
        (INITIAL_SIGNAL, "table4_1_matching"),
        ("§4.3.3, Fig. 4.21", "table4_2_digit"),
        ("§5.3.2, Figs. 5.15(a)/5.16(a)", "table5_1_pixel"),
    ],
)
def test_claims_name_their_sections_job(source, job):
    assert {c.experiment for c in reproduction.CLAIM_ORDER if c.source == source} == {job}
