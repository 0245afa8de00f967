"""Documentation contract: the README is a short front page whose links resolve, and the docs site
(mkdocs.yml, docs/) builds strictly: no warning, no broken link or anchor, no unresolved API
reference, every page in the nav. Starts no SUMO."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import yaml

from conftest import ROOT

README = ROOT / "README.md"
README_MAX_LINES = 250


def _relative_links(path):
    """Targets of the Markdown links of ``path`` that are neither URLs nor in-page anchors."""
    text = path.read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # no links inside code blocks
    text = re.sub(r"`[^`\n]*`", "", text)  # nor inside inline code
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return [t for t in targets if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


def test_readme_is_a_short_front_page_starting_with_the_two_commands():
    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES})"
    assert lines[0].startswith("# ")
    first_block = text.index("```")
    assert text[:first_block].count("\n") <= 2, "the two commands come first, right after the title"
    for section in ("## Convert recorded scenes", "## Train on recorded scenes",
                    "## Train on a city (and with Ray)", "## Evaluate and report", "## Results",
                    "## Architecture", "## Security and robustness"):
        assert f"\n{section}\n" in text, section


@pytest.mark.parametrize("page", [README, ROOT / "benchmarks" / "README.md"], ids=lambda p: p.parent.name)
def test_relative_links_point_at_existing_files(page):
    broken = []
    for target in _relative_links(page):
        path = (page.parent / target.split("#", 1)[0]).resolve()
        if not path.exists():
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"


def test_every_docs_page_is_in_the_nav():
    cfg = yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=yaml.SafeLoader)

    def pages(node):
        if isinstance(node, str):
            yield node
        elif isinstance(node, list):
            for item in node:
                yield from pages(item)
        elif isinstance(node, dict):
            for value in node.values():
                yield from pages(value)

    nav = set(pages(cfg["nav"]))
    docs = {p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md")}
    assert docs == nav, f"not in the nav: {sorted(docs - nav)}; in the nav, missing: {sorted(nav - docs)}"
    assert cfg["strict"] is True
    assert set(cfg["validation"].values()) == {"warn"}  # strict turns each warning into a failure


def test_docs_site_builds_strictly(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # a banner of mkdocs-material, not a build warning
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert "WARNING" not in log, log[-4000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "api" / "scene" / "index.html").is_file()
