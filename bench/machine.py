"""What the benchmarks print about the machine they ran on. No side effects on import: benches
that want one PoCL thread set POCL_MAX_PTHREAD_COUNT themselves, before pyopencl loads."""
import platform


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), or what platform knows."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
