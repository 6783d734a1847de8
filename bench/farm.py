"""The benchmarks' farm: one generated farm secret for the master and every slave of a run
(in $KDTRACE_SECRET, which slave processes inherit), and slave identities in a temporary
folder ($KDTRACE_SLAVE_HOME), never the user's."""
import atexit
import os
import shutil
import tempfile

from kdtrace.core.net.trust import SECRET_ENV, new_farm_secret


def bench_farm() -> bytes:
    """The run's farm secret, made once (a child process of the run inherits it)."""
    if not os.environ.get(SECRET_ENV, "").startswith("kdtrace-farm-"):
        os.environ[SECRET_ENV] = new_farm_secret()
    if not os.environ.get("KDTRACE_SLAVE_HOME"):
        home = tempfile.mkdtemp(prefix="kdtrace-bench-slaves-")
        os.environ["KDTRACE_SLAVE_HOME"] = home
        atexit.register(shutil.rmtree, home, True)
    return os.environ[SECRET_ENV].encode()
