"""The README's quick start (two commands, and CI runs the second exactly as written), and every command
line the README and docs/ show is one the CLI takes."""

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


def _documented_command_lines():
    """Each `sunrig ...` line in a code block of the README and docs/, continuation lines joined.
    Synopses (`[--baud BAUD]`, `PORT_OR_FILE`) and elided lines (`--camera ...`) are left out:
    they show a shape, not a command to type."""
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
            for line in block.replace("\\\n", " ").splitlines():
                # At the line's start, after a shell prompt or `&&`, or after a path (ExecStart=).
                m = re.match(r"(?:\s*\$?\s*|.*&& |.*/)(sunrig .*)", line)
                if not m:
                    continue
                command = m.group(1)
                code = command.split("#")[0]
                if "[" in code or "..." in code or re.search(r" [A-Z_]{4,}\b", code):
                    continue
                yield path.name, command


def test_every_command_the_docs_show_is_one_the_cli_takes():
    import shlex

    from rig.cli import build_parser

    commands = list(_documented_command_lines())
    assert len(commands) >= 10, commands  # the extraction still finds the docs' examples
    for name, command in commands:
        argv = shlex.split(command, comments=True)[1:]
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            raise AssertionError(f"{name}: `{command}` is not a command sunrig takes") from None
