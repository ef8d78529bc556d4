"""No module of the project's packages uses another module's private names.

A reader knows from a file's place and name what it holds and what it may touch: a name with a leading underscore
is its module's own. A helper two modules share gets a public name in the module that owns its concept. This scans
the source (ast, nothing imported) for `from x import _name` and `x._name` with `x` an imported project module.
Tests and bench/ may reach into a module; they are not scanned.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("splatstream", "server", "client_gl", "cli", "refine_gpu", "refine_cpu")

# Cross-module private imports not yet given a public name: (importing module, imported module, name). Empty:
# keep it so, or list one here with the reason, and remove it once the import is gone.
KNOWN: set[tuple[str, str, str]] = set()


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_project_module(name: str) -> bool:
    if name.split(".")[0] not in PACKAGES:
        return False
    base = ROOT.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _absolute(module: str | None, level: int, importer: str, is_package: bool) -> str:
    if not level:
        return module or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def private_uses(path: Path) -> list[tuple[str, str, str, int]]:
    """(importing module, imported module, private name, line) of each use of another project module's private
    name in the file at `path`."""
    me = _module_name(path)
    tree = ast.parse(path.read_text(), str(path))
    modules: dict[str, str] = {}  # local name -> the project module it is bound to
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            source = _absolute(node.module, node.level, me, path.name == "__init__.py")
            if not _is_project_module(source):
                continue
            for alias in node.names:
                if _private(alias.name):
                    found.append((me, source, alias.name, node.lineno))
                elif _is_project_module(f"{source}.{alias.name}"):
                    modules[alias.asname or alias.name] = f"{source}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if _is_project_module(alias.name):
                    if alias.asname:
                        modules[alias.asname] = alias.name
                    found += [(me, alias.name, part, node.lineno) for part in alias.name.split(".") if _private(part)]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            # `x._name` and `pkg.mod._name`: the dotted chain of names before the private attribute.
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if not isinstance(value, ast.Name):
                continue
            chain.append(value.id)
            head = modules.get(value.id, value.id)
            target = ".".join([head, *reversed(chain[:-1])])
            if target != me and _is_project_module(target):
                found.append((me, target, node.attr, node.lineno))
    return found


def _scan() -> list[tuple[str, str, str, int]]:
    uses = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            uses += private_uses(path)
    return uses


def test_no_module_uses_another_modules_private_names():
    uses = [u for u in _scan() if u[:3] not in KNOWN]
    assert not uses, "\n".join(f"{me} (line {line}) uses {source}.{name}: give it a public name in the module "
                               f"that owns it" for me, source, name, line in uses)


def test_known_exceptions_still_exist():
    # An entry whose import is gone is removed from KNOWN, so that the list stays the list of what is left.
    assert KNOWN <= {u[:3] for u in _scan()}


def test_the_scan_finds_each_form(tmp_path, monkeypatch):
    # A scanner that finds nothing passes everything: each form it looks for, found in a module made for the test.
    package = tmp_path / "server"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "owner.py").write_text("def _helper():\n    pass\n")
    (package / "user.py").write_text(
        "from . import owner\n"
        "from .owner import _helper\n"
        "import server.owner as own\n"
        "import server.owner\n"
        "owner._helper()\n"
        "own._helper()\n"
        "server.owner._helper()\n"
        "import os\n"
        "os._exit\n"  # not a project module: not this rule's business
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    uses = private_uses(package / "user.py")
    assert sorted(uses) == [("server.user", "server.owner", "_helper", line) for line in (2, 5, 6, 7)]
