"""Build the KD Trace extension zip(s) with the wheels the add-on and its local slaves need.

    .venv/bin/python .ci/build_extension.py [--out dist] [--platform linux-x64 ...] [--no-wheels]

The files of the zip are what Blender's own `build` takes from the repository: everything but
blender_manifest.toml's [build] paths_exclude_pattern, the one list of what stays out. The
wheels are the runtime packages of requirements.txt whose markers hold on the platform, except
numpy (Blender ships it, and a bundled numpy breaks other add-ons): zeroconf for discovery;
cryptography (with cffi and pycparser) for the identities; pyopencl, and PoCL on Linux x64, for
local slaves. They come unmodified from the package index,
for Blender's Python (3.11), one zip per platform; each zip is checked with Blender's own
`validate`. Needs the bpy module (Blender's tool is inside it) and `packaging`.
"""
import argparse
import importlib.util
import pathlib
import re
import subprocess
import sys
import tempfile
import zipfile

from packaging.requirements import Requirement

ROOT = pathlib.Path(__file__).resolve().parent.parent
BLENDER_PYTHON = "3.11"   # what Blender 5.0 bundles (the manifest's version range)
NEVER_BUNDLED = {"numpy"}

# Blender platform -> pip platform tags (pip matches a tag exactly, so list the usual ones) and
# the marker environment of Blender's Python there.
PLATFORMS = {
    "linux-x64": (["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                   "manylinux2014_x86_64"], {"sys_platform": "linux", "platform_machine": "x86_64"}),
    "windows-x64": (["win_amd64"], {"sys_platform": "win32", "platform_machine": "AMD64"}),
    "macos-arm64": (["macosx_11_0_arm64", "macosx_10_9_universal2"],
                    {"sys_platform": "darwin", "platform_machine": "arm64"}),
}  # no macos-x64: zeroconf publishes no wheel for Intel Macs and Blender's Python 3.11


def blender_ext_tool() -> pathlib.Path:
    """Blender's extension command line tool, inside the bpy wheel (found without importing bpy)."""
    bpy_dir = pathlib.Path(importlib.util.find_spec("bpy").origin).parent
    tools = list(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not tools:
        sys.exit(f"Blender's extension tool is not under {bpy_dir}")
    return tools[0]


def bundled_requirements(platform: str) -> list[str]:
    """The pinned runtime requirements that go into the zip for `platform`."""
    environment = {"python_version": BLENDER_PYTHON, "python_full_version": BLENDER_PYTHON + ".0",
                   "implementation_name": "cpython", **PLATFORMS[platform][1]}
    wanted = []
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        requirement = Requirement(line)
        if requirement.name in NEVER_BUNDLED:
            continue
        if requirement.marker is None or requirement.marker.evaluate(environment):
            wanted.append(f"{requirement.name}{requirement.specifier}")
    return wanted


def download_wheels(platform: str, target: pathlib.Path) -> list[pathlib.Path]:
    tags = [arg for tag in PLATFORMS[platform][0] for arg in ("--platform", tag)]
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
                    "--only-binary=:all:", "--python-version", BLENDER_PYTHON,
                    "--implementation", "cp", *tags, "--dest", str(target),
                    *bundled_requirements(platform)], check=True)
    return sorted(target.glob("*.whl"))   # Blender's --split-platforms sorts them by tag


def blender_build(tool: pathlib.Path, source: pathlib.Path, out: pathlib.Path, *options):
    subprocess.run([sys.executable, str(tool), "build", "--source-dir", str(source),
                    "--output-dir", str(out), *options], check=True, capture_output=True,
                   text=True)


def stage_sources(tool: pathlib.Path, stage: pathlib.Path, scratch: pathlib.Path):
    """The extension's files, as Blender's build selects them from the repository, unpacked
    into `stage` (so that the wheels and a rewritten manifest can be added)."""
    scratch.mkdir()
    blender_build(tool, ROOT, scratch)
    [sources] = scratch.glob("*.zip")
    with zipfile.ZipFile(sources) as archive:
        archive.extractall(stage)


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
        stage_sources(tool, stage, pathlib.Path(tmp) / "sources")
        wheels = []
        if not args.no_wheels:
            for platform in platforms:
                wheels += download_wheels(platform, stage / "wheels")
        write_manifest(stage, platforms, sorted(set(wheels)))
        split = ["--split-platforms"] if len(platforms) > 1 or wheels else []
        blender_build(tool, stage, out, *split)
    for zip_path in sorted(out.glob("kdtrace-*.zip")):
        subprocess.run([sys.executable, str(tool), "validate", str(zip_path)], check=True,
                       capture_output=True, text=True)
        print(f"built and validated {zip_path} ({zip_path.stat().st_size / 2**20:.1f} MiB)")


if __name__ == "__main__":
    main()
