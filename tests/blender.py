"""Running Blender (the bpy module) from tests: each scene runs in its own Python process, since
bpy can be imported once per process and BLENDER_USER_RESOURCES must be set before the import.

The extension is built into a zip with Blender's own extension tool, validated, and installed
into an isolated user resources folder by the scripts in tests/bpy_scripts/.
"""
from __future__ import annotations

import importlib.util
import json
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCRIPTS = pathlib.Path(__file__).resolve().parent / "bpy_scripts"


def blender_ext_tool() -> pathlib.Path:
    """Blender's extension command line tool, inside the bpy wheel (found without importing bpy)."""
    bpy_dir = pathlib.Path(importlib.util.find_spec("bpy").origin).parent
    tools = list(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    assert tools, f"Blender's extension tool is not under {bpy_dir}"
    return tools[0]


def build_extension(output_dir: pathlib.Path) -> pathlib.Path:
    """Build the extension zip from the repository and validate it; return its path."""
    output_dir.mkdir(parents=True, exist_ok=True)
    tool = blender_ext_tool()
    subprocess.run([sys.executable, str(tool), "build", "--source-dir", str(ROOT),
                    "--output-dir", str(output_dir)], check=True, capture_output=True, text=True)
    [zip_path] = output_dir.glob("kdtrace-*.zip")
    check = subprocess.run([sys.executable, str(tool), "validate", str(zip_path)],
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    return zip_path


def run_bpy_script(name: str, work_dir: pathlib.Path, timeout: float = 300, **arguments) -> dict:
    """Run tests/bpy_scripts/<name>.py in a fresh process; it returns a JSON object.

    Arguments travel as one JSON object; the script writes its answer to work_dir/result.json.
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    result_path = work_dir / f"{name}-result.json"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(work_dir / "blender-user"),
               PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    process = subprocess.run(
        [sys.executable, str(SCRIPTS / f"{name}.py"), json.dumps(arguments), str(result_path)],
        env=env, cwd=work_dir, capture_output=True, text=True, timeout=timeout)
    log = process.stdout + process.stderr
    (work_dir / f"{name}.log").write_text(log)
    assert process.returncode == 0 and result_path.exists(), f"{name} failed:\n{log[-6000:]}"
    result = json.loads(result_path.read_text())
    result["log"] = log
    return result
