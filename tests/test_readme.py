"""README contract: two fenced commands at the top; CI runs the second one verbatim."""

from __future__ import annotations

import re

from conftest import ROOT


def test_readme_opens_with_two_commands_and_ci_runs_the_test_command():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)
    head = text.split("\n## ")[0]
    assert len(re.findall(r"```bash", head)) == 2, "README must open with exactly two commands"
    demo, test = blocks[0].strip(), blocks[1].strip()
    assert "\n" not in demo and "\n" not in test
    assert demo.startswith("python -m pip install") and "magail-sumo" in demo
    assert "pytest" in test
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test in ci, ".ci/run must run the README's test command verbatim"
