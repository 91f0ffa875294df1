"""The front door: the README fits one screen and starts with the two commands, and no link in
the README or docs/ points at a file that does not exist, at a heading its page does not have, or
at a machine's absolute path."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_readme_is_one_screen_and_starts_with_the_two_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 160
    blocks = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)
    assert blocks[0].startswith("pip install torch==2.13.0 && pip install -e . && python examples/train_3dgs.py")
    assert blocks[1] == 'pip install torch==2.13.0 && pip install -e ".[dev]" && python -m pytest -q -m "not slow" -n 2 --dist loadfile'
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'python -m pytest -q -m "not slow" -n 2 --dist loadfile' in ci and "python -m pytest -q -m slow" in ci


def relative_links(page: Path) -> list:
    """The targets of a page's markdown links that are not URLs."""
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", page.read_text()) if not re.match(r"[a-z]+://", t)]


def test_every_relative_link_resolves():
    missing = []
    for page in PAGES:
        for target in relative_links(page):
            if target.startswith("#"):
                continue
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.exists():
                missing.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not missing, missing


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text: lower case, every character but letters, digits,
    '_', '-' and spaces dropped, spaces made '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def heading_anchors(page: Path) -> set:
    """The anchors GitHub gives a page's headings (slug; a repeated one gets -1, -2, ...).
    Lines inside fenced code are not headings."""
    anchors, seen, fenced = set(), {}, False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        heading = None if fenced else re.match(r"#{1,6} +(.*?)[ #]*$", line)
        if heading:
            anchor = slug(heading.group(1))
            count = seen.get(anchor, 0)
            seen[anchor] = count + 1
            anchors.add(anchor if count == 0 else f"{anchor}-{count}")
    return anchors


def test_heading_anchors_follow_githubs_rule(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# The 1/4 level does not pay (2026-11-27, later)\n## Notes\n```\n## not a heading\n```\n"
                    "## Notes\n### `default` at 10k: −0.5 dB, 0.7x\n")
    assert heading_anchors(page) == {"the-14-level-does-not-pay-2026-11-27-later", "notes", "notes-1",
                                     "default-at-10k-05-db-07x"}


def test_every_link_to_a_heading_finds_it():
    missing = []
    for page in PAGES:
        for target in relative_links(page):
            if "#" not in target:
                continue
            path, anchor = target.split("#", 1)
            dest = (page.parent / path).resolve() if path else page
            if dest.suffix == ".md" and dest.exists() and anchor not in heading_anchors(dest):
                missing.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not missing, missing


def tracked_files() -> list:
    """The files git tracks (a venv, out/ or a build inside the checkout are not the project's);
    outside a git checkout (an unpacked sdist), every file but those under hidden, build and
    output folders, said so in the test's name for the file list."""
    import subprocess

    try:
        listing = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
        return [ROOT / name for name in listing.decode().split("\0") if name]
    except (OSError, subprocess.CalledProcessError):
        skip = {"out", "build", "dist", "__pycache__"}
        return [p for p in ROOT.rglob("*") if p.is_file() and not any(
            part.startswith(".") or part in skip or part.endswith(".egg-info") for part in p.relative_to(ROOT).parts)]


def test_no_machine_paths():
    """No absolute path of a machine in the docs, the code or the committed benchmark records."""
    files = [p for p in tracked_files() if p.suffix in (".md", ".py", ".json", ".toml", ".txt") and p.is_file()]
    assert any(p.suffix == ".json" for p in files) and any(p.name == "README.md" for p in files)
    found = [f"{p.relative_to(ROOT)}: {m}" for p in files
             for m in re.findall(r"(?<![\w.])/(?:work|tmp|home|root)/[\w./-]+", p.read_text(errors="replace"))]
    assert not found, found[:20]


def test_a_venv_or_outputs_inside_the_checkout_are_not_the_projects_files(tmp_path):
    """python -m venv .venv and the examples' out/ live inside the checkout: git ignores them, so
    the tree walk of the tests does too."""
    ignore = (ROOT / ".gitignore").read_text().split()
    assert ".venv/" in ignore and any(line.rstrip("/").lstrip("/") == "out" for line in ignore)
    venv = ROOT / ".venv" / "lib" / "probe_machine_path.py"
    made = not venv.exists()
    venv.parent.mkdir(parents=True, exist_ok=True)
    try:
        venv.write_text('HOME = "' + "/".join(["", "root", "somewhere"]) + '"\n')  # a machine path, built here
        assert venv not in tracked_files()
    finally:
        if made:
            venv.unlink()
            for folder in (venv.parent, venv.parent.parent):
                if not any(folder.iterdir()):
                    folder.rmdir()


def test_the_results_page_indexes_every_section_of_the_log():
    """docs/equal_compute.md ends with an index of docs/equal_compute_log.md: a section added to the
    log without a line there would be out of the reader's sight."""
    log = ROOT / "docs" / "equal_compute_log.md"
    title = slug(log.read_text().splitlines()[0].lstrip("# "))
    linked = set(re.findall(r"\(equal_compute_log\.md#([^)\s]+)\)", (ROOT / "docs" / "equal_compute.md").read_text()))
    missing = heading_anchors(log) - {title} - linked
    assert not missing, sorted(missing)
