"""Every command's --help as a user reads it at 80 columns (issue 42, item 9): no sentence broken by a hand-made
line break, nothing cut, every option described, no Python type for a placeholder, options grouped into panels
so the pages stay short, and angles in radians as everywhere else. In-process renders only: no mapping."""
import functools
import math
import re

import pytest
import typer.main
from typer.testing import CliRunner

from carto_cli.cli import app

# Every command and group, checked against the app itself so that a new one cannot be left out.
COMMANDS = [(), ("info",), ("convert",), ("map",), ("merge",), ("eval",), ("profile",), ("relocalize",), ("render",),
            ("tune",), ("options",), ("profiles",), ("profiles", "list"), ("profiles", "show")]
# Lines at 80 columns. Before the panels: map 111, profile 107, relocalize 93, tune 66; after: 78, 73, 78, 58.
# The bounds leave room for a new option or two, not for a page that stops being read.
MAX_LINES = {"map": 85, "profile": 85, "relocalize": 85, "tune": 70}
MAX_LINES_OTHERS = 45
ANSI = re.compile(r"\x1b\[[0-9;]*m")
# What typer or click print when a parameter has no metavar of its own: <str>, <list[str]>, <int range>,
# {recording} (typer >= 0.2x) or TEXT, INTEGER RANGE, BOOLEAN (earlier versions), and the range suffix [x>=1].
PYTHON_PLACEHOLDERS = re.compile(r"<[a-z][^<>]*>|\{[A-Za-z_]+\}|\b(TEXT|INTEGER|FLOAT|BOOLEAN|RANGE)\b|\[x[<>]=")


@functools.cache  # a page depends on nothing a test changes; each is read by several tests
def render(command: tuple[str, ...]) -> str:
    result = CliRunner().invoke(app, [*command, "--help"], env={"COLUMNS": "80", "NO_COLOR": "1"})
    assert result.exit_code == 0, result.output
    return ANSI.sub("", result.stdout)


def walk(command, path=()):
    yield path, command
    for name, sub in getattr(command, "commands", {}).items():
        yield from walk(sub, (*path, name))


def name(command: tuple[str, ...]) -> str:
    return " ".join(("carto", *command))


def test_help_text_covers_every_command():
    assert sorted(path for path, _ in walk(typer.main.get_command(app))) == sorted(COMMANDS)


def wrap_breaks(text: str) -> list[str]:
    """Line breaks that rich did not make: rich wraps greedily, so it breaks a line only when the next word does
    not fit in the column. Each column's width is at least its longest line, so a break before a word that would
    have fit within that many characters was in the source text. Checked in the prose outside the panels and in
    each column of each panel, where a continuation line is indented to the column it continues."""
    found = []
    blocks: list[list[str]] = [[]]
    for line in text.splitlines():
        line = line.rstrip()
        if line.startswith(("╭", "╰")) or not line.strip():
            blocks.append([])
        elif line.startswith("│"):
            if blocks[-1] and not blocks[-1][0].startswith("│"):
                blocks.append([])
            blocks[-1].append(line.rstrip("│").rstrip())
        else:
            if blocks[-1] and blocks[-1][0].startswith("│"):
                blocks.append([])
            blocks[-1].append(line)
    for block in blocks:
        indents = [len(line) - len(line.lstrip("│").lstrip()) for line in block]
        rows = 0  # prose: every line continues the one above; a panel: rows begin at or left of its first row's name
        if block and block[0].startswith("│"):
            rows = indents[0]
            if block[0][rows] == "*":  # the required marker's column: names start after it
                rows = len(block[0]) - len(block[0][rows + 1:].lstrip())
        for above, line, x in zip(block, block[1:], indents[1:], strict=False):
            if x <= rows or len(above) <= x or above[x - 1] != " " or above[x] == " ":
                continue
            before, after = above[x:].strip(), line[x:].strip()
            if not before or after.startswith("["):  # typer's own [default: ...] / [required] start a line
                continue
            width = max(len(b[x:]) for b in block if len(b) > x and b[x - 1] == " " and b[x] != " ")
            if len(before) + 1 + len(after.split()[0]) <= width:
                found.append(f"{before!r} / {after!r}")
    return found


@pytest.mark.parametrize("command", COMMANDS, ids=name)
def test_help_text_breaks_no_sentence(command):
    assert wrap_breaks(render(command)) == []


def test_help_text_break_check_finds_a_hand_made_break():
    page = (" The outputs are written as one set (all replaced together or none); an earlier \n"
            " map in the output\n"
            " directory is kept unless --force.\n")
    assert wrap_breaks(page) == ["'map in the output' / 'directory is kept unless --force.'"]
    panel = ("│ --output  -o  DIR   Output directory (default: RECORDING_map next to the       │\n"
             "│                      recording, or NAME_track).                               │\n"
             "│ --profile -p  NAME  auto (the default: settings chosen from                   │\n"
             "│                     the recording).                                           │\n")
    assert wrap_breaks(panel) == ["'auto (the default: settings chosen from' / 'the recording).'"]


@pytest.mark.parametrize("command", COMMANDS, ids=name)
def test_help_text_cuts_no_word(command):
    text = render(command)
    assert "…" not in text, [line for line in text.splitlines() if "…" in line]


@pytest.mark.parametrize("command", COMMANDS, ids=name)
def test_help_text_shows_every_word_it_was_given(command):
    """Rich markup took "[sigma_xy sigma_yaw]" for a style tag and dropped it; a word too long for its column is
    cut. Either way a word of the help is not on the page."""
    (parsed,) = [c for path, c in walk(typer.main.get_command(app)) if path == command]
    shown = set(render(command).replace("│", " ").split())
    given = [parsed.help or "", *(param.help for param in parsed.params if getattr(param, "help", None))]
    assert {word for text in given for word in text.replace("\\[", "[").split()} - shown == set()


@pytest.mark.parametrize("command", COMMANDS, ids=name)
def test_help_text_names_no_python_type(command):
    text = render(command)
    assert [line for line in text.splitlines() if PYTHON_PLACEHOLDERS.search(line)] == []


def test_help_text_describes_every_option_and_argument():
    missing = [f"{name(path)} {param.opts[0] if param.opts else param.name}"
               for path, command in walk(typer.main.get_command(app))
               for param in command.params if not (getattr(param, "help", None) or "").strip()]
    assert missing == []


@pytest.mark.parametrize("command", COMMANDS, ids=name)
def test_help_text_stays_short(command):
    lines = render(command).rstrip().splitlines()
    assert len(lines) <= MAX_LINES.get(" ".join(command), MAX_LINES_OTHERS), "\n".join(lines)


def test_help_text_groups_the_options_of_map():
    text = render(("map",))
    titles = re.findall(r"^╭─ (.+?) ─", text, flags=re.M)
    assert titles[:2] == ["Arguments", "Options"] and {"Input", "Performance"} <= set(titles[2:]), titles
    for panel, option in (("Input", "--scan-topic"), ("Performance", "--memory-budget")):
        section = text.split(f"╭─ {panel} ─", 1)[1].split("╰", 1)[0]
        assert option in section


def test_help_text_sigma_yaw_is_in_radians_as_the_initial_pose(monkeypatch, tmp_path):
    (command,) = [c for path, c in walk(typer.main.get_command(app)) if path == ("relocalize",)]
    helps = {param.opts[0]: param.help for param in command.params if param.opts}
    for option in ("--sigma-yaw", "--initial-pose"):
        assert "rad" in helps[option] and "deg" in helps[option], helps[option]
    assert "degrees)" not in helps["--sigma-yaw"]

    import carto_cli.commands.relocalize as relocalize

    seen = []

    def relocalize_nothing(asked, *args, **kwargs):
        seen.append(getattr(asked, "request", asked).sigma_yaw)  # run_relocalize's RelocalizeScans hold the request
        raise typer.Exit(0)

    monkeypatch.setattr(relocalize, "run_relocalize", relocalize_nothing)
    monkeypatch.setattr(relocalize, "run_track", relocalize_nothing)

    def run(*args):
        # --global: the request the command builds is checked before run_relocalize, and needs a prior or none.
        return CliRunner().invoke(app, ["relocalize", str(tmp_path / "map.carto"), str(tmp_path / "r.bag"), "--global",
                                        *args])

    for args in (("--sigma-yaw", "0.1"), ("--sigma-yaw", "5deg"), ("--sigma-yaw", "5DEG", "--track")):
        assert run(*args).exit_code == 0
    assert seen == pytest.approx([0.1, math.radians(5), math.radians(5)])
    # A bare number above half a turn is no heading uncertainty in radians but most likely degrees, as
    # --sigma-yaw used to take: refused with the fix rather than read as a search of every heading.
    r = run("--sigma-yaw", "5")
    assert r.exit_code == 2 and "5deg" in r.stderr and len(seen) == 3, r.output
