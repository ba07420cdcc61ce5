"""The README a newcomer reads (issue 7/8): short, the two commands first (CONTRACT §1), every page
of docs/ one link away, no broken link, and a gallery whose figures are the files `make figures`
writes."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)|<img src=\"([^\"]+)\"")
sys.path.insert(0, str(ROOT / "docs" / "figures"))
import gallery  # noqa: E402  (docs/figures/gallery.py: a script, not part of the package)


def local_links(page: Path) -> list[str]:
    return [a or b for a, b in LINK.findall(page.read_text()) if not (a or b).startswith(("http", "mailto:"))]


def test_readme_is_short_and_opens_with_the_two_commands():
    lines = README.read_text().splitlines()
    assert len(lines) <= 150
    first_block = lines[lines.index("```") + 1 : lines.index("```", lines.index("```") + 1)]
    assert [line.split()[:2] for line in first_block] == [["make", "run"], ["make", "test"]]
    assert not any(line.startswith("```") for line in lines[: lines.index("```")])


def test_every_page_of_docs_is_linked_from_the_readme():
    linked = {(README.parent / link).resolve() for link in local_links(README)}
    assert [p.name for p in PAGES if p.resolve() not in linked] == []


@pytest.mark.parametrize("page", [README, *PAGES], ids=lambda p: p.name)
def test_local_links_resolve(page):
    broken = [link for link in local_links(page) if not (page.parent / link).exists()]
    assert broken == []


def test_the_repository_cites_its_docs_not_the_contract():
    """The contract is the outside's list of promises, not a page of the repository: train.py, the
    Makefile, the code and docs/ point a reader to docs/ pages, never to the contract's sections."""
    cited = [ROOT / "train.py", ROOT / "analyze.py", ROOT / "Makefile", *PAGES, README]
    cited += [p for folder in ("ferl", "reproduction", "baselines", "conf") for p in (ROOT / folder).rglob("*.*")]
    citing = [
        str(p.relative_to(ROOT))
        for p in cited
        if p.suffix in ("", ".py", ".md", ".yaml") and re.search(r"CONTRACT|contract's §", p.read_text())
    ]
    assert citing == []


def test_the_gallery_shows_the_files_make_figures_writes():
    shown = {Path(link).name for link in local_links(README) if link.startswith("docs/figures/")}
    assert shown == {name for name, _, _ in gallery.GALLERY}
    for name, _, caption in gallery.GALLERY:
        assert (ROOT / "docs" / "figures" / name).stat().st_size > 10_000
        assert caption in README.read_text()


def test_make_figures_copies_each_figure_and_rewrites_only_its_block(tmp_path):
    sweep = tmp_path / "outputs" / "reproduce" / "2026-01-01_00-00-00"
    for k, (name, pattern, _) in enumerate(gallery.GALLERY):
        path = sweep / pattern.replace("*", f"{k}")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(f"png {name}".encode())
    page, out = tmp_path / "README.md", tmp_path / "docs" / "figures"
    out.mkdir(parents=True)
    page.write_text("# top\n{}\nold\n{}\nend\n".format(*gallery.MARKERS))
    script = ROOT / "docs" / "figures" / "gallery.py"
    result = subprocess.run(
        [sys.executable, str(script), str(sweep), "--readme", str(page), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    for name, _, caption in gallery.GALLERY:
        assert (out / name).read_bytes() == f"png {name}".encode()
        assert f'<img src="docs/figures/{name}" width="420"><br>{caption}' in page.read_text()
    text = page.read_text()
    assert text.startswith("# top\n") and text.endswith(f"{gallery.MARKERS[1]}\nend\n") and "old" not in text


def test_make_figures_refuses_a_sweep_without_its_figures_before_copying(tmp_path):
    out = tmp_path / "figures"
    out.mkdir()
    result = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "figures" / "gallery.py"), str(tmp_path), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0 and list(out.iterdir()) == []
    assert result.stderr.strip().startswith("gallery: error:") and len(result.stderr.strip().splitlines()) == 1
