"""The layers of docs/ARCHITECTURE.md, checked on the source: no module of ``mpd/`` imports (at the top or inside a
function) a module of a higher layer, except the known uses listed in ``PENDING`` (none today); a pending entry that
no longer occurs fails too, so the list only shrinks."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# lowest first; a module belongs to the longest prefix that names it
LAYERS: tuple[tuple[str, ...], ...] = (
    ("mpd", "mpd.schema", "mpd.paths", "mpd.provenance", "mpd.device"),
    ("mpd.robots",),
    ("mpd.envs",),
    ("mpd.tasks",),
    ("mpd.collision",),
    ("mpd.trajectory",),
    ("mpd.costs",),
    ("mpd.data",),
    ("mpd.models",),
    ("mpd.planners",),
    ("mpd.metrics",),
    ("mpd.experiments",),
    ("mpd.viz",),
    ("mpd.api",),
    ("mpd.bench",),
    ("mpd.cli",),
)
# (importing module, imported layer's package): known exceptions; none since the verbs moved into mpd/cli/
PENDING: set[tuple[str, str]] = set()


def layer_of(module: str) -> tuple[int, str] | None:
    best: tuple[int, str] | None = None
    for i, names in enumerate(LAYERS):
        for n in names:
            if (module == n or module.startswith(n + ".")) and (best is None or len(n) > len(best[1])):
                best = (i, n)
    return best


def upward_imports() -> set[tuple[str, str, str]]:
    """(module, imported module, imported layer's package) of every import of a higher layer."""
    out = set()
    for f in sorted((ROOT / "mpd").rglob("*.py")):
        mod = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        me = layer_of(mod)
        assert me is not None, f"{mod} is in no layer of LAYERS: add it (and to docs/ARCHITECTURE.md)"
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            for name in names:
                other = layer_of(name) if name.startswith("mpd") else None
                if other is not None and other[0] > me[0]:
                    out.add((mod, name, other[1]))
    return out


def test_no_module_imports_a_higher_layer():
    found = upward_imports()
    new = sorted(f"{m} imports {n}" for m, n, pkg in found if (m, pkg) not in PENDING)
    assert not new, "upward imports (see docs/ARCHITECTURE.md): " + "; ".join(new)
    gone = sorted(PENDING - {(m, pkg) for m, _, pkg in found})
    assert not gone, f"no longer imported, remove from PENDING: {gone}"


def test_the_checker_sees_an_upward_import(tmp_path):
    """The walk reads lazy imports inside functions too (the form every upward import here takes)."""
    tree = ast.parse("def f():\n    from mpd.viz.report import build_report\n")
    (node,) = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert layer_of(node.module)[1] == "mpd.viz" and layer_of("mpd.data.dataset")[0] < layer_of(node.module)[0]


def test_the_package_facade_re_exports_the_api_lazily():
    """``mpd/__init__.py`` (lowest layer) names the Python API of ``mpd.api`` and imports it on first use only (by
    ``importlib``, the one deliberate reach upwards): ``import mpd`` stays light, ``mpd.load_planner`` works."""
    import subprocess
    import sys

    code = "import sys, mpd; assert 'mpd.api' not in sys.modules; mpd.load_planner; assert 'mpd.api' in sys.modules"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True).returncode == 0
    import mpd
    import mpd.api

    assert set(mpd._API) <= set(mpd.api.__all__)
    assert all(getattr(mpd, n) is getattr(mpd.api, n) for n in mpd._API)
