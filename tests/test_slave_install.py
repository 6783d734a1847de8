"""The slave on another machine, as a user installs it: a fresh virtual environment gets the
checkout installed with pip (pyproject.toml) and so only the runtime packages, its own under
kdtrace/; its `kdtrace-slave` command works from any folder and renders for the add-on in
Blender."""
import os
import pathlib
import queue
import shutil
import subprocess
import sys
import threading
import time

import pytest

from tests.blender import ROOT, build_extension, run_bpy_script
from tests.processes import LINE_PREFIX, START_TIMEOUT

# What the copy of the checkout leaves out: what pip would not package anyway, and big folders
# (those of the root only: kernels/build/ holds the builder's kernels).
NOT_COPIED_AT_ROOT = {".git", ".venv", "assets", "tests", "bench", "docs", "build", "dist"}
NOT_COPIED_ANYWHERE = shutil.ignore_patterns("*.egg-info", "__pycache__", ".pytest_cache")
RUNTIME = {"numpy", "pyopencl", "pytools", "platformdirs", "typing-extensions", "siphash24",
           "pocl-binary-distribution", "zeroconf", "ifaddr", "cryptography", "cffi", "pycparser"}


def not_copied(folder: str, names: list) -> set:
    root = NOT_COPIED_AT_ROOT if pathlib.Path(folder) == ROOT else set()
    return (root & set(names)) | NOT_COPIED_ANYWHERE(folder, names)


@pytest.fixture(scope="module")
def venv(tmp_path_factory):
    """A fresh venv holding the installed checkout; yields (bin folder, a folder outside it)."""
    work = tmp_path_factory.mktemp("slave-install")
    # pip builds a local folder in place (build/, *.egg-info): build a copy, not the shared tree.
    shutil.copytree(ROOT, work / "checkout", ignore=not_copied)
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(work / "venv")], check=True)
    python = work / "venv" / "bin" / "python"
    # This environment's pip installs into the new one (and reuses its download cache).
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
                    str(work / "checkout")], check=True, timeout=900)
    yield work / "venv" / "bin", work / "elsewhere"


def test_install_holds_only_the_runtime_packages(venv):
    bin_dir, _ = venv
    listed = subprocess.run([sys.executable, "-m", "pip", "--python", str(bin_dir / "python"),
                             "list", "--format=freeze"], check=True, capture_output=True,
                            text=True).stdout
    names = {line.split("==")[0].lower().replace("_", "-") for line in listed.split()}
    assert names == RUNTIME | {"kdtrace-slave"}


def test_install_is_one_namespace(venv):
    """site-packages gets kdtrace/ (core, slave, kernels with the OpenCL sources) and nothing of
    ours at its top level, where a user's own `core` or `slave` could be."""
    bin_dir, _ = venv
    [site] = (bin_dir.parent / "lib").glob("python3*/site-packages")
    assert (site / "kdtrace" / "slave" / "__main__.py").is_file()
    assert (site / "kdtrace" / "core" / "opencl.py").is_file()
    assert files_under(site / "kdtrace" / "kernels") == files_under(ROOT / "kernels")
    assert not (site / "kdtrace" / "__init__.py").exists()   # a namespace package (pyproject.toml)
    assert sorted(p.name for p in (site / "kdtrace").iterdir()) == ["core", "kernels", "slave"]
    assert not [name for name in ("core", "slave", "kernels") if (site / name).exists()]


def files_under(folder: pathlib.Path) -> list:
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())


def test_installed_slave_renders_for_the_addon_from_another_folder(venv, tmp_path):
    bin_dir, elsewhere = venv
    elsewhere.mkdir(exist_ok=True)
    env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="1", PYTHONUNBUFFERED="1")
    env.pop("PYTHONPATH", None)
    help_run = subprocess.run([str(bin_dir / "kdtrace-slave"), "--help"], cwd=elsewhere, env=env,
                              capture_output=True, text=True, timeout=60)
    assert help_run.returncode == 0, help_run.stderr
    assert help_run.stdout.startswith("usage: kdtrace-slave")
    where = subprocess.run([str(bin_dir / "python"), "-c",
                            "import kdtrace.slave, kdtrace.core.opencl as o; "
                            "print(kdtrace.slave.__file__); "
                            "print(sorted(p.name for p in o.KERNEL_DIR.rglob('*.cl')))"],
                           cwd=elsewhere, env=env, capture_output=True, text=True, check=True)
    assert "site-packages" in where.stdout and "trace.cl" in where.stdout, where.stdout

    log_file = tmp_path / "slave.log"
    slave = subprocess.Popen([str(bin_dir / "kdtrace-slave"), "--port", "0", "--bind", "127.0.0.1",
                              "--name", "venv-slave", "--no-zeroconf", "--log-file", str(log_file)],
                             cwd=elsewhere, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in slave.stdout], daemon=True).start()
    try:
        port = _listening_port(lines, "venv-slave")
        report = run_bpy_script("render_once", tmp_path, zip=str(build_extension(tmp_path / "dist")),
                                width=64, height=48, hosts=[["127.0.0.1", port]],
                                settings={"use_zeroconf": False, "local_slaves": 0})
        tiles = report["tiles_per_slave"]
        assert list(tiles) == ["venv-slave"] and tiles["venv-slave"] >= 1, report["log"][-3000:]
        assert report["local_slave_pids"] == [] and report["local_reason"] == ""
        status = subprocess.run([str(bin_dir / "kdtrace-slave"), "--status", "--port", str(port)],
                                cwd=elsewhere, env=env, capture_output=True, text=True, timeout=30)
        assert status.returncode == 0 and "KD Trace slave venv-slave" in status.stdout, status
    finally:
        slave.terminate()
        assert slave.wait(20) == 0
    log = log_file.read_text()
    assert f"of {tiles['venv-slave']} tiles" in log and "ms/tile" in log, log


def _listening_port(lines: queue.Queue, name: str) -> int:
    deadline, seen = time.monotonic() + START_TIMEOUT, []
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            continue
        seen.append(line)
        if line.startswith(f"{LINE_PREFIX}{name} listening on 127.0.0.1:"):
            return int(line.split("127.0.0.1:")[1].split()[0])
    pytest.fail("the installed slave did not start: " + "".join(seen))
