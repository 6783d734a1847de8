"""Discovery that does not miss: a slave on another host of the LAN (a network namespace, see
test_netns.py), advertised before F12, renders the first frame of a fresh Blender with KD
Trace's default settings, and no local slave is started; the browser that finds it runs while
KD Trace is the render engine."""
import uuid

import pytest

from tests.blender import build_extension, run_bpy_script
from tests.test_netns import Lan, pytestmark, start_slave  # noqa: F401  (root and `ip` only)

ATTEMPTS = 3   # fresh Blenders, one F12 each


@pytest.fixture(scope="module")
def lan_slave():
    lan = Lan(1)
    slave = None
    try:
        slave = start_slave(lan, 0, f"lan-{uuid.uuid4().hex[:6]}")
        yield slave
    finally:
        if slave is not None:
            slave.stop()
        lan.close()


def test_first_render_in_a_fresh_blender_uses_the_slave_on_the_lan(tmp_path, lan_slave):
    slave = lan_slave
    zip_path = build_extension(tmp_path / "dist")
    for attempt in range(ATTEMPTS):
        report = run_bpy_script("render_once", tmp_path / f"blender-{attempt}",
                                zip=str(zip_path), width=64, height=48)
        # Other slaves on this machine's networks may join; the LAN slave must be one.
        assert report["tiles_per_slave"].get(slave.name, 0) >= 1, report["log"][-3000:]
        assert report["local_slave_pids"] == [] and report["local_reason"] == "", report


def test_browser_runs_while_kdtrace_is_the_engine(tmp_path, lan_slave):
    result = run_bpy_script("browse_while_selected", tmp_path, zip=str(build_extension(tmp_path / "dist")),
                            slave=lan_slave.name, wait_seconds=10.0)
    assert result["steps"] == {"cycles": False, "kdtrace": True, "discovery off": False}
    assert lan_slave.name in result["seen"]
