"""The package's layers, checked on its source (AST, no import): every import, at module level or
inside a function, and every ``"package.module[:attr]"`` string points down or within its own
package, never up; no cycle between packages; few function-level imports, each with its reason;
libsumo only in :mod:`magail_sumo.sim`; the bundle layout in one place."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("magail_sumo", "converters")

#: every package, bottom first: a module may import its own package and those before it.
#: Helpers and the scene model at the bottom, then the libsumo session, the converters, the
#: array layers (sensors, networks), the envs, the agents that drive them, expert data,
#: training, the shipped policies, policies by spec (checkpoints are rebuilt by the training
#: code), evaluation, and the command line on top.
LAYERS = (
    "magail_sumo",  # the root package: its version only
    "magail_sumo.errors",
    "magail_sumo.inputs",
    "magail_sumo.outputs",
    "magail_sumo.config",
    "magail_sumo.splits",
    "magail_sumo.workers",
    "magail_sumo.scene",
    "magail_sumo.sim",
    "converters.files",
    "converters.tfrecord",
    "converters.womd",
    "converters.scenarionet",
    "converters.gpudrive",
    "converters.scene_files",
    "converters.sumo",
    "converters",
    "magail_sumo.sensors",
    "magail_sumo.models",
    "magail_sumo.env",
    "magail_sumo.agents",
    "magail_sumo.expert",
    "magail_sumo.training",
    "magail_sumo.pretrained",
    "magail_sumo.policies",
    "magail_sumo.evaluation",
    "magail_sumo.cli",
    "magail_sumo.__main__",
)
RANK = {name: i for i, name in enumerate(LAYERS)}
#: the largest share of internal imports that may sit inside functions
MAX_LAZY_SHARE = 0.05
#: a function-level import says why, on its line or in a comment atop its run of imports:
#: ``# lazy: <reason>``
LAZY_REASON = re.compile(r"#\s*lazy:\s*\S")
#: a string naming one of our modules (an entry point, ``module:function``)
ENTRY = re.compile(r"^(magail_sumo|converters)(\.\w+)+(:\w+)?$")


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if "protos" in rel.parts:  # generated protobuf code
                continue
            text = path.read_text(encoding="utf-8")
            yield rel.as_posix(), ast.parse(text, str(rel)), text.splitlines()


def _module_name(rel: str) -> str:
    name = rel[:-3].replace("/", ".")
    return name[:-len(".__init__")] if name.endswith(".__init__") else name


def _package(name: str) -> str:
    """The :data:`LAYERS` entry a module belongs to (the longest that prefixes it)."""
    best = ""
    for layer in LAYERS:
        if (name == layer or name.startswith(layer + ".")) and len(layer) > len(best):
            best = layer
    if best == "magail_sumo" and name != "magail_sumo":
        raise AssertionError(f"{name}: a package missing from LAYERS (add it where it belongs)")
    return best


def _function_lines(tree: ast.Module) -> set[int]:
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines |= {sub.lineno for sub in ast.walk(node)
                      if isinstance(sub, (ast.Import, ast.ImportFrom))}
    return lines


def _imports(rel: str, tree: ast.Module) -> list[tuple[str, int]]:
    """(absolute module name, line) of every import statement in ``tree`` (lazy ones included;
    ``from a import b`` gives ``a``)."""
    here = _module_name(rel).split(".")
    if not rel.endswith("__init__.py"):
        here = here[:-1]  # the module's package
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(here[:len(here) - node.level + 1] + ([node.module] if node.module
                                                                       else []))
            else:
                base = node.module or ""
            out.append((base, node.lineno))
    return out


def _internal(name: str) -> bool:
    return name.split(".")[0] in PACKAGES


def _entry_points(tree: ast.Module) -> list[tuple[str, int]]:
    return [(node.value.partition(":")[0], node.lineno) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and ENTRY.match(node.value)]


def _edges():
    """(importing package, imported package, where) of every internal import and entry point."""
    for rel, tree, _ in _modules():
        src = _package(_module_name(rel))
        for name, line in _imports(rel, tree) + _entry_points(tree):
            if _internal(name):
                yield src, _package(name), f"{rel}:{line}: {name}"


def test_every_import_and_entry_point_points_down():
    up = [f"{where} ({src} may not import {dst}: above it in LAYERS)"
          for src, dst, where in _edges() if RANK[dst] > RANK[src]]
    assert not up, "imports against the layers:\n" + "\n".join(up)


def test_no_cycle_between_packages():
    graph: dict[str, set[str]] = {}
    for src, dst, _ in _edges():
        if src != dst:
            graph.setdefault(src, set()).add(dst)
    seen: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(node: str, path: list[str]) -> list[str] | None:
        seen[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if seen.get(nxt) == 1:
                return path + [node, nxt]
            if nxt not in seen:
                found = visit(nxt, path + [node])
                if found:
                    return found
        seen[node] = 2
        return None

    for start in sorted(graph):
        if start not in seen:
            cycle = visit(start, [])
            assert cycle is None, "a cycle between packages: " + " -> ".join(cycle)


def _says_why(lines: list[str], line: int) -> bool:
    """Whether the import at ``line`` (1-based) or a line above it in the same run of imports,
    comments and blank lines carries ``# lazy: <reason>``."""
    k = line - 1
    while k >= 0:
        text = lines[k].strip()
        if LAZY_REASON.search(text):
            return True
        if k < line - 1 and not (text == "" or text.startswith(("from ", "import ", "#"))
                                 or text.endswith((",", ")"))):
            return False
        k -= 1
    return False


def test_function_level_imports_are_few_and_say_why():
    total, lazy, silent = 0, [], []
    for rel, tree, lines in _modules():
        inside = _function_lines(tree)
        for name, line in _imports(rel, tree):
            if not _internal(name):
                continue
            total += 1
            if line in inside:
                lazy.append(f"{rel}:{line}: {name}")
                if not _says_why(lines, line):
                    silent.append(f"{rel}:{line}: {name}")
    assert not silent, ("a function-level import without '# lazy: <reason>' on its line or the "
                        "line above:\n" + "\n".join(silent))
    assert len(lazy) <= MAX_LAZY_SHARE * total, (
        f"{len(lazy)} of {total} internal imports sit inside functions (at most "
        f"{MAX_LAZY_SHARE:.0%}):\n" + "\n".join(lazy))


def test_layer_checks_see_function_level_imports_and_entry_points():
    """The checks above read imports inside functions and ``module:function`` strings too (on a
    source the layers refuse both ways)."""
    tree = ast.parse("def f():\n    from magail_sumo.training import trainer\n"
                     "LOADER = 'magail_sumo.policies.registry:make_policy'\n")
    rel = "magail_sumo/env/x.py"
    names = [n for n, _ in _imports(rel, tree) + _entry_points(tree)]
    assert names == ["magail_sumo.training", "magail_sumo.policies.registry"]
    assert all(RANK[_package(n)] > RANK[_package("magail_sumo.env.x")] for n in names)
    assert _function_lines(tree) == {2}


def test_libsumo_is_imported_only_by_the_sim_layer():
    found = []
    for rel, tree, _ in _modules():
        if rel.startswith("magail_sumo/sim/"):
            continue
        found += [f"{rel}:{line}: {name}" for name, line in _imports(rel, tree)
                  if name.split(".")[0] in ("libsumo", "traci")]
    assert not found, "import SUMO through magail_sumo.sim.session.SumoSession:\n" + \
        "\n".join(found)


def test_bundle_layout_is_defined_once():
    """Only converters/sumo/bundle.py spells a bundle's file names; writer and readers use
    :class:`converters.sumo.bundle.BundleLayout` (``SceneBundle.files``) and ``REPORT_FILE``."""
    spelled = []
    for rel, tree, _ in _modules():
        if rel == "converters/sumo/bundle.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                    node.value in ("conversion.json", ".rou.xml", ".tll.xml", ".net.xml"):
                spelled.append(f"{rel}:{node.lineno}: {node.value!r}")
    assert not spelled, "use converters.sumo.bundle (BundleLayout, REPORT_FILE):\n" + \
        "\n".join(spelled)
