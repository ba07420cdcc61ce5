"""The one-line errors for what Hydra rejects before main() runs (``ferl.config.hydra_glue``:
``one_line_errors`` → ``hydra_report_line``) parse Hydra's own report, whose wording belongs to Hydra.
pyproject.toml allows hydra-core>=1.3,<1.4: every 1.3.x release on the package index (1.3.0 … 1.3.8
on 2026-12-03) must give the same line as the installed one, for each kind of report.

Each release's wheel is fetched once (``pip download``, into ~/.cache/ferl/hydra-core, or
FERL_HYDRA_WHEELS) and run unpacked, without installing it: a child process composes conf/ with that
Hydra through ``hydra.main`` as train.py does (it imports neither ferl nor torch) and hands back
what Hydra printed; this process turns each report into its line. Without the package index and
without cached wheels the test is skipped. About 2 s per release.
"""

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import hydra
import pytest

from conftest import ROOT
from ferl.config.hydra_glue import hydra_report_line

RELEASES = [f"1.3.{patch}" for patch in range(9)]
WHEELS = Path(os.environ.get("FERL_HYDRA_WHEELS", Path.home() / ".cache" / "ferl" / "hydra-core"))

# Every case runs each Hydra in the same folders, so the paths in the lines agree.
CHILD = """
import contextlib, io, json, sys
import hydra
from hydra.core.global_hydra import GlobalHydra

@hydra.main(version_base="1.3", config_path={conf!r}, config_name="config")
def main(cfg):
    raise SystemExit("main() ran: Hydra accepted the input")

reports = []
for arguments in json.loads(sys.argv[1]):
    sys.argv, err, code = ["train.py", *arguments], io.StringIO(), 0
    with contextlib.redirect_stderr(err):
        try:
            main()
        except SystemExit as e:
            code = e.code
    GlobalHydra.instance().clear()
    reports.append([code if isinstance(code, int) else str(code), err.getvalue()])
print(json.dumps({{"version": hydra.__version__, "reports": reports}}))
"""


def cases(tmp: Path) -> dict[str, tuple[list[str], str]]:
    """Input → (the command line, a part of the line that it must give)."""
    (tmp / "a_file").write_text("")
    run = f"hydra.run.dir={tmp / 'run'}"
    return {
        # ferl's own keys are typed by ferl (ferl.config.validate, in main()); Hydra's by Hydra
        "wrong type": (["hydra.job.chdir=maybe", run], "hydra.job.chdir: Value 'maybe' is not a valid bool"),
        "unknown option": (["actor=no_such_actor", run], "Could not find 'actor/no_such_actor'"),
        "null option": (["experiment=null", run], "experiment=null is not allowed: a group's option cannot be null"),
        "unknown key": (["no_such_key=1", run], "Could not override 'no_such_key'"),
        "bad syntax": (["n_runs=[1", run], "no viable alternative at input '[1'"),
        "run dir under a file": (
            [f"hydra.run.dir={tmp / 'a_file' / 'run'}"],
            "a file stands where a directory should be (errno ENOTDIR)",
        ),
    }


def wheel(version: str) -> Path | None:
    """hydra-core ``version``'s wheel, fetched once; None where it cannot be had."""
    found = sorted(WHEELS.glob(f"hydra_core-{version}-*.whl"))
    if not found:
        WHEELS.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                f"hydra-core=={version}",
                "--no-deps",
                "-q",
                "--retries",
                "0",
                "--timeout",
                "15",
                "-d",
                str(WHEELS),
            ],
            capture_output=True,
            timeout=120,
        )
        found = sorted(WHEELS.glob(f"hydra_core-{version}-*.whl"))
    return found[0] if found else None


def reports(hydra_dir: Path | None, arguments: list[list[str]], cwd: Path) -> dict:
    """What the Hydra unpacked in ``hydra_dir`` (None: the installed one) prints for each command line."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    if hydra_dir is not None:
        env["PYTHONPATH"] = str(hydra_dir)  # ahead of site-packages: this release, not the installed one
    result = subprocess.run(
        [sys.executable, "-c", CHILD.format(conf=str(ROOT / "conf")), json.dumps(arguments)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_every_allowed_hydra_release_gives_the_same_lines(tmp_path):
    named = cases(tmp_path)
    arguments = [arguments for arguments, _ in named.values()]
    installed = reports(None, arguments, tmp_path)
    assert installed["version"] == hydra.__version__
    expected = {}
    for (name, (args, part)), (code, report) in zip(named.items(), installed["reports"]):
        line = hydra_report_line(report, args)
        assert code not in (0, None) and part in line and "\n" not in line, (name, code, report, line)
        expected[name] = line
    wheels = {version: wheel(version) for version in RELEASES}
    if not any(wheels.values()):
        pytest.skip(f"no hydra-core 1.3.x wheel in {WHEELS} and no package index to fetch one from")
    assert all(wheels.values()), f"hydra-core releases the pin allows that pip could not fetch: {wheels}"
    for version, path in wheels.items():
        unpacked = tmp_path / "hydra" / version
        zipfile.ZipFile(path).extractall(unpacked)
        got = reports(unpacked, arguments, tmp_path)
        assert got["version"] == version
        lines = {
            name: hydra_report_line(report, args)
            for (name, (args, _)), (_, report) in zip(named.items(), got["reports"])
        }
        assert lines == expected, f"hydra-core {version}"
