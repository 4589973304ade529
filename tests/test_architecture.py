"""The layout's rules, checked on the source (docs/design.md, "Layout"):

* only the command line (host/cli/) imports the simulator (virtual_sheet);
* protocol/ imports neither pyserial nor python-can, nor any other capsheet package;
* the science (host/analysis/) imports only protocol.lattice, numpy/scipy/matplotlib (and the
  optional sksparse, and the per-link peer's vqf) and itself;
* firmware_ref and virtual_sheet do not import each other's chip modules in a cycle.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imports_of(path: Path) -> set[str]:
    """Every module an import statement in ``path`` names (absolute; relative ones resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            out.add(mod)
    return out


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def offenders(package: str, forbidden, *, allow_under: str | None = None) -> list[str]:
    bad = []
    for path in sources(package):
        rel = path.relative_to(ROOT).as_posix()
        if allow_under and rel.startswith(allow_under):
            continue
        for mod in imports_of(path):
            if forbidden(mod):
                bad.append(f"{rel} imports {mod}")
    return bad


def test_imports_are_resolved_from_the_source():
    # the checker itself: a file that imports the simulator is seen doing so
    assert "virtual_sheet.sheet" in imports_of(ROOT / "host/cli/demo.py")
    assert "host.transport" in imports_of(ROOT / "host/session.py")  # `from .transport import ...`


def test_only_the_command_line_imports_the_virtual_sheet():
    bad = offenders("host", lambda m: m == "virtual_sheet" or m.startswith("virtual_sheet."),
                    allow_under="host/cli/")
    bad += offenders("protocol", lambda m: m.startswith("virtual_sheet"))
    assert bad == []


@pytest.mark.parametrize("lib", ["serial", "can", "host", "virtual_sheet", "firmware_ref"])
def test_protocol_does_no_io_and_depends_on_nothing_of_ours(lib):
    assert offenders("protocol", lambda m: m == lib or m.startswith(lib + ".")) == []


def test_the_science_imports_only_the_lattice_and_itself():
    # sksparse: the estimator's optional CHOLMOD backend (scipy's splu when absent); cffi: only
    # host/analysis/_kernel/build.py, which builds the estimator's optional kernel at install time
    # (and host/analysis/motion/_kernel/build.py the fused estimator's); vqf: the per-link peer
    # of host/analysis/motion/peers.py (optional, imported when that peer runs)
    allowed = ("protocol.lattice", "host.analysis", "numpy", "scipy", "sksparse", "matplotlib",
               "__future__", "cffi", "vqf")
    stdlib = sys.stdlib_module_names

    def forbidden(m: str) -> bool:
        return not (m.split(".")[0] in stdlib or any(m == a or m.startswith(a + ".") for a in allowed))

    assert offenders("host/analysis", forbidden) == []


def test_the_two_chip_implementations_share_a_neutral_interface_not_each_other():
    # both import protocol.chip_interface; neither imports the other package
    assert offenders("firmware_ref", lambda m: m.startswith("virtual_sheet")) == []
    assert offenders("virtual_sheet", lambda m: m.startswith("firmware_ref")) == []
    assert "protocol.chip_interface" in imports_of(ROOT / "firmware_ref/chip.py")
    assert "protocol.chip_interface" in imports_of(ROOT / "virtual_sheet/chip.py")


def test_conventions_are_cited_from_the_repo_not_from_outside_it():
    # docs/design.md holds the conventions; a clone has no ../shared/DESIGN.md
    assert (ROOT / "docs/design.md").is_file()
    bad = []
    for pattern in ("*.py", "*.md", "*.c", "*.h"):
        for path in ROOT.rglob(pattern):
            rel = path.relative_to(ROOT).as_posix()
            if rel.startswith((".venv/", "build/")) or "/." in "/" + rel:
                continue
            text = path.read_text(errors="replace")
            if "DESIGN.md" in text.replace("docs/design.md", ""):
                bad.append(rel)
    bad = [b for b in bad if b != "tests/test_architecture.py"]
    assert bad == []
