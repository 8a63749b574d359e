"""docs/architecture.md's layout names every package and module of ``cellctl/``, ``drivers/`` and
``analysis/`` where it lives, and names no module that is not there; README.md's layout names every
package. A module added, moved or removed without its line in the docs fails here.

The layout is the first code block under ``## Layout``: an entry starts at column 0 with a path
(``cellctl/``, ``drivers/abb_egm/``), a sub-entry at column 2 with a name (``api/``, ``cli.py,
__main__.py``), and deeper-indented lines continue the entry above them. A module
``<dir>/<name>.py`` is named when ``<name>.py`` stands in the entry of ``<dir>``: the sub-entry
``<dir>`` for a sub-package, or the top entry ``<dir>`` with its sub-entries that are not folders;
or when ``<dir>/<name>.py`` is written out from the repository root anywhere (``drivers/runtime.py``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
ROOTS = ("cellctl", "drivers", "analysis")
#: a file name in prose: ``keys.py``, ``__main__.py``, ``drivers/runtime.py``
_MODULE_TOKEN = re.compile(r"(?<![\w./])((?:[\w]+/)*[\w]+\.py)\b")


@dataclass
class Entry:
    """One entry of the layout: its folder (``cellctl/api/``; a file entry's folder is its parent)
    and its text (the entry's lines, continuation lines included)."""

    path: str
    is_folder: bool
    text: list[str] = field(default_factory=list)


def layout_block(markdown: str) -> list[str]:
    """The lines of the first fenced block after ``## Layout``."""
    after = markdown.split("\n## Layout", 1)[1]
    return after.split("```", 2)[1].split("\n")[1:]


def layout_entries(lines: list[str]) -> list[Entry]:
    """The entries of a layout block, sub-entries with their full folder (``cellctl/`` + ``api/``);
    a file's entry (``drivers/runtime.py``, ``  config.py``) has the folder that holds it."""
    entries: list[Entry] = []
    top = ""
    for line in lines:
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip(" "))
        head = line.strip().split()[0].rstrip(",")
        is_folder = head.endswith("/")
        if indent == 0:
            top = head if is_folder else head.rpartition("/")[0] + "/"
            entries.append(Entry(top, is_folder, [line]))
        elif indent == 2 and entries:
            entries.append(Entry(top + head if is_folder else top, is_folder, [line]))
        elif entries:
            entries[-1].text.append(line)
    return entries


def _tokens(entry: Entry) -> list[str]:
    return [t for line in entry.text for t in _MODULE_TOKEN.findall(line)]


def modules_named(entries: list[Entry], folder: str) -> set[str]:
    """File names the layout gives for ``folder`` (``cellctl/api/``): the bare ``name.py`` of the
    entries of ``folder``, and every ``folder/name.py`` written from the repository root."""
    found: set[str] = set()
    for e in entries:
        for t in _tokens(e):
            if "/" not in t and e.path == folder:
                found.add(t)
            elif t.rpartition("/")[0] + "/" == folder:
                found.add(t.rpartition("/")[2])
    return found


def source_tree() -> dict[str, set[str]]:
    """Folder (``cellctl/api/``) -> its module file names, for every folder holding Python."""
    tree: dict[str, set[str]] = {}
    for root in ROOTS:
        for p in sorted((REPO / root).rglob("*.py")):
            if "__pycache__" in p.parts or p.name == "__init__.py":
                continue
            folder = str(p.parent.relative_to(REPO)) + "/"
            tree.setdefault(folder, set()).add(p.name)
        for d in sorted((REPO / root).rglob("*")):
            if d.is_dir() and d.name != "__pycache__" and any(d.glob("*.py")):
                tree.setdefault(str(d.relative_to(REPO)) + "/", set())
    return tree


def missing_from(markdown: str, tree: dict[str, set[str]]) -> list[str]:
    """What ``markdown``'s layout leaves out of ``tree``: each folder without an entry, each module
    its folder's entry does not name."""
    entries = layout_entries(layout_block(markdown))
    folders = {e.path for e in entries if e.is_folder}
    out = []
    for folder, names in sorted(tree.items()):
        if folder.count("/") > 1 and folder not in folders:  # a root itself may be described in prose
            out.append(f"{folder}: no entry")
        out += [
            f"{folder}{n}: not named in {folder}'s entry"
            for n in sorted(names - modules_named(entries, folder))
        ]
    return out


def stale_in(markdown: str, tree: dict[str, set[str]]) -> list[str]:
    """Modules ``markdown``'s layout names under ``cellctl/``, ``drivers/``, ``analysis/`` that are
    not in their entry's folder (a module described in the wrong place, or gone)."""
    out = []
    for e in layout_entries(layout_block(markdown)):
        for token in _tokens(e):
            where = token if "/" in token else e.path + token
            if not where.startswith(tuple(f"{r}/" for r in ROOTS)):
                continue
            folder, _, name = where.rpartition("/")
            if name not in tree.get(folder + "/", set()):
                out.append(f"{e.path}: names {token}, which is not {where}")
    return out


@pytest.fixture(scope="module")
def architecture() -> str:
    return (REPO / "docs" / "architecture.md").read_text(encoding="utf-8")


def test_architecture_doc_names_every_package_and_module(architecture: str) -> None:
    missing = missing_from(architecture, source_tree())
    assert not missing, "docs/architecture.md's layout misses:\n" + "\n".join(missing)


def test_architecture_doc_names_no_module_outside_its_folder(architecture: str) -> None:
    stale = stale_in(architecture, source_tree())
    assert not stale, "docs/architecture.md's layout:\n" + "\n".join(stale)


def test_readme_layout_names_every_package() -> None:
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    text = "\n".join(layout_block(readme))
    entries = layout_entries(layout_block(readme))
    missing = []
    for folder in sorted(source_tree()):
        top = max((e.path for e in entries if e.path and folder.startswith(e.path)), key=len, default="")
        rest = folder.removeprefix(top)
        if rest and not re.search(rf"(?<![\w/]){re.escape(rest)}", text):
            missing.append(folder)
    assert not missing, "README.md's layout misses the packages " + ", ".join(missing)


# ------------------------------------------------------------------ the checks on planted layouts

PLANTED = """# x

## Layout

```
cellctl/                  the cell
  cli.py, __main__.py     the command
  config.py               cell.toml
  api/                    the contract: keys.py (keys), models.py
  daemon/                 the service (service.py) and jobs.py
  hmi/                    server.py, history.py (the plate history)

drivers/abb_egm/          ABB: codec.py
  sim/                    egm.py; see drivers/runtime.py
tests/                    test_x.py
```
"""
PLANTED_TREE = {
    "cellctl/": {"cli.py", "__main__.py", "config.py"},
    "cellctl/api/": {"keys.py", "models.py", "session.py"},
    "cellctl/daemon/": {"service.py", "jobs.py", "history.py"},
    "cellctl/hmi/": {"server.py"},
    "drivers/abb_egm/": {"codec.py"},
    "drivers/abb_egm/sim/": {"egm.py"},
    "drivers/": {"runtime.py"},
    "drivers/sim/": {"fault_channel.py"},
}


def test_check_finds_a_missing_module_and_a_missing_package() -> None:
    assert missing_from(PLANTED, PLANTED_TREE) == [
        "cellctl/api/session.py: not named in cellctl/api/'s entry",
        "cellctl/daemon/history.py: not named in cellctl/daemon/'s entry",
        "drivers/sim/: no entry",
        "drivers/sim/fault_channel.py: not named in drivers/sim/'s entry",
    ]


def test_check_finds_a_module_named_in_the_wrong_folder() -> None:
    assert stale_in(PLANTED, PLANTED_TREE) == [
        "cellctl/hmi/: names history.py, which is not cellctl/hmi/history.py",
    ]


def test_check_passes_a_layout_that_names_everything_where_it_lives() -> None:
    fixed = PLANTED.replace("and jobs.py", "and jobs.py, history.py").replace(
        "history.py (the plate history)", "link.py"
    )
    fixed = fixed.replace("models.py\n", "models.py, session.py\n").replace(
        "tests/", "drivers/sim/              fault_channel.py\ntests/"
    )
    tree = {**PLANTED_TREE, "cellctl/hmi/": {"server.py", "link.py"}}
    assert missing_from(fixed, tree) == [] and stale_in(fixed, tree) == []
