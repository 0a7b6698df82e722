"""The README's quick start: two commands, and CI runs the second exactly as written."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_ci_runs_the_readme_test_command_as_written():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    quick = re.search(r"## Quick start\s+```sh\n(.*?)```", readme, flags=re.S)
    assert quick, "README has no Quick start block"
    commands = [line for line in quick.group(1).splitlines() if line.strip()]
    assert len(commands) == 2, commands
    ci = [line for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
          if line.strip() and not line.startswith(("#", "set ", "cd "))]
    assert ci == [commands[1]]
