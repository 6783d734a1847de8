"""The package boundaries of docs/architecture.md, checked on the source."""
import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parent.parent


def imported_modules(path: pathlib.Path) -> set[str]:
    """Top-level names of every module a file imports; a relative import is resolved against
    the file's package to its top-level package, marked with a leading '.' (`from ..core import
    x` in addon/ and `from ..accel import y` in core/net/ both give '.core')."""
    package = list(path.relative_to(ROOT).parent.parts)
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - (node.level - 1)] if node.level > 1 else package
            parts = base + (node.module.split(".") if node.module else [])
            names.add("." + (parts[0] if parts else ""))
    return names


def sources(package: str):
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"{package}/ has no Python files"
    return files


def test_bpy_is_imported_only_by_the_addon():
    for package in ("core", "slave"):
        for path in sources(package):
            assert "bpy" not in imported_modules(path), f"{path.relative_to(ROOT)} imports bpy"


def test_core_depends_on_neither_addon_nor_slave():
    for path in sources("core"):
        imports = imported_modules(path)
        assert not imports & {"addon", "slave", ".addon", ".slave"}, path.relative_to(ROOT)


def test_addon_reaches_core_relatively_and_never_the_slave():
    for path in sources("addon"):
        imports = imported_modules(path)
        assert "core" not in imports, f"{path.relative_to(ROOT)} imports core absolutely"
        assert not imports & {"slave", ".slave"}, f"{path.relative_to(ROOT)} imports the slave"


def test_nothing_is_unpickled_or_evaluated():
    for package in ("core", "slave", "addon"):
        for path in sources(package):
            tree = ast.parse(path.read_text())
            imports = imported_modules(path)
            assert not imports & {"pickle", "marshal", "shelve"}, path.relative_to(ROOT)
            calls = {n.func.id for n in ast.walk(tree)
                     if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
            assert not calls & {"eval", "exec"}, path.relative_to(ROOT)


def test_kernels_hold_only_opencl_sources():
    files = [p for p in (ROOT / "kernels").rglob("*") if p.is_file()]
    assert files and all(p.suffix in (".cl", ".h") for p in files), files
