"""What users install: the extension zip with its wheels (built per platform, validated by
Blender's tool, installed, used by the add-on, its local slaves and its `kdtrace_slave`
command), its licences and what stays out of it; the requirement files and the slave package's
metadata."""
import importlib.metadata
import json
import os
import pathlib
import re
import subprocess
import sys
import tomllib
import uuid
import zipfile

import pytest

from kdtrace.core.net.master import Master
from kdtrace.core.scene.scene import Scene
from tests.blender import ROOT, SCRIPTS, run_bpy_script
from tests.processes import LINE_PREFIX, ChildProcess
from tests.test_network import assert_images_equal, make_scene, make_view, render_all

MANIFEST = tomllib.loads((ROOT / "blender_manifest.toml").read_text())


def requirement_names(path) -> set:
    lines = [line.split("#")[0].strip() for line in path.read_text().splitlines()]
    return {re.split(r"[=<>;\[ ]", line)[0].lower().replace("_", "-")
            for line in lines if line and not line.startswith("-")}


@pytest.fixture(scope="module")
def bench_output():
    """A file where the benchmarks write (bench/out/), present while the zip is built."""
    path = ROOT / "bench" / "out" / f"packaging-test-{uuid.uuid4().hex[:8]}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG not really")
    yield path
    path.unlink()


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory, bench_output):
    dist = tmp_path_factory.mktemp("dist")
    subprocess.run([sys.executable, str(ROOT / ".ci" / "build_extension.py"), "--out", str(dist),
                    "--platform", "linux-x64"], check=True, capture_output=True, text=True)
    [zip_path] = dist.glob("kdtrace-*linux_x64.zip")
    return zip_path


def test_zip_holds_the_wheels_and_licences_and_no_outputs(linux_zip, bench_output):
    names = zipfile.ZipFile(linux_zip).namelist()
    wheels = [n for n in names if n.startswith("wheels/")]
    assert any("zeroconf" in w for w in wheels) and any("pyopencl" in w for w in wheels)
    assert any("pocl_binary_distribution" in w for w in wheels)
    # Identities (key pairs, certificates): cryptography and what it needs, for Blender's Python.
    assert all(any(os.path.basename(w).startswith(f"{name}-") for w in wheels)
               for name in ("cryptography", "cffi", "pycparser")), wheels
    assert not any("numpy" in w for w in wheels), "numpy must never be bundled"
    assert not any(n.startswith(("tests/", "bench/", "docs/", ".ci/")) for n in names)
    # Local slaves run `python -m kdtrace.slave` in the extension's root: kdtrace/ names it.
    assert {"__init__.py", "kdtrace/__init__.py", "slave/__main__.py"} <= set(names)
    assert bench_output.name not in " ".join(names)
    # Nothing git ignores (build outputs, caches, bench results) is in the zip.
    ignored = subprocess.run(["git", "check-ignore", "--no-index", "--stdin"], cwd=ROOT,
                             input="\n".join(names), capture_output=True, text=True).stdout
    assert ignored.split() == []

    archive = zipfile.ZipFile(linux_zip)
    assert "GNU GENERAL PUBLIC LICENSE" in archive.read("LICENSE").decode()
    assert "Version 3" in archive.read("LICENSE").decode()
    notices = archive.read("THIRD_PARTY_NOTICES.md").decode()
    for wheel in wheels:   # every bundled wheel is named with its version and licence
        name, version = os.path.basename(wheel).split("-")[:2]
        row = next((line for line in notices.splitlines()
                    if line.startswith(f"| {name.replace('_', '-')} |")
                    or line.startswith(f"| {name} |")), None)
        assert row is not None, f"{wheel} is not in THIRD_PARTY_NOTICES.md"
        assert f"| {version} |" in row, row


def test_bench_outputs_go_where_git_and_the_zips_ignore_them():
    sys.path.insert(0, str(ROOT / "tests" / "bpy_scripts"))
    from bench.render_demo import DEFAULT_OUT
    assert DEFAULT_OUT.is_relative_to(ROOT / "bench" / "out")
    check = subprocess.run(["git", "check-ignore", "-q", "--no-index", str(DEFAULT_OUT)], cwd=ROOT)
    assert check.returncode == 0, f"git does not ignore {DEFAULT_OUT}"
    assert "/bench/" in MANIFEST["build"]["paths_exclude_pattern"]


def test_versions_and_python_match_what_is_shipped_and_tested():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["version"] == MANIFEST["version"]
    # The manifest claims the Blender versions whose Python the wheels are built for, and the
    # tested Blender (the bpy module) is one of them.
    bpy_version = tuple(int(p) for p in importlib.metadata.version("bpy").split(".")[:3])
    low = tuple(int(p) for p in MANIFEST["blender_version_min"].split("."))
    high = tuple(int(p) for p in MANIFEST["blender_version_max"].split("."))
    assert low <= bpy_version < high
    assert sys.version_info[:2] == (3, 11), "bpy 5.0 runs on Python 3.11, as Blender 5.0 does"


def test_zip_wheels_are_for_blenders_python(linux_zip):
    for name in zipfile.ZipFile(linux_zip).namelist():
        if name.startswith("wheels/"):
            python_tag = os.path.basename(name).split("-")[-3]
            assert python_tag in ("cp311", "py3", "py2.py3"), name


def test_runtime_requirements_leave_out_the_development_tools():
    runtime = requirement_names(ROOT / "requirements.txt")
    development = requirement_names(ROOT / "requirements-dev.txt")
    assert {"numpy", "pyopencl", "zeroconf", "pocl-binary-distribution", "cryptography"} <= runtime
    assert not runtime & {"bpy", "pytest", "embreex"}
    assert {"bpy", "pytest", "embreex"} <= development
    assert "-r requirements.txt" in (ROOT / "requirements-dev.txt").read_text()
    setup = (ROOT / ".ci" / "setup").read_text()
    assert "-r requirements.txt" in setup and "-r requirements-dev.txt" in setup


def test_zip_with_wheels_installs_and_renders(linux_zip, tmp_path):
    result = run_bpy_script("install_with_wheels", tmp_path, zip=str(linux_zip))
    assert result["wheel_dirs"], "Blender did not add the extension's wheels to sys.path"
    assert {"zeroconf", "ifaddr", "pyopencl", "pytools", "pocl_binary_distribution",
            "cryptography", "cffi", "pycparser"} <= set(result["installed"])
    assert result["rendered"]


def test_blender_command_runs_the_slave_on_the_bundled_wheels(linux_zip, tmp_path):
    """`blender --background --command kdtrace_slave ...` with the installed extension: the
    slave it starts runs from the extension on its wheels, renders the same pixels as the
    tracer here, logs the frame and answers --status."""
    result_path = tmp_path / "command-result.json"
    # A new identity folder: its identity is made here, with the bundled cryptography.
    argv = ["--port", "0", "--bind", "127.0.0.1", "--name", "blender-cli", "--no-zeroconf",
            "--log-file", str(tmp_path / "slave.log"), "--identity-dir", str(tmp_path / "id")]
    blender = ChildProcess([str(SCRIPTS / "run_slave_command.py"),
                            json.dumps({"zip": str(linux_zip), "argv": argv}), str(result_path)],
                           env={"BLENDER_USER_RESOURCES": str(tmp_path / "blender-user"),
                                "PYTHONPATH": str(SCRIPTS)})
    try:
        line = blender.wait_line(LINE_PREFIX + "blender-cli listening on 127.0.0.1:", 120)
        port = int(line.split("127.0.0.1:")[1].split()[0])
        [slave_pid] = children(blender.proc.pid)
        slave_cwd = os.readlink(f"/proc/{slave_pid}/cwd")
        loaded = {line.split()[-1] for line in open(f"/proc/{slave_pid}/maps") if "/" in line}
        geometry, tree = make_scene()
        scene = Scene.from_parts(geometry, tree)
        with Master([("127.0.0.1", port)]) as master:
            master.connect()
            master.load_scene(scene)
            images, results = render_all(master.render(make_view(), tile_size=16))
        from kdtrace.slave.tracer import Tracer
        tracer = Tracer()
        tracer.load(scene)
        view = make_view()
        assert_images_equal(images, tracer.render_tile(view, 0, 0, view.width, view.height))
        # The status port is the slave's port + 1 unless that was taken: the log says which.
        [status_port] = re.findall(r"--status --status-port (\d+)",
                                   (tmp_path / "slave.log").read_text())
        status = subprocess.run([sys.executable, "-m", "kdtrace.slave", "--status", "--status-port",
                                 status_port], cwd=ROOT, capture_output=True, text=True,
                                timeout=30)
        assert status.returncode == 0, status.stderr
        assert "KD Trace slave blender-cli" in status.stdout
        assert f"1 frames, {len(results)} tiles" in status.stdout, status.stdout
    finally:
        blender.stop()
    outcome = json.loads(result_path.read_text())
    assert outcome["registered"] and outcome["status"] == 0, blender.log[-3000:]
    assert slave_cwd == outcome["extension_root"]   # `python -m kdtrace.slave` from the extension
    pyopencl = [path for path in loaded if "/pyopencl/_cl." in path]
    assert pyopencl and all(any(p.startswith(d) for d in outcome["wheel_dirs"]) for p in pyopencl)
    # Its identity was made with the bundled cryptography (its compiled part from the wheel).
    rust = [path for path in loaded if "/cryptography/hazmat/bindings/_rust" in path]
    assert rust and all(any(p.startswith(d) for d in outcome["wheel_dirs"]) for p in rust), loaded
    log = (tmp_path / "slave.log").read_text()
    assert re.search(rf"^\d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d kdtrace-slave INFO: frame [0-9a-f]+ "
                     rf"for .*: scene {scene.hash[:8]}, {len(results)} of {len(results)} tiles, "
                     rf"[\d.]+ ms/tile, kernel build [\d.]+ s, [\d.]+ MiB sent", log, re.M), log


def children(pid: int) -> list:
    """The pids of a process's children (Linux /proc)."""
    found = []
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found
