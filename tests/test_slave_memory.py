"""The slave's process limits glibc's malloc arenas (slave/__main__.py limit_malloc_arenas): with
the default, every new thread may get an arena of its own that keeps what is freed in it, and a
slave serving connection after connection grows (docs/distributed.md, "Soak")."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from tests.processes import ROOT

# Eight threads allocating at the same time, then glibc's own count of its heaps (arenas).
PROBE = textwrap.dedent("""
    import ctypes, sys, tempfile, threading
    sys.path.insert(0, ".")
    from kdtrace.slave.__main__ import limit_malloc_arenas
    if sys.argv[1] == "limited":
        limit_malloc_arenas()
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    libc.fopen.restype = ctypes.c_void_p
    libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
    libc.fclose.argtypes = [ctypes.c_void_p]
    together = threading.Barrier(8)
    def work():
        blocks = [libc.malloc(4096) for _ in range(100)]
        together.wait()
        for block in blocks:
            libc.free(block)
    threads = [threading.Thread(target=work) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    path = tempfile.mktemp()
    out = libc.fopen(path.encode(), b"w")
    libc.malloc_info(0, out)
    libc.fclose(out)
    print(open(path).read().count("<heap nr="))
""")


def heaps(mode: str) -> int:
    done = subprocess.run([sys.executable, "-c", PROBE, mode], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env={"PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's arenas: Linux only")
def test_the_slave_keeps_two_malloc_arenas_whatever_its_threads():
    assert heaps("default") > 2          # the probe does see one arena per thread
    assert heaps("limited") <= 2
