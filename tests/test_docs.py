"""The documentation: the site builds with --strict (a broken link or anchor fails), the README stays short,
and neither speaks of how the work was organised (work-item or session numbers)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_the_site_builds_strictly(tmp_path):
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file() and (tmp_path / "site" / "results" / "index.html").is_file()


def test_the_readme_is_read_in_five_minutes():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 120
    first_block = next(i for i, line in enumerate(lines) if line.startswith("```"))
    assert lines[first_block + 1].startswith("make run") and lines[first_block + 2].startswith("make test")


def _section(lines: list[str], title: str) -> list[str]:
    start = lines.index(f"## {title}") + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    return lines[start:end]


def test_the_readme_is_narrow_its_results_short_and_its_limits_few():
    lines = (ROOT / "README.md").read_text().splitlines()
    wide = [f"README.md:{n}: {len(cell)} characters: {cell[:60]}..." for n, line in enumerate(lines, 1)
            if line.startswith("|") for cell in (c.strip() for c in line.strip("|").split("|")) if len(cell) > 160]
    assert not wide, "table cells over 160 characters:\n" + "\n".join(wide)
    rows = [line for line in _section(lines, "Results") if line.startswith("|")][2:]  # past header and rule
    assert 1 <= len(rows) <= 8, f"{len(rows)} results rows (at most 8)"
    bullets = [line for line in _section(lines, "Limits") if line.startswith("- ")]
    assert 1 <= len(bullets) <= 6, f"{len(bullets)} limits (at most 6)"
    assert all(len(b) <= 160 for b in bullets), [b for b in bullets if len(b) > 160]


def test_pages_speak_of_the_product_only():
    pattern = re.compile(r"\b(issue|session|work item)s? ?#?\d+", re.IGNORECASE)
    hits = [f"{page.relative_to(ROOT)}:{n}: {line.strip()}" for page in PAGES
            for n, line in enumerate(page.read_text().splitlines(), 1) if pattern.search(line)]
    assert not hits, "\n".join(hits)


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target
