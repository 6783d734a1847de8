"""The tracer's kernel sources and their contracts with the host (docs/tracer.md "Kernels").
One list (slave/tracer.py KERNEL_FILES) names every file of kernels/trace/ and kernels/shade/ in
the order they are concatenated, no file includes another, so the build key (a hash of the
concatenated text and the options) covers every source of a program, and no file holds more
than one job's worth of code. Each kernel's parameters are one table (core/layout.py
KERNEL_PARAMS): the compiled kernels have exactly its parameters, and the tracer passes its
arguments in exactly its order, so that a change to either side alone fails here."""
from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

import kdtrace.core.opencl
from kdtrace.core.accel.compact import compact_tree
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.layout import KERNEL_PARAMS
from kdtrace.core.opencl import KERNEL_DIR, kernel_source
from kdtrace.core.scene.features import ALL_FEATURES, full_geometry
from kdtrace.core.scene.model import Camera, Geometry, Light, RenderSettings, Shading, View
from kdtrace.core.scene.scene import Scene
from kdtrace.slave.tracer import (KERNEL_FILES, SCENE_STRUCTURE, Tracer, kernel_files_through,
                                  kernel_options)
from tests.meshes import grid_plane, look_at, uv_sphere

# Generated tables, not code (.ci/ggx_albedo.py writes it).
GENERATED = {"shade/ggx_albedo.cl"}
MAX_LINES = 900


def test_every_tracer_source_is_listed_once_and_includes_nothing():
    assert len(set(KERNEL_FILES)) == len(KERNEL_FILES)
    on_disk = {path.relative_to(KERNEL_DIR).as_posix()
               for folder in ("trace", "shade") for path in (KERNEL_DIR / folder).glob("*.cl")}
    assert on_disk == set(KERNEL_FILES)
    for name in KERNEL_FILES:
        text = (KERNEL_DIR / name).read_text()
        assert not re.search(r"^\s*#\s*include", text, re.M), f"kernels/{name} includes a file"


def test_the_program_text_changes_with_every_source(tmp_path, monkeypatch):
    """Programs are cached by a hash of kernel_source's text: a change to any listed file
    must change that text (a file the compiler read by itself would not)."""
    copy = tmp_path / "kernels"
    shutil.copytree(KERNEL_DIR, copy)
    monkeypatch.setattr(kdtrace.core.opencl, "KERNEL_DIR", copy)
    before = kernel_source(KERNEL_FILES)
    for name in KERNEL_FILES:
        path = copy / name
        text = path.read_text()
        path.write_text(text + "\n// changed\n")
        assert kernel_source(KERNEL_FILES) != before, name
        path.write_text(text)
    assert kernel_source(KERNEL_FILES) == before


def test_a_prefix_of_the_sources_ends_at_the_named_file():
    assert kernel_files_through(KERNEL_FILES[0]) == KERNEL_FILES[:1]
    assert kernel_files_through(KERNEL_FILES[-1]) == KERNEL_FILES


def test_each_kernel_file_stays_under_the_size_of_one_job():
    for name in KERNEL_FILES:
        if name not in GENERATED:
            lines = len((KERNEL_DIR / name).read_text().splitlines())
            assert lines <= MAX_LINES, f"kernels/{name} has {lines} lines: split it by job"


# ---------------------------------------------------------------------------------------------
# Kernel parameters (core/layout.py KERNEL_PARAMS)

# The feature sets that change some kernel's parameters (the `when` of TOPLEVEL_PARAMS and of
# the film buffer).
PARAMETER_FLAGS = [(), ("INSTANCES",), ("INSTANCES", "OBJECT_MOTION"), ("FILM", "GUIDES")]


def test_kernels_are_declared_by_their_generated_parameter_lists():
    code = "\n".join(re.sub(r"//[^\n]*", "", (KERNEL_DIR / name).read_text())
                     for name in KERNEL_FILES)
    declared = re.findall(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)", code)
    assert sorted(declared) == sorted((k.kernel, k.macro) for k in KERNEL_PARAMS)


def expected_arg_info(cl, param) -> tuple:
    """clGetKernelArgInfo's answer for a parameter as the table describes it."""
    info = cl.kernel_arg_type_qualifier
    qualifier = {"in": info.CONST, "out": info.NONE, "atomic": info.VOLATILE}[param.access]
    space = cl.kernel_arg_address_qualifier
    return (param.name, param.ctype, space.GLOBAL if param.buffer else space.PRIVATE,
            qualifier if param.buffer else info.NONE)


@pytest.mark.parametrize("flags", PARAMETER_FLAGS)
def test_compiled_kernels_have_the_parameters_of_the_table(flags):
    """The tracer's program, built with the kernel-argument information on: every kernel's
    parameters, by name, type, address space and const/volatile, are its table's."""
    tracer = Tracer("cpu")
    cl = tracer._cl
    options = kernel_options({"flags": flags}) + ["-cl-kernel-arg-info"]
    kernels = tracer._programs.kernels(kernel_source(KERNEL_FILES), options)
    arg = cl.kernel_arg_info
    for params in KERNEL_PARAMS:
        kernel = kernels[params.kernel]
        compiled = [(kernel.get_arg_info(i, arg.NAME), kernel.get_arg_info(i, arg.TYPE_NAME),
                     kernel.get_arg_info(i, arg.ADDRESS_QUALIFIER),
                     kernel.get_arg_info(i, arg.TYPE_QUALIFIER)) for i in range(kernel.num_args)]
        assert compiled == [expected_arg_info(cl, p) for p in params.present(flags)], params.kernel


class CheckedKernel:
    """A kernel that checks each call's arguments against its table (check_arguments) before
    it runs: arguments out of order could make a traversal run for ever."""

    def __init__(self, kernel, options, check):
        self.kernel, self.options, self.check = kernel, options, check

    def __call__(self, queue, global_size, local_size, *args):
        self.check(self.kernel.function_name, self.options, args)
        return self.kernel(queue, global_size, local_size, *args)


def check_arguments(tracer, known: dict, seen: set):
    """A check of each call against its kernel's table: as many arguments as the program's
    parameters, buffers where it has buffers, scalars of its scalars' types, and the values
    `known` (by parameter name: buffers by identity) where the table puts them."""
    cl = tracer._cl
    tables = {k.kernel: k for k in KERNEL_PARAMS}

    def check(name, options, args):
        flags = [o[len("-DHAS_"):] for o in options if o.startswith("-DHAS_")]
        params = tables[name].present(flags)
        assert len(args) == len(params), name
        for param, value in zip(params, args):
            if param.buffer:
                assert isinstance(value, cl.MemoryObjectHolder), (name, param.name)
            else:
                assert isinstance(value, np.generic) and value.dtype == np.dtype(param.dtype), \
                    (name, param.name, value)
            if param.name in known:
                expected = known[param.name]
                assert value is expected if param.buffer else value == expected, (name, param.name)
        seen.add((name, tuple(flags)))
    return check


def checking(tracer, monkeypatch, known: dict) -> set:
    """Every kernel the tracer takes from its programs from now on checks its calls; returns
    the (kernel, features) seen."""
    seen = set()
    check = check_arguments(tracer, known, seen)
    built = tracer._programs.kernels

    def kernels(source, options):
        return {name: CheckedKernel(k, tuple(options), check)
                for name, k in built(source, options).items()}
    monkeypatch.setattr(tracer._programs, "kernels", kernels)
    return seen


def small_scene(instanced: bool):
    sphere_v, sphere_t = uv_sphere(12, 6, radius=1.0)
    plane_v, plane_t = grid_plane(8.0, 2)
    if not instanced:
        vertices = np.concatenate([plane_v, sphere_v + np.float32([0, 0, 1])])
        triangles = np.concatenate([plane_t, sphere_t + len(plane_v)]).astype(np.uint32)
        geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
        return Scene.from_parts(geometry, build_kdtree(geometry.vertices, geometry.triangles))
    meshes = []
    for vertices, triangles in ((plane_v, plane_t), (sphere_v, sphere_t)):
        geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
        meshes.append((geometry, compact_tree(build_kdtree(geometry.vertices, geometry.triangles),
                                              geometry.triangle_count, mode="compressed")))
    start, end = np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1))
    start[1, :3, 3], end[1, :3, 3] = (-2.0, 0.0, 1.0), (-1.0, 0.5, 1.0)     # moves
    start[2, :3, 3] = end[2, :3, 3] = (2.0, 0.0, 1.0)
    return Scene.from_instances(meshes, [0, 1, 1], start, to_world_end=end)


@pytest.mark.parametrize("instanced", [False, True])
def test_the_tracer_passes_arguments_in_the_order_of_the_table(instanced, monkeypatch):
    """A render and both ray queries of a flat and of an instanced, moving scene, with
    settings whose values all differ: every argument where the table says."""
    tracer = Tracer("cpu")
    scene = small_scene(instanced)
    tracer.load(scene)
    known = {**tracer._scene, **tracer._toplevel, "x0": 3, "y0": 2, "tile_w": 13,
             "jitter": 1, "max_bounces": 9, "diffuse_bounces": 3, "glossy_bounces": 2,
             "transmission_bounces": 5, "transparent_bounces": 6, "clamp_direct": 7.5,
             "clamp_indirect": 8.5, "filter_glossy": 0.25, "light_n": 4, "seed": 77,
             "light_count": 2, "ray_count": 37, "tmin": np.float32(0.125), "tmax": 1000.0}
    seen = checking(tracer, monkeypatch, known)
    settings = RenderSettings(samples_per_axis=2, adaptive=False, max_bounces=9,
                              diffuse_bounces=3, glossy_bounces=2, transmission_bounces=5,
                              transparent_bounces=6, clamp_direct=7.5, clamp_indirect=8.5,
                              filter_glossy=0.25, light_samples_per_axis=4, seed=77)
    lights = [Light("SUN", (1.0, 1.0, 1.0), 3.0, direction=(-0.3, -0.2, -1.0)),
              Light("POINT", (1.0, 0.9, 0.8), 100.0, (0.0, 0.0, 5.0))]
    shading = Shading(np.array([[0.8, 0.6, 0.4, 1.0]], np.float32), lights, (0.1, 0.1, 0.1))
    view = View(Camera("PERSP", look_at((0.0, -9.0, 6.0), (0.0, 0.0, 0.5))), 24, 18, shading,
                settings=settings)
    tracer.render_tile(view, 3, 2, 13, 11)
    tracer.render_tile(view, 3, 2, 13, 11, ("combined", "albedo", "denoising_normal"))
    assert {"FILM", "GUIDES"} <= set(tracer.last_render["features"])     # with its film buffer
    origins = np.tile(np.float32([[0.0, -9.0, 6.0]]), (37, 1))
    directions = np.random.default_rng(1).normal(size=(37, 3)).astype(np.float32) - [0, -1, 1]
    tracer.intersect(origins, directions, tmin=0.125, tmax=1000.0, time=0.25)
    tracer.occluded(origins, directions, tmin=0.125, tmax=1000.0, time=0.25)
    assert {name for name, _ in seen} == {k.kernel for k in KERNEL_PARAMS}
    if instanced:       # the top level's parameters were there
        assert all({"INSTANCES", "OBJECT_MOTION"} <= set(flags) for _, flags in seen)


def test_an_unspecialised_render_takes_the_scene_structure_from_the_scene():
    """Tracer.specialise = False compiles every shading feature, but INSTANCES and
    OBJECT_MOTION only as the scene has them: they add kernel parameters a flat scene has no
    values for (it failed for want of the top level's buffers)."""
    tracer = Tracer("cpu")
    flat = small_scene(False)
    tracer.load(Scene.from_parts(full_geometry(flat.geometry), flat.tree))
    tracer.specialise = False
    view = View(Camera("PERSP", look_at((0.0, -9.0, 6.0), (0.0, 0.0, 0.5))), 8, 6,
                Shading(np.array([[0.8, 0.6, 0.4, 1.0]], np.float32), [], (0.5, 0.5, 0.5)),
                settings=RenderSettings(samples_per_axis=1, adaptive=False))
    passes = tracer.render_tile(view, 0, 0, 8, 6)
    assert set(tracer.last_render["features"]) == ALL_FEATURES - SCENE_STRUCTURE
    assert np.isfinite(passes["combined"]).all() and passes["combined"][..., :3].max() > 0
