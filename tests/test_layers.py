"""The package's layers, checked on its source (AST, no import): one-way imports, libsumo only in
:mod:`magail_sumo.sim`, the bundle layout in one place."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("magail_sumo", "converters")

#: bottom layer: the scene model, the SUMO session and shared helpers
BOTTOM = ("magail_sumo.errors", "magail_sumo.outputs", "magail_sumo.config",
          "magail_sumo.workers", "magail_sumo.scene", "magail_sumo.sim")
#: top-layer packages that must not import training code: evaluating a policy needs no trainer
#: (a trained policy's loader is found through the agents registry's lazy entry points)
NO_TRAINING = ("magail_sumo.evaluation", "magail_sumo.agents", "magail_sumo.env",
               "magail_sumo.sensors", "magail_sumo.expert", "magail_sumo.models")


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT)
            if "protos" in rel.parts:  # generated protobuf code
                continue
            yield rel.as_posix(), ast.parse(path.read_text(encoding="utf-8"), str(rel))


def _module_name(rel: str) -> str:
    name = rel[:-3].replace("/", ".")
    return name[:-len(".__init__")] if name.endswith(".__init__") else name


def _imports(rel: str, tree: ast.Module) -> list[tuple[str, int]]:
    """(absolute module name, line) of every import in ``tree`` (lazy ones included)."""
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
            out += [(f"{base}.{a.name}", node.lineno) for a in node.names]
    return out


def _under(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def test_libsumo_is_imported_only_by_the_sim_layer():
    found = []
    for rel, tree in _modules():
        if rel.startswith("magail_sumo/sim/"):
            continue
        found += [f"{rel}:{line}: {name}" for name, line in _imports(rel, tree)
                  if _under(name, ("libsumo", "traci"))]
    assert not found, "import SUMO through magail_sumo.sim.session.SumoSession:\n" + \
        "\n".join(found)


def test_evaluation_and_agents_import_no_training():
    found = []
    for rel, tree in _modules():
        if _under(_module_name(rel), NO_TRAINING):
            found += [f"{rel}:{line}: {imp}" for imp, line in _imports(rel, tree)
                      if _under(imp, ("magail_sumo.training",))]
    assert not found, "imports of training code:\n" + "\n".join(found)


def test_imports_go_one_way():
    """Bottom (scene model, session, helpers) < converters < everything else."""
    found = []
    for rel, tree in _modules():
        name = _module_name(rel)
        if _under(name, BOTTOM):
            allowed = BOTTOM
        elif _under(name, ("converters",)):
            allowed = BOTTOM + ("converters",)
        else:
            continue
        found += [f"{rel}:{line}: {imp}" for imp, line in _imports(rel, tree)
                  if _under(imp, PACKAGES) and imp != "magail_sumo" and not _under(imp, allowed)]
    assert not found, "an import against the layers:\n" + "\n".join(found)


def test_bundle_layout_is_defined_once():
    """Only converters/sumo/bundle.py spells a bundle's file names; writer and readers use
    :class:`converters.sumo.bundle.BundleLayout` (``SceneBundle.files``) and ``REPORT_FILE``."""
    spelled = []
    for rel, tree in _modules():
        if rel == "converters/sumo/bundle.py":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                    node.value in ("conversion.json", ".rou.xml", ".tll.xml", ".net.xml"):
                spelled.append(f"{rel}:{node.lineno}: {node.value!r}")
    assert not spelled, "use converters.sumo.bundle (BundleLayout, REPORT_FILE):\n" + \
        "\n".join(spelled)
