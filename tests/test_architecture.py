"""The layout's rules, checked on the source (docs/design.md, "Layout"):

* only the command line (host/cli/) imports the simulator (virtual_sheet);
* protocol/ imports neither pyserial nor python-can, nor any other capsheet package;
* the science (host/analysis/) imports only protocol's pure modules (`PURE_PROTOCOL`: the lattice,
  the constants, the frames' conventions; each imports nothing but the standard library, numpy and
  each other), numpy/scipy/matplotlib (and the optional sksparse, and the per-link peer's vqf) and itself;
* firmware_ref and virtual_sheet do not import each other's chip modules in a cycle;
* no import cycle among capsheet's own modules (function-level imports included);
* seams, not patches: no module of protocol/, host/, virtual_sheet/ reads or writes
  another module's private attribute (``obj._name``), and none reassigns a method of another object;
* the aggregator (and its counter trust and deadline policy) is sans-I/O: it imports no clock and
  no thread; python-can finds the SLCAN bus by name (the ``can.interface`` entry point).
"""

from __future__ import annotations

import ast
import re
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
    assert "host.transport.ports" in imports_of(ROOT / "host/session/core.py")
    assert "host.analysis.estimator.angles" in imports_of(ROOT / "host/analysis/estimator/pipeline.py")  # `from .angles import ...`


def test_only_the_command_line_imports_the_virtual_sheet():
    bad = offenders("host", lambda m: m == "virtual_sheet" or m.startswith("virtual_sheet."),
                    allow_under="host/cli/")
    bad += offenders("protocol", lambda m: m.startswith("virtual_sheet"))
    assert bad == []


@pytest.mark.parametrize("lib", ["serial", "can", "host", "virtual_sheet", "firmware_ref"])
def test_protocol_does_no_io_and_depends_on_nothing_of_ours(lib):
    assert offenders("protocol", lambda m: m == lib or m.startswith(lib + ".")) == []


#: protocol's modules that are pure computation (no I/O, nothing but the standard library and numpy):
#: the conventions defined once there (docs/design.md §2) that the science may import
PURE_PROTOCOL = ("protocol.lattice", "protocol.constants", "protocol.frames", "protocol.files", "protocol.rotations")


def test_the_pure_protocol_modules_import_only_the_standard_library_numpy_and_each_other():
    stdlib = sys.stdlib_module_names
    for mod in PURE_PROTOCOL:
        path = ROOT / (mod.replace(".", "/") + ".py")
        bad = {m for m in imports_of(path)
               if not (m.split(".")[0] in stdlib or m == "numpy" or m.startswith("numpy.") or m in PURE_PROTOCOL)}
        assert bad == set(), f"{mod} imports {bad}"


def test_the_science_imports_only_the_pure_protocol_and_itself():
    # sksparse: the estimator's optional CHOLMOD backend (scipy's splu when absent); cffi: only
    # host/analysis/_kernel/build.py, which builds the estimator's optional kernel at install time
    # (and host/analysis/motion/_kernel/build_link_kernel.py the fused estimator's); vqf: the per-link peer
    # of host/analysis/motion/peers.py (optional, imported when that peer runs)
    allowed = PURE_PROTOCOL + ("host.analysis", "numpy", "scipy", "sksparse", "matplotlib",
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


# ------------------------------------------------------------------- import cycles

PACKAGES = ("protocol", "host", "virtual_sheet", "firmware_ref")


def module_names(root: Path = ROOT) -> dict[str, Path | None]:
    """Our modules: every .py, and the compiled ones each cffi build script names in
    ``set_source`` (leaves, mapped to None), whether or not they are built here — else
    ``from ._link_kernel import lib`` would count as importing the package around it."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            out[".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)] = path
            out.update((m, None) for m in re.findall(r"set_source\(\s*[\"']([\w.]+)[\"']",
                                                     path.read_text(errors="replace")))
    return out


def compiled_modules(root: Path = ROOT) -> set[str]:
    """The C extensions setup.py builds (each cffi builder's ``set_source`` name): modules with no
    .py file and no imports of ours. Without them ``from ._response_kernel import lib`` would
    resolve to the package that holds it, a cycle that does not exist."""
    setup = ast.parse((root / "setup.py").read_text())
    builders = [c.value.split(":")[0] for c in ast.walk(setup)
                if isinstance(c, ast.Constant) and isinstance(c.value, str) and ".py:" in c.value]
    out = set()
    for b in builders:
        tree = ast.parse((root / b).read_text())
        helpers = set()  # functions whose parameter is set_source's name (firmware_ref: _builder(module, ...))
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef):
                continue
            params = [a.arg for a in fn.args.args]
            for node in ast.walk(fn):
                if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "set_source" and node.args \
                        and isinstance(node.args[0], ast.Name) and node.args[0].id in params:
                    helpers.add((fn.name, params.index(node.args[0].id)))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call) or not node.args:
                continue
            if getattr(node.func, "attr", None) == "set_source" and isinstance(node.args[0], ast.Constant):
                out.add(node.args[0].value)
            for name, k in helpers:
                if getattr(node.func, "id", None) == name and len(node.args) > k \
                        and isinstance(node.args[k], ast.Constant):
                    out.add(node.args[k].value)
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the capsheet modules it imports anywhere (module level or inside a function);
    ``from package import name`` counts as importing ``package.name`` when that is a module."""
    mods = module_names(root)
    leaves = compiled_modules(root)
    graph = {}
    for name, path in mods.items():
        if path is None:  # a compiled module imports none of ours
            graph[name] = set()
            continue
        tree = ast.parse(path.read_text(), str(path))
        pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found |= {al.name for al in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = (".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1] + ([node.module] if node.module else []))
                        if node.level else node.module)
                found |= {base} | {f"{base}.{al.name}" for al in node.names}
        edges = set()
        for m in found:
            while m and m not in mods and m not in leaves:
                m = m.rpartition(".")[0]
            if m and m != name:
                edges.add(m)
        graph[name] = edges
    for leaf in leaves:  # a C extension: a leaf, nothing of ours behind it
        graph.setdefault(leaf, set())
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_sees_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_compiled_extensions_are_known_to_the_import_graph():
    # each cffi module of setup.py; the estimator and the tactile response import theirs relatively
    assert compiled_modules() == {"firmware_ref._capsheet_fw", "firmware_ref._capsheet_fw_mutants",
                                  "host.analysis._yaw_kernel", "host.analysis.tactile._response_kernel",
                                  "host.analysis.motion._link_kernel", "protocol._stream_kernel"}
    graph = import_graph()
    assert "protocol._stream_kernel" in graph["protocol.framing"]
    assert "host.analysis.tactile" not in graph["host.analysis.tactile.response"]
    assert "host.analysis.tactile.response" in graph["host.analysis.tactile.fit"]


def test_the_graph_knows_the_compiled_modules_built_or_not():
    # cffi's API-mode extensions are not .py files; read from their build scripts they are leaves
    graph = import_graph()
    for name in ("host.analysis._yaw_kernel", "host.analysis.motion._link_kernel", "firmware_ref._capsheet_fw",
                 "protocol._stream_kernel"):
        assert graph[name] == set()
    assert "host.analysis.motion._link_kernel" in graph["host.analysis.motion._linalg"]
    assert "host.analysis.motion" not in graph["host.analysis.motion._linalg"]


def test_no_import_cycles_among_our_modules():
    # host/transport/slcan.py <-> host/transport/ports.py (FrameBlock lived in the transport module) and
    # virtual_sheet/board.py <-> virtual_sheet/shapes.py (flat_net lived in shapes) were the two
    assert cycles(import_graph()) == []


# ------------------------------------------------------------ seams, not patches

SEAM_PACKAGES = ("protocol", "host", "virtual_sheet")
#: namedtuple's documented methods (underscored so as not to clash with field names)
NAMEDTUPLE_API = {"_replace", "_asdict", "_fields", "_make", "_field_defaults"}


def _private(name: str) -> bool:
    """A private name: one leading underscore; not a dunder, not an enum's sunder (``_value_``)."""
    return name.startswith("_") and not name.endswith("_") and name not in NAMEDTUPLE_API


def _annotations(tree) -> set[int]:
    """ids of the nodes inside annotations (they name types; nothing is accessed at run time)."""
    out = set()
    for node in ast.walk(tree):
        anns = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            anns = [a.annotation for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs] + [node.returns]
            anns += [a.annotation for a in (node.args.vararg, node.args.kwarg) if a is not None]
        elif isinstance(node, ast.AnnAssign):
            anns = [node.annotation]
        for ann in anns:
            if ann is not None:
                out |= {id(n) for n in ast.walk(ann)}
    return out


def defined_privates(tree) -> set[str]:
    """Private names a module defines: functions, classes, module or local names, arguments,
    attributes it assigns (``x._a = ...``, ``object.__setattr__(self, "_a", ...)``), __slots__."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            out.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            out.add(node.id)
        elif isinstance(node, ast.arg):
            out.add(node.arg)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "__setattr__" and len(node.args) >= 2 \
                and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str):
            out.add(node.args[1].value)
        elif isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__slots__" for t in node.targets):
            out |= {c.value for c in ast.walk(node.value) if isinstance(c, ast.Constant) and isinstance(c.value, str)}
    return {n for n in out if _private(n)}


def private_access_offenders(root: Path = ROOT) -> list[str]:
    """Every ``obj._name`` (and ``getattr(obj, "_name")``) whose private name the module does not
    define itself: another module's private attribute (an inherited one through ``self`` too)."""
    bad = []
    for pkg in SEAM_PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            own = defined_privates(tree)
            skip = _annotations(tree)
            rel = path.relative_to(root).as_posix()
            for node in ast.walk(tree):
                name = None
                if isinstance(node, ast.Attribute) and _private(node.attr) and id(node) not in skip:
                    name = node.attr
                elif isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("getattr", "setattr", "hasattr") \
                        and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) \
                        and isinstance(node.args[1].value, str) and _private(node.args[1].value):
                    name = node.args[1].value
                if name is not None and name not in own:
                    bad.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    return bad


def method_patch_offenders(root: Path = ROOT) -> list[str]:
    """Every ``obj.name = <a function>`` (obj not ``self``/``cls``; the value a lambda or a function
    the module defines) where ``name`` is a method of one of our classes: one object rewiring
    another's behaviour (a monkeypatch)."""
    methods = set()
    trees = {}
    for pkg in SEAM_PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            trees[path] = tree = ast.parse(path.read_text(), str(path))
            for cls in (n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)):
                methods |= {f.name for f in cls.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                            and not any(getattr(d, "id", None) == "property" or getattr(d, "attr", None) == "setter"
                                        for d in f.decorator_list)}
    bad = []
    for path, tree in trees.items():
        functions = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        for node in ast.walk(tree):
            if not isinstance(node, ast.Assign):
                continue
            v = node.value
            if not (isinstance(v, ast.Lambda) or (isinstance(v, ast.Name) and v.id in functions)):
                continue
            for t in node.targets:
                if isinstance(t, ast.Attribute) and t.attr in methods and not (
                        isinstance(t.value, ast.Name) and t.value.id in ("self", "cls")):
                    bad.append(f"{path.relative_to(root).as_posix()}:{node.lineno}: {ast.unparse(t)} = ...")
    return bad


def test_the_seam_checks_see_what_they_look_for(tmp_path):
    # the checkers on a miniature tree: another module's private read, an inherited private used
    # through self, a method reassigned on another object; the module's own privates are fine
    (tmp_path / "host").mkdir()
    (tmp_path / "host" / "a.py").write_text(
        "class A:\n    def __init__(self):\n        self._x = 1\n    def go(self):\n        return self._x\n")
    (tmp_path / "host" / "b.py").write_text(
        "from host.a import A\nclass B(A):\n    def go(self):\n        return self._x\n"
        "def use(a: 'A._Hint'):\n    a.go = lambda: 0\n    return a._x + getattr(a, '_x')\n"
        "def later(a):\n    def go():\n        return 1\n    a.go = go\n    a.n = 2\n")
    for pkg in ("protocol", "virtual_sheet"):
        (tmp_path / pkg).mkdir()
    assert private_access_offenders(tmp_path) == ["host/b.py:4: self._x", "host/b.py:7: a._x",
                                                  "host/b.py:7: getattr(a, '_x')"]
    assert method_patch_offenders(tmp_path) == ["host/b.py:6: a.go = ...", "host/b.py:11: a.go = ..."]


def test_no_module_reads_another_modules_private_attributes():
    # on the code before these seams: CanTransport._decode reused by replay and patched by the
    # recorder, AuditedCanTransport's _bus/_can/_send_lock, aggregator._lut, host._round,
    # dec._partial, slcanBus's _queue/_filters/_buffer, devices' _pty_* ... (34 offenders)
    assert private_access_offenders() == []


def test_no_module_reassigns_another_objects_methods():
    # before these seams: aggregator.ingest, aggregator.open_counter and transport._decode were patched
    assert method_patch_offenders() == []


@pytest.mark.parametrize("part", ["host/snapshots/aggregator.py", "host/snapshots/counter_trust.py", "host/snapshots/deadline.py"])
def test_the_aggregator_reads_no_clock_and_starts_no_thread(part):
    # sans-I/O (docs/design.md §8): now is passed in; the lock, clock and queue are host/snapshots/feed.py's;
    # its counter trust and deadline policy are told counters and latencies, and read no clock either
    assert not imports_of(ROOT / part) & {"time", "threading", "queue", "asyncio"}


def test_python_can_finds_capsheets_buses_by_name():
    import tomllib
    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["can.interface"]
    assert eps == {"capsheet_slcan": "host.transport.slcan:SlcanBus",
                   "capsheet_udp_multicast": "host.transport.udp_multicast:IsolatedUdpMulticastBus"}


# ---------------------------------------------------- no reach into another's or a library's names

#: Enum's documented sunder names (the enum module's docs, "Supported _sunder_ names"); the rest
#: (``_value2member_map_``, ``_member_map_``, ...) are its internals
ENUM_API = {"_name_", "_value_", "_missing_", "_ignore_", "_order_", "_generate_next_value_", "_add_alias_",
            "_add_value_alias_"}


def foreign_reach_offenders(root: Path = ROOT) -> list[str]:
    """What `private_access_offenders` lets pass and is a reach all the same:

    * an enum's undocumented internals (``MsgType._value2member_map_``);
    * a library's private name through its module, even in an annotation (``argparse._ArgumentGroup``);
    * a private attribute set on another object (``other._state = ...``, anything but ``self`` or
      ``cls``), even another instance of the module's own class: it changes state its owner keeps
      through its own methods;
    * a private name imported from another module (``from .base import _check``): a helper two
      modules share is public to its package."""
    bad = []
    for pkg in SEAM_PACKAGES + ("firmware_ref",):
        for path in sorted((root / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            rel = path.relative_to(root).as_posix()
            modules = {al.asname or al.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
                       for al in n.names}
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom):
                    bad += [f"{rel}:{node.lineno}: from {'.' * node.level}{node.module or ''} import {al.name}"
                            for al in node.names if al.name.startswith("_") and not al.name.startswith("__")]
                    continue
                if not isinstance(node, ast.Attribute) or not node.attr.startswith("_") or node.attr.startswith("__"):
                    continue
                where = f"{rel}:{node.lineno}: {ast.unparse(node)}"
                if node.attr.endswith("_") and node.attr not in ENUM_API:
                    bad.append(where)
                elif isinstance(node.value, ast.Name) and node.value.id in modules and not node.attr.endswith("_"):
                    bad.append(where)
                elif isinstance(node.ctx, ast.Store) and not node.attr.endswith("_") and not (
                        isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                    bad.append(where)
    return sorted(bad, key=lambda w: (w.split(":")[0], int(w.split(":")[1])))


def test_the_reach_check_sees_what_it_looks_for(tmp_path):
    for pkg in ("protocol", "virtual_sheet", "firmware_ref"):
        (tmp_path / pkg).mkdir()
    (tmp_path / "host").mkdir()
    (tmp_path / "host" / "a.py").write_text(
        "import argparse\nimport enum\n"
        "class A:\n    def __init__(self):\n        self._x = 1\n    def copy(self, other):\n        other._x = 2\n"
        "def f(g: argparse._ArgumentGroup, m: enum.Enum, b):\n    b._state = 1\n    return 1 in m._value2member_map_\n"
        "class E(enum.IntEnum):\n    A = 1\n    @classmethod\n    def _missing_(cls, v):\n        return cls.A\n"
        "from .b import _helper, __version__\n")
    assert foreign_reach_offenders(tmp_path) == [
        "host/a.py:7: other._x", "host/a.py:8: argparse._ArgumentGroup", "host/a.py:9: b._state",
        "host/a.py:10: m._value2member_map_", "host/a.py:16: from .b import _helper"]


def test_no_module_reaches_into_another_objects_or_a_librarys_private_names():
    assert foreign_reach_offenders() == []
