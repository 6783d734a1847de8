"""The extension zip with its wheels: built per platform, validated by Blender's tool, installed
and used (Blender installs the wheels; the add-on and its local slave import them)."""
import subprocess
import sys
import zipfile

from tests.blender import ROOT, run_bpy_script


def test_zip_with_wheels_builds_validates_installs_and_renders(tmp_path):
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, str(ROOT / ".ci" / "build_extension.py"), "--out", str(dist),
                    "--platform", "linux-x64"], check=True, capture_output=True, text=True)
    [zip_path] = dist.glob("kdtrace-*linux_x64.zip")
    names = zipfile.ZipFile(zip_path).namelist()
    wheels = [n for n in names if n.startswith("wheels/")]
    assert any("zeroconf" in w for w in wheels) and any("pyopencl" in w for w in wheels)
    assert any("pocl_binary_distribution" in w for w in wheels)
    assert not any("numpy" in w for w in wheels), "numpy must never be bundled"
    assert not any(n.startswith(("tests/", "bench/", "docs/", ".ci/")) for n in names)

    result = run_bpy_script("install_with_wheels", tmp_path, zip=str(zip_path))
    assert result["wheel_dirs"], "Blender did not add the extension's wheels to sys.path"
    assert {"zeroconf", "ifaddr", "pyopencl", "pytools", "pocl_binary_distribution"} <= set(result["installed"])
    assert result["rendered"]
