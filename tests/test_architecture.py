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


CORE_ORDER = ("accel", "scene", "net", "frame")   # each imports only those before it


def core_packages_imported(path: pathlib.Path) -> set[str]:
    """The packages of core/ (CORE_ORDER's names, or "" for core's own modules) that a file in
    core/ imports, relatively or as `core.<package>`."""
    package = list(path.relative_to(ROOT).parent.parts)
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package[:len(package) - (node.level - 1)]
            parts = base + (node.module.split(".") if node.module else [])
        elif isinstance(node, ast.ImportFrom) and node.module.startswith("core"):
            parts = node.module.split(".")
        else:
            continue
        if parts[:1] == ["core"]:
            sub = parts[1] if len(parts) > 1 else ""
            found.add(sub if sub in CORE_ORDER else "")
    return found


def test_core_packages_import_in_pipeline_order():
    """accel <- scene <- net <- frame (core/__init__.py); core's own modules (layout, opencl,
    denoise, npz_folder) import none of the packages."""
    for path in sources("core"):
        parts = path.relative_to(ROOT / "core").parts
        own = parts[0] if len(parts) > 1 else ""
        allowed = {""} | (set(CORE_ORDER[:CORE_ORDER.index(own) + 1]) if own else set())
        imported = core_packages_imported(path)
        assert imported <= allowed, f"{path.relative_to(ROOT)} imports core/{imported - allowed}"


def defined_names(path: pathlib.Path) -> set[str]:
    """Classes and functions defined at the top of a module."""
    return {node.name for node in ast.parse(path.read_text(), str(path)).body
            if isinstance(node, (ast.ClassDef, ast.FunctionDef))}


def test_the_addon_holds_no_frame_logic():
    """The frame pipeline lives in core/frame (it runs without Blender); the add-on imports it
    and defines none of it again."""
    frame = set().union(*(defined_names(p) for p in sources("core/frame")))
    for path in sources("addon"):
        again = defined_names(path) & frame
        assert not again, f"{path.relative_to(ROOT)} defines {again}, which core/frame has"
    render = (ROOT / "addon" / "render.py").read_text()
    assert "from ..core.frame.render import" in render and "render_frame(" in render


# Issue 37: no module or kernel file grows past what one reader holds in mind; split it by job.
PYTHON_LINES = 800      # every .py of addon/, core/, slave/ and the root __init__.py: fewer
KERNEL_LINES = 900      # every file of kernels/ but generated tables: fewer


def is_generated(path: pathlib.Path) -> bool:
    """A generated file says so on its first line, as kernels/shade/ggx_albedo.cl does (`//
    Generated by .ci/ggx_albedo.py: do not edit.`): its length is its table's, not code's."""
    first = path.read_text().split("\n", 1)[0]
    return "Generated by" in first and "do not edit" in first


def line_count(path: pathlib.Path) -> int:
    return len(path.read_text().splitlines())


def test_modules_and_kernels_stay_under_their_line_limits():
    modules = [ROOT / "__init__.py"] + [p for package in ("addon", "core", "slave")
                                        for p in sources(package)]
    kernels = [p for p in sorted((ROOT / "kernels").rglob("*")) if p.is_file()]
    generated = [p for p in kernels if is_generated(p)]
    assert ROOT / "kernels/shade/ggx_albedo.cl" in generated   # the rule still finds the table
    too_long = [f"{p.relative_to(ROOT)}: {line_count(p)} lines (limit: under {limit})"
                for files, limit in ((modules, PYTHON_LINES), (kernels, KERNEL_LINES))
                for p in files if p not in generated and line_count(p) >= limit]
    assert not too_long, "split by job (issue 37): " + "; ".join(too_long)
