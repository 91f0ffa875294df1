"""The front door: the README fits one screen and starts with the two commands, and no link in
the README or docs/ points at a file that does not exist or at a machine's absolute path."""

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
    assert blocks[1] == 'pip install torch==2.13.0 && pip install -e ".[dev]" && python -m pytest -q -m "not slow"'
    ci = (ROOT / ".ci" / "run").read_text()
    assert 'python -m pytest -q -m "not slow"' in ci and "python -m pytest -q -m slow" in ci


def test_every_relative_link_resolves():
    missing = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+://", target) or target.startswith("#"):
                continue
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.exists():
                missing.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not missing, missing


def test_no_machine_paths():
    found = [f"{p.relative_to(ROOT)}: {m}" for p in PAGES + sorted(ROOT.glob("*/**/*.py"))
             for m in re.findall(r"(?<![\w.])/(?:work|tmp|home|root)/[\w./-]+", p.read_text())]
    assert not found, found
