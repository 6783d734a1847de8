"""Tests import the extension's packages as kdtrace.core and kdtrace.slave (the installed names:
kdtrace/__init__.py) from the repository root.

The tests' farm: every master and slave process a test starts holds one generated farm secret
($KDTRACE_SECRET, inherited by the slaves and Blenders the tests start), unless a test says
otherwise (tests/test_trust.py, the first-run pairing of tests/test_lan_first_render.py); slave
processes keep their identities in a temporary folder ($KDTRACE_SLAVE_HOME), never the user's."""
import atexit
import os
import pathlib
import shutil
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from kdtrace.core.net.trust import SECRET_ENV, new_farm_secret  # noqa: E402

if not os.environ.get(SECRET_ENV, "").startswith("kdtrace-farm-"):   # a test's child keeps it
    os.environ[SECRET_ENV] = new_farm_secret()
FARM_SECRET = os.environ[SECRET_ENV].encode()
if not os.environ.get("KDTRACE_SLAVE_HOME"):
    os.environ["KDTRACE_SLAVE_HOME"] = tempfile.mkdtemp(prefix="kdtrace-test-slaves-")
    atexit.register(shutil.rmtree, os.environ["KDTRACE_SLAVE_HOME"], True)

# The fast tier, `pytest -m "not slow"` (under 3 minutes, while working): these modules start
# Blender, slave processes or network namespaces, and a few long tests are marked slow where
# they are. .ci/run runs every test.
SLOW_MODULES = {
    "test_addon", "test_cycles_reference", "test_cycles_scenes", "test_degenerate_input",
    "test_export", "test_frame_denoise", "test_frame_session", "test_lan_first_render",
    "test_netns", "test_network", "test_packaging", "test_passes_blender", "test_real_files",
    "test_reliability", "test_scale", "test_scene_deltas", "test_shading", "test_slave_install",
    "test_trust", "test_viewport_blender", "test_viewport_session",
}


def pytest_collection_modifyitems(items):
    import pytest
    for item in items:
        if item.module.__name__.rpartition(".")[2] in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)

