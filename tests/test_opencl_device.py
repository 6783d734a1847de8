"""core.opencl's choice of device among several of a kind, with a stand-in pyopencl: a system
can list two CPU devices of which one cannot compile here (the PoCL wheel on AMD Zen 5)."""
import pytest

from kdtrace.core.opencl import UNKNOWN_CPU_HINT, OpenCLError, Programs, select_device


class FakeCL:
    """The few pyopencl names select_device and Programs use; `broken` devices fail to build
    with the log PoCL 3.0 gives on a CPU its LLVM does not know."""

    class Error(Exception):
        pass

    class device_type:
        CPU, GPU = 2, 4

    class program_build_info:
        LOG = "log"

    def __init__(self, platforms):
        self.platforms = platforms
        self.builds = []
        cl = self

        class Context:
            def __init__(self, devices):
                self.devices = devices

        class Program:
            def __init__(self, context, source):
                self.context = context

            def build(self, options=(), devices=()):
                cl.builds.append(devices[0].name)
                if devices[0].broken:
                    raise cl.Error("BUILD_PROGRAM_FAILURE")

            def get_build_info(self, device, what):
                return "error: unknown target CPU 'generic'"

            def all_kernels(self):
                return []

        self.Context, self.Program = Context, Program

    def get_platforms(self):
        return self.platforms


class Device:
    def __init__(self, name, kind=FakeCL.device_type.CPU, broken=False):
        self.name, self.type, self.broken = name, kind, broken


class Platform:
    def __init__(self, *devices):
        self.devices = list(devices)
        self.name = "platform"

    def get_devices(self):
        return self.devices


def test_the_first_cpu_device_that_compiles_is_chosen():
    wheel, system = Device("pocl 3.0", broken=True), Device("pocl 3.1")
    cl = FakeCL([Platform(wheel), Platform(system)])
    assert select_device(cl, "cpu") is system
    assert select_device(cl, "auto") is system
    assert select_device(cl, "0:0") is wheel            # named by index: taken as named


def test_a_single_device_is_not_probed_and_its_build_error_says_what_to_do():
    wheel = Device("pocl 3.0", broken=True)
    cl = FakeCL([Platform(wheel)])
    assert select_device(cl, "cpu") is wheel
    assert cl.builds == []
    with pytest.raises(OpenCLError, match="unknown target CPU") as failed:
        Programs(cl, cl.Context([wheel]), wheel).kernels("__kernel void k(void) {}", [])
    assert UNKNOWN_CPU_HINT in str(failed.value)


def test_with_none_that_compiles_the_first_is_chosen_and_gpus_come_first():
    one, two = Device("one", broken=True), Device("two", broken=True)
    assert select_device(FakeCL([Platform(one, two)]), "cpu") is one
    gpu = Device("gpu", FakeCL.device_type.GPU)
    assert select_device(FakeCL([Platform(one, gpu)]), "auto") is gpu
