"""docs/cli.md is the CLI reference: it names every sub-command and every option `--help` lists, and no other."""

import re
from pathlib import Path

import pytest

from napari_lbs._cli import main

CLI_DOC = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as leaving:
        main([*argv, "--help"])
    assert leaving.value.code == 0
    return capsys.readouterr().out


def _sections() -> dict[str, str]:
    parts = re.split(r"^## `napari-lbs (\w+)`$", CLI_DOC.read_text(), flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))


def _subcommands(capsys) -> list[str]:
    listing = re.search(r"\{([\w,]+)\}", _help(capsys)).group(1)
    return listing.split(",")


def test_every_subcommand_has_a_section_and_no_section_is_stale(capsys):
    assert sorted(_sections()) == sorted(_subcommands(capsys))


def test_every_option_of_every_subcommand_is_documented_and_none_is_stale(capsys):
    sections = _sections()
    for command in _subcommands(capsys):
        text = _help(capsys, command)
        listed = set(OPTION.findall(text.split("options:", 1)[1])) - {"--help"}
        table = "\n".join(line for line in sections[command].splitlines() if line.startswith("| `"))
        documented = {OPTION.match(cell).group(1) for cell in re.findall(r"^\| `([^`]+)`", table, re.M) if OPTION.match(cell)}
        assert listed == documented, f"{command}: in --help only {sorted(listed - documented)}; in docs/cli.md only {sorted(documented - listed)}"
        positionals = re.findall(r"^  ([A-Z][A-Za-z_.]*)(?:\s|$)", text.split("options:", 1)[0], re.M)
        for name in positionals:
            assert f"| `{name}`" in table, f"{command}: positional {name} not in docs/cli.md"


def test_global_options_are_documented(capsys):
    listed = set(OPTION.findall(_help(capsys))) - {"--help"}
    head = CLI_DOC.read_text().split("## `napari-lbs", 1)[0]
    assert listed <= set(OPTION.findall(head))
