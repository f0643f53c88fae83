"""The package tree is the data flow (docs/architecture.md): each subpackage of the engine imports
only itself and those before it, no module imports another inside a function (an edge the reader
cannot see), there is no import cycle, the engine never imports bpy, the add-on uses only public
engine names, and every engine module has its own test module (tests mirror the layout)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ENGINE = ROOT / "ntp_engine"
# the data flow: a package may import only packages at its own position or before it
ORDER = ["io", "scanner", "physics", "learn", "fit", "refine", "register", "pipeline", "sim", "bench", "cli"]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (ROOT / rel.with_suffix(".py")).is_file() or (ROOT / rel / "__init__.py").is_file()


def _imports(path: Path) -> list[tuple[str, bool, list[str]]]:
    """(imported module, inside a function?, names) for every import in ``path``."""
    name = _module_name(path)
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    tree = ast.parse(path.read_text())
    local = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            local.update(id(n) for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, id(node) in local, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = (
                ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
                if node.level
                else node.module
            )
            names = [a.name for a in node.names]
            subs = [f"{base}.{n}" for n in names if _is_module(f"{base}.{n}")]
            out += [(m, id(node) in local, [m.rsplit(".", 1)[1]]) for m in subs]
            rest = [n for n in names if not _is_module(f"{base}.{n}")]
            if rest:
                out.append((base, id(node) in local, rest))
    return out


def _engine_modules() -> list[Path]:
    return sorted(ENGINE.rglob("*.py"))


def _rank(module: str) -> int:
    parts = module.split(".")
    return ORDER.index(parts[1]) if len(parts) > 1 and parts[1] in ORDER else -1


def test_each_package_imports_only_itself_and_earlier_stages():
    wrong = []
    for path in _engine_modules():
        me = _module_name(path)
        for target, _, _ in _imports(path):
            if target.startswith("ntp_engine") and _rank(target) > _rank(me):
                wrong.append(f"{me} -> {target}")
    assert not wrong, "imports against the data flow: " + ", ".join(wrong)


def test_no_function_local_imports_between_engine_modules_and_no_bpy():
    hidden = [
        f"{_module_name(p)} -> {t}"
        for p in _engine_modules()
        for t, local, _ in _imports(p)
        if local and t.startswith("ntp_engine")
    ]
    assert not hidden, "function-local engine imports hide edges: " + ", ".join(hidden)
    bpy = [_module_name(p) for p in _engine_modules() for t, _, _ in _imports(p) if t.split(".")[0] == "bpy"]
    assert not bpy, f"the engine imports bpy: {bpy}"


def test_no_import_cycles():
    graph = {
        _module_name(p): {t for t, _, _ in _imports(p) if t.startswith("ntp_engine") and _is_module(t)}
        for p in _engine_modules()
    }
    state: dict[str, int] = {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if nxt == node or nxt in ("ntp_engine",) or nxt == node.rsplit(".", 1)[0]:
                continue  # a package's own __init__ is loaded first, not an edge back
            if state.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(nxt) :] + [nxt]))
            if nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for module in graph:
        if module not in state:
            visit(module, [module])


def test_the_add_on_uses_public_engine_names_only():
    private = [
        f"{_module_name(p)}: {t}.{n}"
        for p in sorted((ROOT / "ntp_addon").glob("*.py"))
        for t, _, names in _imports(p)
        if t.startswith("ntp_engine")
        for n in names
        if n.startswith("_")
    ]
    assert not private, f"the add-on reaches into private engine names: {private}"


def test_every_engine_module_has_its_own_test_module():
    missing = []
    for path in _engine_modules():
        rel = path.relative_to(ENGINE)
        if path.name == "__init__.py":
            if not any(isinstance(n, (ast.FunctionDef, ast.ClassDef)) for n in ast.parse(path.read_text()).body):
                continue  # a docstring only
            test = ROOT / "tests" / rel.parent / f"test_{rel.parent.name or 'engine'}.py"
        else:
            test = ROOT / "tests" / rel.parent / f"test_{path.stem}.py"
        if not test.is_file():
            missing.append(str(test.relative_to(ROOT)))
    assert not missing, f"engine modules without a test module: {missing}"


def test_only_the_task_pool_imports_ray_and_only_when_entered():
    """Without --ray nothing imports ray: one module may, inside the function that connects."""
    found = [
        (_module_name(p), local) for p in _engine_modules() for t, local, _ in _imports(p) if t.split(".")[0] == "ray"
    ]
    assert found == [("ntp_engine.pipeline.task_pool", True)]


def _code_strings(path: Path) -> list[str]:
    """String constants of ``path`` other than docstrings."""
    tree = ast.parse(path.read_text())
    docs = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    return [
        n.value
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
    ]


def test_the_engine_starts_add_on_scripts_only_through_its_one_entry_point():
    """Only ``io.blender_process`` names an add-on module in code; every script it names exists and
    runs as ``python -m`` (a ``__main__`` guard)."""
    from ntp_engine.io.blender_process import BLENDER_SCRIPTS

    naming = [
        _module_name(p)
        for p in _engine_modules()
        if any("ntp_addon" in s for s in _code_strings(p)) or any(t.startswith("ntp_addon") for t, _, _ in _imports(p))
    ]
    assert naming == ["ntp_engine.io.blender_process"], f"engine modules that start or import the add-on: {naming}"
    for module in BLENDER_SCRIPTS.values():
        path = ROOT / Path(*module.split(".")).with_suffix(".py")
        assert path.is_file(), f"{module}: no such add-on module"
        assert '__name__ == "__main__"' in path.read_text(), f"{module} cannot run as a script"
