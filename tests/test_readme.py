"""The README's Python examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_examples():
    assert BLOCKS, "the README lost its Python examples"


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_example_runs(index):
    exec(compile(BLOCKS[index], f"README.md[python block {index}]", "exec"), {})


def _cli_sections() -> dict[str, set[str]]:
    """docs/cli.md (generated from the parsers, checked current by tests/test_cli.py): command ->
    the options its table lists."""
    text = (README.parent / "docs" / "cli.md").read_text()
    sections: dict[str, set[str]] = {}
    for head, body in re.findall(r"### `torchcontact ?([^`]*)`\n(.*?)(?=\n### |\Z)", text, re.S):
        options = set(re.findall(r"`(--[a-z][a-z0-9-]*)", body))
        sections.setdefault(head.strip(), set()).update(options)
    return sections


def _readme_commands() -> list[str]:
    """Every ``torchcontact ...`` command line of the README: in shell blocks (continuation
    lines joined) and in inline code."""
    text = README.read_text()
    lines = []
    for block in re.findall(r"```(?:sh|bash)\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            for part in re.split(r"&&|;", line.split("#", 1)[0]):
                if part.strip().startswith("torchcontact "):
                    lines.append(part.strip())
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    lines += [c.replace("\n", " ") for c in re.findall(r"`(torchcontact\s[^`]+)`", prose)]
    return lines


def test_every_command_the_readme_shows_exists_with_its_options():
    sections = _cli_sections()
    commands = _readme_commands()
    assert len(commands) > 20, commands
    wrong = []
    for line in commands:
        words = line.split()[1:]
        path = ""
        for n in range(len(words), 0, -1):
            if " ".join(words[:n]) in sections:
                path = " ".join(words[:n])
                break
        if not path and words and not words[0].startswith("-"):
            wrong.append(f"{line}: no command {words[0]!r}")
            continue
        for word in words:
            option = word.split("=", 1)[0].strip("[]")
            if option.startswith("--") and option not in sections[path] | {"--help"}:
                wrong.append(f"{line}: torchcontact {path} has no option {option}")
    assert not wrong, "\n".join(wrong)


def test_own_robot_example_is_the_one_tests_run():
    """The README's --ft-sensor example on the panda is docs/cli.md's, which tests/test_cli.py
    runs as written."""
    cli = (README.parent / "docs" / "cli.md").read_text()
    block = re.search(r"```sh\n(pip install example-robot-data.*?)```", cli, re.S).group(1)
    assert block in README.read_text()
