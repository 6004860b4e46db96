"""The README as a new user reads it (issue 42): its quick start is what CI runs, and its examples can be pasted
as they are into a fresh clone."""
import re
import shlex

from support import REPO

README = (REPO / "README.md").read_text()


def sh_blocks(section: str | None = None) -> list[str]:
    text = README if section is None else README.split(f"## {section}", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```sh\n(.*?)\n```", text, flags=re.S)


def test_ci_runs_the_readme_quick_start_in_order():
    """Item 1: `.ci/run` runs the README's two quick-start commands as written, in their order (the first split at
    its `&&`, to list the installed package between install and map), so CI sees what a new user's first five
    minutes do to the install."""
    first, second = sh_blocks("Quick start")
    lines = (REPO / ".ci" / "run").read_text().splitlines()
    order = [lines.index(half) for half in first.split(" && ")] + [
        next(k for k, line in enumerate(lines) if line.startswith(second))]
    assert order == sorted(order)


FILE_SUFFIXES = (".bag", ".mcap", ".clf", ".gz", ".log", ".relations", ".carto", ".pbstream", ".yaml", ".tum",
                 ".lua", ".csv")


def test_readme_examples_use_files_a_fresh_clone_has():
    """Item 11: every file a README example reads is in the repository or written by an example before it (the
    tune example named `recording.bag` and `recording.relations`, which nobody has)."""
    written: list[str] = []
    missing = []
    for block in sh_blocks():
        for line in block.splitlines():
            for command in line.split("&&"):
                argv = shlex.split(command)
                if not argv or argv[0] != "carto":
                    continue
                for flag in ("-o", "--output"):
                    if flag in argv:
                        written.append(argv[argv.index(flag) + 1])
                outputs = set(written[-1:]) if any(f in argv for f in ("-o", "--output")) else set()
                for arg in argv[1:]:
                    if arg in outputs or not arg.endswith(FILE_SUFFIXES):
                        continue
                    if not (REPO / arg).exists() and not any(arg.startswith(w.rstrip("/") + "/") or arg == w
                                                             for w in written):
                        missing.append(f"{line.strip()}: {arg}")
    assert not missing, missing
