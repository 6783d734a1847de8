"""Build the KD Trace extension zip(s) with the wheels the add-on and its local slaves need.

    .venv/bin/python .ci/build_extension.py [--out dist] [--platform linux-x64 ...] [--no-wheels]

The add-on itself needs zeroconf (LAN discovery); local slaves started from Blender's own Python
also need pyopencl, and on Linux PoCL as the CPU OpenCL device (Windows and macOS users get
OpenCL from their GPU drivers or the system). numpy is never bundled: Blender ships it, and a
bundled numpy breaks other add-ons. The wheels come unmodified from PyPI, for Blender's Python
(3.11), one zip per platform; each zip is checked with Blender's own `validate`.
"""
import argparse
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.blender import blender_ext_tool  # noqa: E402

# Blender platform -> pip platform tags (pip matches a tag exactly, so list the usual ones).
PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                  "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_11_0_arm64", "macosx_10_9_universal2"],
}  # no macos-x64: zeroconf publishes no wheel for Intel Macs and Blender's Python 3.11
# Pinned like requirements.txt; dependencies listed by hand since numpy must stay out.
WHEELS = ["zeroconf==0.154.0", "ifaddr==0.2.0", "pyopencl==2026.1.4", "pytools==2026.1.1",
          "platformdirs==4.14.7", "typing_extensions==4.16.0", "siphash24==1.9"]
LINUX_ONLY_WHEELS = ["pocl-binary-distribution==3.0"]
BLENDER_PYTHON = "3.11"


def download_wheels(platform: str, target: pathlib.Path) -> list[pathlib.Path]:
    packages = WHEELS + (LINUX_ONLY_WHEELS if platform == "linux-x64" else [])
    tags = [arg for tag in PLATFORMS[platform] for arg in ("--platform", tag)]
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
                    "--only-binary=:all:", "--python-version", BLENDER_PYTHON,
                    "--implementation", "cp", *tags, "--dest", str(target), *packages], check=True)
    return sorted(target.glob("*.whl"))


def stage_sources(stage: pathlib.Path):
    """Copy the extension's files (what Blender's build would take) to a staging folder."""
    skip = shutil.ignore_patterns(".git", ".venv", ".ci", "assets", "bench", "build", "docs",
                                  "tests", "dist", "wheels", "__pycache__", "*.pyc")
    shutil.copytree(ROOT, stage, ignore=skip)


def write_manifest(stage: pathlib.Path, platforms: list[str], wheels: list[pathlib.Path]):
    manifest = (stage / "blender_manifest.toml").read_text()
    listed = ", ".join(f'"{p}"' for p in platforms)
    manifest = re.sub(r"^platforms = .*$", f"platforms = [{listed}]", manifest, flags=re.M)
    if wheels:
        entries = ",\n".join(f'  "./wheels/{w.name}"' for w in wheels)
        manifest = manifest.replace("\n[permissions]", f"\nwheels = [\n{entries},\n]\n\n[permissions]")
    (stage / "blender_manifest.toml").write_text(manifest)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "dist"), help="folder for the zips")
    parser.add_argument("--platform", action="append", choices=sorted(PLATFORMS),
                        help="build for this platform (repeatable; default: all)")
    parser.add_argument("--no-wheels", action="store_true", help="leave the wheels out")
    args = parser.parse_args()
    platforms = args.platform or sorted(PLATFORMS)
    out = pathlib.Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    tool = blender_ext_tool()
    with tempfile.TemporaryDirectory() as tmp:
        stage = pathlib.Path(tmp) / "kdtrace"
        stage_sources(stage)
        wheels = []
        if not args.no_wheels:
            for platform in platforms:
                wheels += download_wheels(platform, stage / "wheels")
        write_manifest(stage, platforms, sorted(set(wheels)))
        split = ["--split-platforms"] if len(platforms) > 1 or wheels else []
        subprocess.run([sys.executable, str(tool), "build", "--source-dir", str(stage),
                        "--output-dir", str(out), *split], check=True)
    for zip_path in sorted(out.glob("kdtrace-*.zip")):
        subprocess.run([sys.executable, str(tool), "validate", str(zip_path)], check=True)
        print(f"built and validated {zip_path} ({zip_path.stat().st_size / 2**20:.1f} MiB)")


if __name__ == "__main__":
    main()
