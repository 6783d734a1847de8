"""The package boundaries of docs/architecture.md, checked on the source."""
import ast
import pathlib
import re
import textwrap
import tomllib

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
        assert not imports & {"addon", "slave", ".addon", ".slave", "kdtrace"}, \
            path.relative_to(ROOT)


def test_addon_reaches_core_relatively_and_never_the_slave():
    for path in sources("addon"):
        imports = imported_modules(path)
        assert not imports & {"core", "kdtrace"}, \
            f"{path.relative_to(ROOT)} imports core absolutely"
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


# Issue 37: the installed slave is one namespace, kdtrace.core, kdtrace.slave and kdtrace.kernels
# (pyproject.toml), and kdtrace/__init__.py gives a checkout and the extension the same names. A
# top-level `core` or `slave` left anywhere does not exist in the wheel, and in a checkout it
# loads a second copy of a module: its classes under two names, monkeypatches of the other copy.
TOP_LEVEL = {"core", "slave", "kernels"}
TOP_LEVEL_LINE = re.compile(r"^\s*(from|import)\s+(core|slave|kernels)\b.*$", re.M)
TOP_LEVEL_LAUNCH = re.compile(r"-m\s+(core|slave)\b")
MODULE_TARGET = re.compile(r"(core|slave|kernels)(\.\w+)*")
TARGET_CALLS = {"setattr", "delattr", "patch", "import_module", "__import__", "find_spec"}
# Strings that are not ours to change: bench/build_vs_embree.py --before runs these in a checkout
# of an earlier version, whose packages are top-level; this file's samples of what is found.
OTHER_CODE = {"bench/build_vs_embree.py": {"BEFORE_TREE", "BEFORE_LOAD"},
              "tests/test_architecture.py": {"TOP_LEVEL_SAMPLES"}}


def call_name(func: ast.expr) -> str:
    return func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")


def top_level_uses(source: str, other_code=frozenset()) -> list[str]:
    """Where Python source reaches core, slave or kernels as top-level packages: its imports
    (inside functions too), module names it gives setattr, patch or import_module, a launch
    with -m in an argument list, and in its strings code that imports them (run with -c) or
    launches them; strings assigned to a name in `other_code` are left out."""
    tree = ast.parse(source)
    skipped = {id(inner) for node in ast.walk(tree) if isinstance(node, ast.Assign)
               and any(getattr(target, "id", None) in other_code for target in node.targets)
               for inner in ast.walk(node.value)}
    found = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if a.name.split(".")[0] in TOP_LEVEL]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            if node.module.split(".")[0] in TOP_LEVEL:
                found.append(f"from {node.module} import")
        elif isinstance(node, ast.Call) and node.args and call_name(node.func) in TARGET_CALLS:
            first = node.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str) \
                    and MODULE_TARGET.fullmatch(first.value):
                found.append(f"{call_name(node.func)}({first.value!r})")
        elif isinstance(node, (ast.List, ast.Tuple)):
            values = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
            found += [f"-m {b}" for a, b in zip(values, values[1:]) if a == "-m" and b in TOP_LEVEL]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            found += code_uses(node.value)
    return found


def code_uses(text: str) -> list[str]:
    """Top-level imports and launches in a string: code for `python -c`, a shell script, a
    docstring naming the command."""
    found = [m.group(0).strip() for m in TOP_LEVEL_LINE.finditer(text)]
    found += [m.group(0) for m in TOP_LEVEL_LAUNCH.finditer(text)]
    if "import" in text:
        try:
            found += top_level_uses(textwrap.dedent(text))
        except SyntaxError:   # prose, or a template (`{root!r}`): its lines were read above
            pass
    return found


def checked_files():
    for folder in ("tests", "bench", "slave", ".ci", "addon", "core"):
        for path in sorted((ROOT / folder).rglob("*")):
            parts = path.relative_to(ROOT).parts
            if path.is_file() and "__pycache__" not in parts and parts[:2] != ("bench", "out"):
                yield path


def test_everything_reaches_the_packages_as_kdtrace():
    """tests/, bench/, .ci/ and slave/ import kdtrace.core and kdtrace.slave (slave/ and core/
    relatively), and every slave is launched as `-m kdtrace.slave`."""
    wrong = []
    for path in checked_files():
        name = path.relative_to(ROOT).as_posix()
        text = path.read_text(errors="replace")
        if path.suffix == ".py":
            uses = top_level_uses(text, OTHER_CODE.get(name, set()))
        else:
            uses = code_uses(text) if path.suffix not in (".cl", ".h") else []
        wrong += [f"{name}: {use}" for use in uses]
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        wrong += [f"{path.relative_to(ROOT)}: {m.group(0)}"
                  for m in TOP_LEVEL_LAUNCH.finditer(path.read_text())]
    assert not wrong, "reach them as kdtrace.core, kdtrace.slave (issue 37): " + "; ".join(wrong)


TOP_LEVEL_SAMPLES = (
    "from core.net import protocol",
    "import slave.tracer as tracer",
    "def f():\n    import core.opencl",
    'monkeypatch.setattr("core.opencl.KERNEL_DIR", folder)',
    'mock.patch("slave.server.SlaveServer")',
    'importlib.import_module("core.scene.model")',
    'subprocess.run([sys.executable, "-m", "slave", "--help"])',
    'subprocess.run([sys.executable, "-c", "import os; import core.layout"])',
    'SCRIPT = """\nimport sys\nsys.path.insert(0, {root!r})\nfrom slave.tracer import Tracer\n"""',
    '"""Run it with `python -m slave --status`."""',
)


def test_the_check_finds_each_way_of_reaching_a_top_level_package():
    for sample in TOP_LEVEL_SAMPLES:
        assert top_level_uses(sample), sample
    assert top_level_uses(f"X = {TOP_LEVEL_SAMPLES[0]!r}", {"X"}) == []
    assert top_level_uses('from kdtrace.core.net import protocol\nChannel(sock, "slave")\n'
                          'run([python, "-m", "kdtrace.slave"])\nfrom .core import layout') == []


def test_the_wheel_holds_every_package_folder_under_kdtrace():
    """pyproject.toml names each package folder (setuptools' find cannot add the prefix) and
    leaves kdtrace itself a namespace package."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    setuptools = pyproject["tool"]["setuptools"]
    assert setuptools["package-dir"] == {f"kdtrace.{top}": top for top in sorted(TOP_LEVEL)}
    folders = {f"kdtrace.{top}" for top in TOP_LEVEL} | {
        ".".join(("kdtrace",) + path.relative_to(ROOT).parts) for top in TOP_LEVEL
        for path in (ROOT / top).rglob("*") if path.is_dir() and path.name != "__pycache__"
        and any(child.is_file() for child in path.iterdir())}
    assert set(setuptools["packages"]) == folders
    assert pyproject["project"]["scripts"] == {"kdtrace-slave": "kdtrace.slave.__main__:main"}
