"""``analyze.py``'s work: analyze run and sweep directories, write their ``analysis/`` folders.

A directory holding ``summary.json`` is a run: its ``analysis/`` folder is rebuilt (PNG figures,
CSV/JSON data, ``report.md``) and the figures are logged to its TensorBoard under
``tb/analysis/`` (replaced on every analysis), unless nothing it is made from changed since its
last analysis (``ferl.analysis.cache``: then it is kept; ``force`` rebuilds it). What a run gets is decided on what it recorded
(``records/run.json``) and on what plug-ins registered (``ferl.analysis.dispatch.REGISTRY``); a run
without run.json is skipped with a message. Any other directory is a sweep: every run below it
is analyzed, and ``DIR/analysis/`` gets the sweep's aggregate tables and claims report
(``ferl.analysis.sweep``) and the registered sweep sections, its figures also logged to
``DIR/analysis/tb/``.
"""

from __future__ import annotations

import contextlib
import gc
import io
import os
import shutil
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ferl import runs
from ferl.analysis import cache, generic, members
from ferl.analysis import sweep as sw
from ferl.analysis.claims import VERDICTS, ClaimResult, Numbering, evaluate
from ferl.analysis.dispatch import REGISTRY, import_plugins
from ferl.analysis.io import write_json
from ferl.analysis.records import MANIFEST, Manifest, Run
from ferl.analysis.report import RunAnalysis, RunOutcome, jobs_table, write_run_report
from ferl.run.sweepdir import NOTES

PROG = "analyze.py"
POOL_MIN_RUNS = 4  # a pool's workers take a few seconds to start: fewer runs are analyzed in turn


PNG_COMPRESS_LEVEL = 1  # zlib level: a third less encoding time than the default 6, files ~9 % larger


def png_bytes(rgba: np.ndarray) -> bytes:
    """One figure's pixels (H, W, 4) as PNG bytes, encoded once for both the file and TensorBoard."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(rgba).save(buffer, format="png", compress_level=PNG_COMPRESS_LEVEL)
    return buffer.getvalue()


def publish_figures(figures: dict, out: Path, tb_dir: Path) -> None:
    """Save every figure as PNG and log it to a fresh TensorBoard log ``tb_dir`` under
    ``analysis/<name>``.

    Each figure is rendered once by the Agg canvas and encoded once: the PNG file's bytes are the
    TensorBoard image's (an image summary holds encoded PNG, what ``SummaryWriter.add_image``
    would encode again). The event file is written with tensorboard's own writer, so an
    analysis never imports torch.
    """
    shutil.rmtree(tb_dir, ignore_errors=True)
    if not figures:
        return
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.compat.proto.summary_pb2 import Summary
    from tensorboard.summary.writer.event_file_writer import EventFileWriter

    writer = EventFileWriter(str(tb_dir))
    try:
        for name, (fig, _) in figures.items():
            canvas = FigureCanvasAgg(fig)
            canvas.draw()
            rgba = np.asarray(canvas.buffer_rgba())
            png = png_bytes(rgba)
            (out / f"{name}.png").write_bytes(png)
            height, width, channels = rgba.shape
            image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=png)
            summary = Summary(value=[Summary.Value(tag=f"analysis/{name}", image=image)])
            writer.add_event(Event(wall_time=time.time(), step=0, summary=summary))
    finally:
        writer.close()


def _claim_json(r: ClaimResult, **where) -> dict:
    return {
        "claim": r.claim.text,
        "source": r.claim.source,
        "measured": r.measured.text,
        "criterion": r.claim.criterion,
        "verdict": r.verdict,
        **where,
    }


def _fresh(out: Path) -> Path:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    return out


def run_analysis(run: Run, out: Path) -> RunAnalysis:
    """The generic analysis of any run, its environment's figures and, where a registered chapter
    applies, that chapter's figure numbers and claims (``ferl.analysis.dispatch``)."""
    chapter = REGISTRY.chapter_of(run.manifest)
    num = chapter.numbering(run.manifest) if chapter else Numbering()
    analysis = generic.analyze(run, num, out)
    analysis.claims_apply = chapter is not None
    # Where the reference has nothing to say on the task (an environment it did not register, a
    # user's own), the report does not mention it at all.
    if REGISTRY.reference and (chapter or run.manifest.env_kind in REGISTRY.environments):
        analysis.header.append(
            (
                REGISTRY.reference,
                chapter.model if chapter else "no chapter's model matches this run: generic figures, no claims",
            )
        )
    environment = REGISTRY.environments.get(run.manifest.env_kind)
    parts = environment(run, num, out) if environment is not None else None
    if parts is None:
        return analysis
    view, own = parts
    analysis.title = own.title
    analysis.add(own)
    if chapter is not None:
        analysis.results = evaluate(chapter.claims, view)
    return analysis


def analyze_run(run_dir: Path, force: bool = False) -> RunOutcome:
    """Rebuild ``run_dir/analysis/``, unless what it was made from is unchanged since and ``force``
    is off (``ferl.analysis.cache``); return the run's line of a sweep report."""
    summary = runs.load_summary(run_dir)
    task, experiment = str(summary.get("task")), str(summary.get("experiment", "?"))
    manifest = Manifest.load(run_dir)
    if manifest is None:
        print(f"{run_dir}: skipped, no {MANIFEST}")
        return RunOutcome(run_dir, experiment, task, f"skipped: no {MANIFEST}")

    out, tb_dir = run_dir / "analysis", run_dir / "tb" / "analysis"
    digest = cache.inputs_digest(run_dir, REGISTRY)
    kept = None if force else _kept(run_dir, digest)
    if kept is not None:
        return kept
    analysis = run_analysis(Run.load(run_dir, manifest), _fresh(out))
    publish_figures(analysis.figures, out, tb_dir)
    write_json(out / cache.CLAIMS, [_claim_json(r) for r in analysis.results])
    analysis.data_files.append(cache.CLAIMS)
    write_run_report(out / "report.md", analysis, REGISTRY.reference)

    verdicts = {v: sum(r.verdict == v for r in analysis.results) for v in VERDICTS}
    print(
        f"{run_dir}: {len(analysis.figures)} figures, {len(analysis.results)} claims "
        f"({', '.join(f'{n} {v}' for v, n in verdicts.items())}) -> {out / 'report.md'}"
    )
    figures = [(name, caption) for name, (_, caption) in analysis.figures.items()]
    outcome = RunOutcome(run_dir, experiment, task, "analyzed", verdicts, analysis.results, figures)
    cache.save(out, outcome, digest, sorted(p.name for p in tb_dir.glob("*")))
    return outcome


def _kept(run_dir: Path, digest: str | None = None) -> RunOutcome | None:
    """The run's kept analysis (``ferl.analysis.cache``), said in one line; None: analyse it."""
    out = run_dir / "analysis"

    def inputs_digest() -> str:
        return digest or cache.inputs_digest(run_dir, REGISTRY)

    kept = cache.load(run_dir, out, inputs_digest, run_dir / "tb" / "analysis", REGISTRY.all_claims)
    if kept is not None:
        print(
            f"{run_dir}: unchanged since its last analysis, kept ({len(kept.figures)} figures) -> {out / 'report.md'}"
        )
    return kept


def _safe_analyze_run(run_dir: Path, force: bool = False) -> RunOutcome:
    """One failing run must not stop a sweep: report it in one line and go on."""
    try:
        with _collected_once():
            return analyze_run(run_dir, force)
    except Exception as exc:  # noqa: BLE001 — any failure is reported per run
        # One write: the pool's workers share stderr, which writes through, and print() would
        # write the line and its newline apart, letting another worker's line in between.
        sys.stderr.write(f"{PROG}: error: {run_dir}: {type(exc).__name__}: {exc}\n")
        return RunOutcome(run_dir, "?", "?", f"failed: {type(exc).__name__}: {exc}")


@contextlib.contextmanager
def _collected_once() -> Iterator[None]:
    """Run the body with Python's cyclic garbage collector paused, then collect once.

    A matplotlib figure is a web of reference cycles (figure, axes, artists, callbacks), so a
    run's analysis leaves ~10^5 objects that only the cyclic collector frees. Left to its
    thresholds, the collector made several full passes during each run, and every pass walked all
    the figures still alive. One full collection at the end frees the same garbage in one pass
    (with the workers' freeze below, ``analyze.py`` on the reproduction sweep took 8 % less time:
    docs/performance.md, "One collection per run"). The collector is left as it was found.
    """
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
        gc.collect()


def _analyze_in_worker(run_dir: Path, plugins: Sequence[str], force: bool) -> RunOutcome:
    """``_safe_analyze_run`` in a pool's worker process, whose registry starts empty: import the
    parent's ``plugins`` first (``dispatch.import_plugins``). On the worker's first run, freeze
    what is alive then (the modules, matplotlib's caches): it lives as long as the worker, and
    frozen, the collector's passes no longer walk it (``gc.freeze``)."""
    import_plugins(plugins)
    if gc.get_freeze_count() == 0:
        gc.collect()
        gc.freeze()
    return _safe_analyze_run(run_dir, force)


def _read_summary(run_dir: Path) -> dict | None:
    """A run's summary for the sweep tables, also where its own analysis failed; None if
    unreadable."""
    try:
        return runs.load_summary(run_dir)
    except (OSError, ValueError):
        return None


def analyze_runs(found: list[Path], force: bool = False) -> list[RunOutcome]:
    """Every run's own analysis, on every CPU at once from POOL_MIN_RUNS runs on (the figures'
    drawing is most of the time, and the runs are independent); a run whose analysis is kept
    (unchanged since, ``ferl.analysis.cache``; not with ``force``) is not handed to a worker."""
    kept = {} if force else {r: o for r in found if (o := _safe_kept(r)) is not None}
    # The largest records first: no worker is left with the longest analysis at the end.
    stale = sorted((r for r in found if r not in kept), key=_records_bytes, reverse=True)
    workers = min(os.cpu_count() or 1, len(stale))
    if workers < 2 or len(stale) < POOL_MIN_RUNS:
        done = [_safe_analyze_run(r, force=force) for r in stale]
    else:
        from joblib import Parallel, delayed  # loky's workers return the claims' functions too (cloudpickle)

        done = Parallel(n_jobs=workers, batch_size=1)(
            delayed(_analyze_in_worker)(r, REGISTRY.modules, force) for r in stale
        )
    by_run = kept | dict(zip(stale, done))
    return [by_run[r] for r in found]


def _records_bytes(run_dir: Path) -> int:
    """The size of a run's records, what its analysis reads (its time grows with it); 0 where
    they cannot be read (its analysis reports that)."""
    try:
        return sum(p.stat().st_size for p in (run_dir / "records").glob("*") if p.is_file())
    except OSError:
        return 0


def _safe_kept(run_dir: Path) -> RunOutcome | None:
    """``_kept``, where an unreadable run is left to its analysis to report."""
    try:
        return _kept(run_dir)
    except (OSError, ValueError):
        return None


def analyze_sweep(sweep_dir: Path, pages: Sequence[Path] = (), force: bool = False) -> list[RunOutcome]:
    """Analyze every run below ``sweep_dir``, then the sweep as a whole (``ferl.analysis.sweep``,
    then the registered sweep sections)."""
    start = time.perf_counter()
    found = runs.find_runs(sweep_dir)
    skipped = report_unfinished(sweep_dir)
    outcomes = analyze_runs(found, force)
    jobs = [_job(o, summary) for o in outcomes if (summary := _read_summary(o.run_dir)) is not None]
    sweep = sw.Sweep(sweep_dir, jobs)
    out = _fresh(sweep_dir / "analysis")
    rows = sw.reproduction_rows(jobs, evaluate(REGISTRY.sweep_claims, sweep), REGISTRY.claim_order)
    # a sweep of no run that the reference speaks to is a plain "Report", without a claims section
    reproduces = bool(rows) or any(job.reference for job in jobs)
    analysis = sw.analyze_sweep(sweep, out, REGISTRY.sweep_title if reproduces else sw.PLAIN_TITLE)
    findings = [line for section in REGISTRY.sweep_sections for line in section(sweep, out, analysis)]
    publish_figures(analysis.figures, out, out / "tb")
    write_json(
        out / "claims.json",
        [
            _claim_json(
                r.result,
                job=None if r.job is None else str(r.job.run_dir),
                variant=None if r.job is None else r.job.variant,
            )
            for r in rows
        ],
    )
    analysis.data_files.append("claims.json")

    wall = {}
    train_wall = sweep_dir / sw.TRAIN_WALL_TIME
    if train_wall.is_file():
        wall["training wall time (make reproduce / make beyond)"] = float(train_wall.read_text())
    wall["sum of the jobs' wall_time_s"] = sum(float(j.summary.get("wall_time_s", 0)) for j in jobs)
    wall["analysis wall time"] = time.perf_counter() - start
    lines = sw.report_lines(sweep, analysis, rows, out, wall, REGISTRY.claims_heading if reproduces else None)
    notes = sweep_dir / NOTES  # a launcher's lines for the report (baselines/reference.py: where PPO's rows come from)
    lines += (["", *notes.read_text().splitlines()] if notes.is_file() else []) + findings
    lines += ["", "## Jobs", ""] + jobs_table(sweep_dir, out, outcomes + skipped)
    (out / "report.md").write_text("\n".join(lines) + "\n")
    if pages and REGISTRY.pages is not None:
        REGISTRY.pages.update_pages(pages, rows, wall, out / "report.md")
        print(f"{', '.join(map(str, pages))}: reproduction results updated")
    print(
        f"{sweep_dir}: sweep of {len(found)} runs{_skipped_note(sweep_dir, skipped)}, {len(rows)} claims "
        f"({sw.verdict_counts(rows)}) -> {out / 'report.md'}"
    )
    return outcomes


def _job(outcome: RunOutcome, summary: dict) -> sw.Job:
    """A sweep's job, with the reference its run reproduces: where a registered chapter applies to
    what it recorded (then a job without overrides runs "as in the dissertation")."""
    job = sw.Job(outcome, summary)
    if job.manifest is not None and REGISTRY.chapter_of(job.manifest) is not None:
        job.reference = REGISTRY.reference
    return job


def report_unfinished(sweep_dir: Path) -> list[RunOutcome]:
    """One stderr line for each member of the sweep that has no summary.json yet (still
    running, killed or failed: ``ferl.analysis.members``); their rows of the sweep's jobs table."""
    skipped = []
    for run_dir, why in members.unfinished(sweep_dir):
        print(f"{PROG}: skipped {run_dir}: {why}", file=sys.stderr)
        skipped.append(RunOutcome(run_dir, "?", "?", f"skipped: {why}"))
    return skipped


def _skipped_note(sweep_dir: Path, skipped: list[RunOutcome]) -> str:
    """``; 2 skipped: 3, 7`` (the skipped members relative to the sweep), or nothing."""
    if not skipped:
        return ""
    return f"; {len(skipped)} skipped: " + ", ".join(os.path.relpath(o.run_dir, sweep_dir) for o in skipped)


def _usage_error(dirs: list[Path], pages: Sequence[Path]) -> str | None:
    """What is wrong with the command line, None when nothing is."""
    missing = [str(d) for d in dirs if not d.is_dir()]
    if missing:
        return f"no such directory: {', '.join(missing)}"
    single = [str(d) for d in dirs if (d / "summary.json").is_file()]
    if pages and single:
        return f"--readme takes sweep directories only, not the run {', '.join(single)}"
    writer = REGISTRY.pages
    if pages and writer is None:
        return "--readme: no plug-in that writes pages is registered"
    for page in pages:
        assert writer is not None
        if not (page.is_file() and writer.blocks_in(page.read_text())):
            markers = " or ".join(f"{b!r} … {e!r}" for b, e in writer.BLOCKS)
            return f"--readme {page}: needs a file with the marker lines {markers}"
    return None


def main(dirs: list[Path], pages: Sequence[Path] = (), force: bool = False) -> int:
    """Analyze each directory (a run or a sweep); the exit status: 2 for a usage error or a
    directory without runs, 1 when a run's analysis failed (a damaged or missing file), else 0 —
    also when members of a sweep were skipped for having no summary.json yet (each is named in
    one line, and the sweep's header counts them)."""
    error = _usage_error(dirs, pages)
    if error is not None:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    status = 0
    for d in dirs:
        if (d / "summary.json").is_file():
            outcomes = [_safe_analyze_run(d, force=force)]
        elif not any(d.rglob("summary.json")):
            skipped = report_unfinished(d)
            print(
                f"{PROG}: error: {d}: no run (summary.json) found below it"
                + (f" ({len(skipped)} unfinished)" if skipped else ""),
                file=sys.stderr,
            )
            status = 2
            continue
        else:
            outcomes = analyze_sweep(d, pages, force)
        if any(o.status.startswith("failed") for o in outcomes):
            status = max(status, 1)
    return status
