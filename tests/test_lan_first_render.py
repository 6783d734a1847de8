"""Discovery that does not miss: a slave on another host of the LAN (a network namespace, see
test_netns.py), advertised before F12, renders the first frame of a fresh Blender with KD
Trace's default settings, and no local slave is started."""
import uuid

from tests.blender import build_extension, run_bpy_script
from tests.test_netns import Lan, pytestmark, start_slave  # noqa: F401  (root and `ip` only)

ATTEMPTS = 3   # fresh Blenders, one F12 each


def test_first_render_in_a_fresh_blender_uses_the_slave_on_the_lan(tmp_path):
    lan = Lan(1)
    slave = None
    try:
        slave = start_slave(lan, 0, f"lan-{uuid.uuid4().hex[:6]}")
        zip_path = build_extension(tmp_path / "dist")
        for attempt in range(ATTEMPTS):
            report = run_bpy_script("render_once", tmp_path / f"blender-{attempt}",
                                    zip=str(zip_path), width=64, height=48)
            # Other slaves on this machine's networks may join; the LAN slave must be one.
            assert report["tiles_per_slave"].get(slave.name, 0) >= 1, report["log"][-3000:]
            assert report["local_slave_pids"] == [] and report["local_reason"] == "", report
    finally:
        if slave is not None:
            slave.stop()
        lan.close()
