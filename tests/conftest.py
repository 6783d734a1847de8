"""Tests import the extension's packages (core, slave) from the repository root.

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

from core.net.trust import SECRET_ENV, new_farm_secret  # noqa: E402

if not os.environ.get(SECRET_ENV, "").startswith("kdtrace-farm-"):   # a test's child keeps it
    os.environ[SECRET_ENV] = new_farm_secret()
FARM_SECRET = os.environ[SECRET_ENV].encode()
if not os.environ.get("KDTRACE_SLAVE_HOME"):
    os.environ["KDTRACE_SLAVE_HOME"] = tempfile.mkdtemp(prefix="kdtrace-test-slaves-")
    atexit.register(shutil.rmtree, os.environ["KDTRACE_SLAVE_HOME"], True)
