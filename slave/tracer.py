"""The OpenCL tracer: ray queries against a kd-tree and camera tiles (docs/tracer.md).

One kernel source set (KERNEL_FILES: traversal in kernels/trace/, sampling and shading in
kernels/shade/) serves both `intersect` and `render_tile`, with one triangle test. Runs on PoCL's
CPU device and on GPU drivers alike: single precision, no extensions, no fast-math options. The
render kernel is compiled per feature set (core/scene/features.py): a scene compiles only what it
uses. How a tile's samples are spent is slave/adaptive.py; the scene buffers' packing is
slave/buffers.py.
"""
from __future__ import annotations

import functools
import math
import pathlib
import time
from typing import NamedTuple

import numpy as np

from core.accel.morton import morton_order
from core.accel.reorder import treelet_order
from core.layout import ACCUM, MESH, STATS, c_header
from core.opencl import OpenCLError, Programs, ensure_pocl_cache_dir, kernel_source, select_device
from core.scene.features import ALL_FEATURES, needed_arrays
from core.scene.model import SceneError, View
from core.scene.scene import Scene

from .adaptive import pixel_rgba, sample_tile
from .buffers import (pack_bounds, pack_camera, pack_emitters, pack_instances, pack_lights,
                      pack_materials, pack_triangles, pack_world, world_importance)

# Concatenated in this order: each file uses only what the ones before it define.
KERNEL_FILES = ("trace/trace.cl", "shade/sampling.cl", "shade/ggx_albedo.cl", "shade/shading.cl",
                "trace/packet.cl", "trace/intersect.cl", "shade/render.cl")
MIN_STACK_SIZE = 32
PACKET_RAYS = 8             # rays per work-item of intersect_rays on CPU devices


class TracerError(OpenCLError):
    """The tracer cannot run: no OpenCL device, a kernel that does not build, bad input."""


class RayHits(NamedTuple):
    t: np.ndarray           # float32, inf on a miss
    triangle: np.ndarray    # int32, -1 on a miss (an index into the scene's geometry)
    u: np.ndarray           # float32, weight of the triangle's second vertex
    v: np.ndarray           # float32, weight of the third vertex


class InstanceHits(NamedTuple):
    """RayHits of an instanced scene: also the instance hit (docs/instances.md)."""
    t: np.ndarray
    triangle: np.ndarray    # int32 index into the scene's geometry (the mesh's triangle)
    u: np.ndarray
    v: np.ndarray
    instance: np.ndarray    # int64, -1 on a miss


def kernel_options(features: dict) -> list:
    """THE place that turns scene features into build options.

    features: "stack_size" (int, at least the kd-tree depth + 1), "flags" (the scene's feature
    set from core.scene.features.scene_features: light kinds and shading features, each becomes
    -DHAS_<NAME>), "light_kinds" (extra light kinds, for callers that only name those),
    "correct_divide_sqrt" (bool: the device can round / and sqrt correctly, which keeps pixels
    identical across devices), "packet" (rays per work-item of intersect_rays: 8 on CPU
    devices, 0 elsewhere), "prefetch" (bool: trace_ray fetches a leaf's triangles ahead of
    their tests with clang's __builtin_prefetch; CPU devices), "pixel_queue" (bool: the render
    kernel's work-items take a tile's pixels one at a time from a counter; CPU devices). Never
    fast-math: traversal needs inf/NaN/-0.
    """
    options = [f"-DKD_STACK_SIZE={int(features.get('stack_size', MIN_STACK_SIZE))}"]
    flags = set(features.get("flags", ())) | set(features.get("light_kinds", ()))
    options += [f"-DHAS_{flag}" for flag in sorted(flags)]
    if features.get("correct_divide_sqrt"):
        options.append("-cl-fp32-correctly-rounded-divide-sqrt")
    if features.get("packet"):
        options.append(f"-DKD_PACKET={int(features['packet'])}")
    if features.get("prefetch"):
        options.append("-DKD_PREFETCH")
    if features.get("pixel_queue"):
        options.append("-DRENDER_PIXEL_QUEUE")
    return options


class Tracer:
    """Ray queries and tile rendering on one OpenCL device (docs/architecture.md, "Tracer")."""

    def __init__(self, device=None, kernel_dir=None):
        """`kernel_dir`: read the kernel files from another copy of kernels/ (benchmarks of
        one kernel against another)."""
        ensure_pocl_cache_dir()     # before the ICD loader initialises PoCL
        import pyopencl as cl
        self._cl = cl
        self.device = select_device(cl, device, TracerError)
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self._programs = Programs(cl, self.context, self.device, TracerError)
        self._source = kernel_source(KERNEL_FILES) if kernel_dir is None else "\n".join(
            [c_header()] + [(pathlib.Path(kernel_dir) / name).read_text() for name in KERNEL_FILES])
        self._scene = None
        self._stack_size = MIN_STACK_SIZE
        self._loaded = None         # the Scene whose buffers self._scene holds
        self.mesh_loads_skipped = 0  # loads that kept the meshes' buffers (only instances moved)
        self.trees_reordered = 0    # trees laid out in treelets (a mesh's tree once while loaded)
        self._mesh_treelets = {}    # sizes -> [(mesh tree, the same in treelets)], loaded scene
        self._toplevel = ()         # an instanced scene's top-level buffers (kernel arguments)
        self._checked_view = None   # the last view checked against it
        self._light_tables = None   # (key, buffers) of the world importance map and emitters
        self.specialise = True      # False: compile every feature (for measuring specialisation)
        self.last_render = {}       # kernel seconds, samples traced, features of the last tile
        self.local_size = None      # intersect's work-group size; None: the driver's (best on PoCL)
        # CPU devices: a few render work-items take a tile's pixels one at a time (a pixel's
        # samples cost many times another's, and PoCL hands a launch's work-groups to its
        # threads in halves, so one thread waited for the other; docs/tracer.md "Speed").
        # Elsewhere one work-item per pixel, in the driver's work-groups.
        self.pixel_queue = bool(self.device.type & cl.device_type.CPU)
        # Rays per work-item in intersect(): CPU devices trace 8 neighbouring rays together in
        # vector lanes (kernels/trace/packet.cl); 0 = one ray per work-item (GPUs).
        self.packet = PACKET_RAYS if self.device.type & cl.device_type.CPU else 0
        self.reorder_rays = True    # trace scattered rays of a query in their origins' order
        # CPU devices: the ray queries' kernels read the caller's rays and write the results
        # in place (USE_HOST_PTR, results mapped), no copies or fresh pages per query.
        self.zero_copy = bool(self.device.type & cl.device_type.CPU)
        self.treelets = True        # load() lays the tree's nodes out in treelets

    @property
    def device_info(self) -> dict:
        d = self.device
        return {"name": d.name.strip(), "compute_units": int(d.max_compute_units),
                "memory": int(d.global_mem_size), "platform": d.platform.name.strip()}

    @property
    def build_seconds(self) -> float:
        """Seconds spent building kernel programs so far."""
        return self._programs.build_seconds

    # -- programs ------------------------------------------------------------------------
    def _features(self, flags=(), packet=0) -> dict:
        fp = getattr(self.device, "single_fp_config", 0)
        return {"stack_size": self._stack_size, "flags": tuple(sorted(flags)),
                "correct_divide_sqrt": bool(fp & self._cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT),
                "packet": packet, "prefetch": bool(self.device.type & self._cl.device_type.CPU),
                "pixel_queue": self.pixel_queue}

    def _program(self, features: dict):
        return self._programs.kernels(self._source, kernel_options(features))

    @staticmethod
    def _launch_sizes(n, local_size):
        """Global and local size of a launch of n work-items: a set local size must divide the
        global size (the kernels skip the padding items); None lets the driver choose."""
        if local_size is None:
            return (n,), None
        return (-(-n // local_size) * local_size,), (local_size,)

    # -- scene ---------------------------------------------------------------------------
    def load(self, scene: Scene) -> None:
        """Upload a scene (core.scene.scene.Scene: geometry and its compact kd-tree, already
        validated) once; later calls trace against it."""
        cl = self._cl
        geometry, tree = scene.geometry, scene.tree
        self._stack_size = max(MIN_STACK_SIZE, -(-(scene.depth + 1) // 16) * 16)
        mf = cl.mem_flags

        def upload(array):  # OpenCL has no empty buffers
            array = np.ascontiguousarray(array)
            if array.nbytes == 0:
                array = np.zeros(1, array.dtype)
            return cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=array)

        loaded = self._loaded
        if scene.instances is not None and loaded is not None and loaded.instances is not None \
                and loaded.meshes_hash == scene.meshes_hash:
            # The same meshes placed anew (a transform-only frame): their buffers stay, only
            # the top level and the world box are uploaded.
            self._toplevel = tuple(upload(a) for a in pack_instances(scene.instances).values())
            self._scene["bounds"] = upload(pack_bounds(scene.tree.bounds))
            self.mesh_loads_skipped += 1
            self._loaded_as(scene)
            return

        def optional(array, dtype):
            return upload(np.zeros(4, dtype) if array is None else np.ascontiguousarray(array, dtype))

        # The same tree with its nodes in treelets, a cache-friendlier order (core/accel/reorder.py);
        # an instanced scene's mesh trees each on its own (same lengths: the bases stay), and a
        # mesh the loaded scene has too (an animation frame where another mesh changed) keeps
        # its reordered tree (12 dragons' took 6-11 s).
        if self.treelets and scene.instances is None:
            tree = treelet_order(tree)
            self.trees_reordered += 1
            self._mesh_treelets = {}
        elif self.treelets:
            meshes = scene.mesh_trees()
            trees = [self._in_treelets(t) for t in meshes]
            self._mesh_treelets = {}
            for mesh, ordered in zip(meshes, trees):
                self._mesh_treelets.setdefault(_sizes(mesh), []).append((mesh, ordered))
            tree = type(tree)(*(np.concatenate([getattr(t, name) for t in trees])
                                for name in ("nodes", "leaf_index32", "leaf_index16")),
                              tree.bounds, 0)
            assert len(tree.nodes) == len(scene.tree.nodes)
        self._toplevel = () if scene.instances is None else tuple(
            upload(array) for array in pack_instances(scene.instances).values())
        self._scene = {"nodes": upload(tree.nodes), "leaf_index32": upload(tree.leaf_index32),
                       "leaf_index16": upload(tree.leaf_index16),
                       "leaf_shift": np.uint32(tree.leaf_shift),
                       "tri_verts": upload(pack_triangles(geometry)),
                       "bounds": upload(pack_bounds(tree.bounds)),
                       "material_ids": upload(geometry.material_ids),
                       "normals": optional(geometry.normals, np.float32),
                       "uvs": optional(geometry.uvs, np.float32),
                       "texels": optional(geometry.texels, np.float16),
                       "texture_sizes": optional(geometry.texture_sizes, np.uint32)}
        self._loaded_as(scene)

    def _in_treelets(self, tree):
        """`tree` in treelets: the loaded scene's, where one of its meshes has this tree (the
        order depends on the tree's arrays alone; comparing them costs a memcmp)."""
        for held, ordered in self._mesh_treelets.get(_sizes(tree), ()):
            if all(np.array_equal(getattr(held, name), getattr(tree, name))
                   for name in ("nodes", "leaf_index32", "leaf_index16")):
                return ordered
        self.trees_reordered += 1
        return treelet_order(tree)

    def _loaded_as(self, scene: Scene) -> None:
        self._loaded = scene
        self._checked_view = None
        self._light_tables = None

    def _toplevel_args(self, moment: float, flags) -> tuple:
        """The top-level kernel arguments (TOPLEVEL_PARAMS): the buffers and, with
        OBJECT_MOTION, the rays' moment in the shutter (the render kernel draws its own per
        sample)."""
        return (*self._toplevel, np.float32(moment)) if "OBJECT_MOTION" in flags else self._toplevel

    def _scene_buffers(self):
        if self._scene is None:
            raise TracerError("call load(scene) before tracing")
        return self._scene

    # -- ray queries ---------------------------------------------------------------------
    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf,
                  time=0.0) -> RayHits | InstanceHits:
        """Nearest hit of each ray with t in [tmin, tmax], t in units of the direction's length.
        `time`: the rays' moment in the shutter interval [0, 1], where objects move (the
        instances' transforms blended from shutter open to close)."""
        t, tri, u, v = self._query("intersect_rays", origins, directions, tmin, tmax,
                                   (np.float32, np.int32, np.float32, np.float32), time)
        instances = self._loaded.instances
        if instances is None:
            return RayHits(t, tri, u, v)
        # The kernel reports hit keys: back to (instance, the scene's triangle index).
        inst, local = instances.hit_instance(tri.astype(np.int64))
        base = instances.mesh_table[instances.mesh[np.maximum(inst, 0)], MESH.index("tri_base")]
        triangle = np.where(inst < 0, -1, base.astype(np.int64) + local).astype(np.int32)
        return InstanceHits(t, triangle, u, v, inst)

    def occluded(self, origins, directions, tmin=0.0, tmax=np.inf, time=0.0) -> np.ndarray:
        """Whether each ray has a hit with t in [tmin, tmax] (a bool array): shadow rays. The
        traversal stops at the first hit it finds (trace_ray's any_hit), so this is faster
        than intersect() and says exactly whether intersect() would find a hit."""
        (hit,) = self._query("occluded_rays", origins, directions, tmin, tmax, (np.uint8,), time)
        return hit.view(np.bool_)

    def _query(self, kernel_name, origins, directions, tmin, tmax, out_dtypes, time) -> list:
        """Run a ray-query kernel of intersect.cl: checked rays in, one array per output."""
        cl = self._cl
        origins = np.ascontiguousarray(origins, dtype=np.float32)
        directions = np.ascontiguousarray(directions, dtype=np.float32)
        if origins.ndim != 2 or origins.shape[1] != 3 or origins.shape != directions.shape:
            raise ValueError(f"origins and directions must both be (n, 3) arrays, got "
                             f"{origins.shape} and {directions.shape}")
        if not (np.isfinite(origins).all() and np.isfinite(directions).all()):
            raise ValueError("ray origins and directions must be finite")
        # Column by column: 10x faster than (directions == 0).all(axis=1) on a million rays.
        if ((directions[:, 0] == 0) & (directions[:, 1] == 0) & (directions[:, 2] == 0)).any():
            raise ValueError("a ray direction is the zero vector")
        if math.isnan(tmin) or math.isnan(tmax):
            raise ValueError("tmin and tmax must not be NaN")
        if not 0.0 <= time <= 1.0:
            raise ValueError(f"a ray's time is in the shutter interval [0, 1], got {time}")
        scene = self._scene_buffers()
        n = len(origins)
        outs = [np.empty(n, dtype) for dtype in out_dtypes]
        if n == 0:
            return outs
        # Rays in scattered order (bounces gathered from a whole image, random samples) are
        # traced in the order of their origins along a space-filling curve: neighbouring
        # work-items then read the same nodes and triangles while they are in cache.
        order = ray_order(origins, self._loaded.tree.bounds) if self.reorder_rays else None
        if order is not None:
            origins, directions = origins[order], directions[order]
        mf = cl.mem_flags
        ctx = self.context
        zero_copy = self.zero_copy and origins.flags.writeable and directions.flags.writeable
        given = mf.USE_HOST_PTR if zero_copy else mf.COPY_HOST_PTR
        o_buf = cl.Buffer(ctx, mf.READ_ONLY | given, hostbuf=origins)
        d_buf = cl.Buffer(ctx, mf.READ_ONLY | given, hostbuf=directions)
        out_bufs = [cl.Buffer(ctx, mf.WRITE_ONLY | mf.USE_HOST_PTR, hostbuf=a) if zero_copy
                    else cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes) for a in outs]
        # Only the ray queries compile the packet kernels (render programs build without them).
        # Instanced scenes trace one ray per work-item (intersect.cl).
        instanced = self._loaded.instances is not None
        packet = 0 if instanced else self.packet
        flags = ("INSTANCES",) if instanced else ()
        if instanced and self._loaded.instances.moving:
            flags += ("OBJECT_MOTION",)
        kernel = self._program(self._features(flags, packet=packet))[kernel_name]
        work_items = -(-n // packet) if packet else n
        kernel(self.queue, *self._launch_sizes(work_items, self.local_size), o_buf, d_buf,
               np.float32(tmin), np.float32(tmax), np.uint32(n), scene["nodes"],
               scene["leaf_index32"], scene["leaf_index16"], scene["leaf_shift"],
               scene["tri_verts"], scene["bounds"], *self._toplevel_args(time, flags), *out_bufs)
        for host, buf in zip(outs, out_bufs):
            if zero_copy:       # mapping makes the results in `host` current (no copy on PoCL)
                mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0,
                                                  host.shape, host.dtype)
                mapped.base.release(self.queue)
            else:
                cl.enqueue_copy(self.queue, host, buf)
        self.queue.finish()
        if order is not None:
            for i, traced in enumerate(outs):
                outs[i] = np.empty_like(traced)
                outs[i][order] = traced
        return outs

    # -- camera tiles --------------------------------------------------------------------
    def render_tile(self, view: View, x: int, y: int, w: int, h: int) -> dict:
        """Render pixels [x, x+w) x [y, y+h) of the full image (top-left origin).

        Samples as view.settings says (core/scene/model.py RenderSettings): uniform N x N stratified,
        or adaptive. Seeds depend only on the global pixel index and the sample number, so a
        tile gives the same pixels whichever slave renders it.
        """
        cl = self._cl
        if not (0 <= x and 0 <= y and w > 0 and h > 0
                and x + w <= view.width and y + h <= view.height):
            raise ValueError(f"tile ({x}, {y}, {w}, {h}) is not inside the "
                             f"{view.width}x{view.height} image")
        scene = self._scene_buffers()
        shading = view.shading
        kernel, flags = self._render_kernel(view)
        mf = cl.mem_flags
        ctx = self.context

        def upload(array):
            return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(array))

        settings = view.settings
        n = w * h
        accum = np.zeros((n, 4 * ACCUM.size), np.float32)
        stats = np.zeros((n, STATS.width * STATS.size), np.float32)
        depth = np.empty((h, w), np.float32)
        normal = np.empty((h, w, 3), np.float32)
        accum_buf = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=accum)
        stats_buf = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=stats)
        depth_buf = cl.Buffer(ctx, mf.WRITE_ONLY, depth.nbytes)
        normal_buf = cl.Buffer(ctx, mf.WRITE_ONLY, normal.nbytes)
        fixed = (upload(pack_camera(view)), np.int32(x), np.int32(y), np.int32(w))
        world, env_cdf, emitters, emitter_count, emitter_power = self._lights_for(shading, flags)
        scene_args = (scene["nodes"], scene["leaf_index32"], scene["leaf_index16"],
                      scene["leaf_shift"], scene["tri_verts"], scene["bounds"],
                      *self._toplevel_args(0.5, flags),
                      scene["material_ids"], upload(pack_materials(shading)),
                      upload(pack_lights(shading.lights)), np.uint32(len(shading.lights)),
                      scene["normals"], scene["uvs"], scene["texels"], scene["texture_sizes"],
                      world, env_cdf, emitters, np.uint32(emitter_count),
                      np.float32(emitter_power), accum_buf, stats_buf, depth_buf, normal_buf)
        started = time.perf_counter()
        tile = _TileOnDevice(self, kernel, fixed, scene_args, settings, accum, accum_buf, stats,
                             stats_buf)
        sample_tile(tile, settings, x, y, w, h, tile_pixel_order(w, h))
        cl.enqueue_copy(self.queue, accum, accum_buf)
        cl.enqueue_copy(self.queue, depth, depth_buf)
        cl.enqueue_copy(self.queue, normal, normal_buf)
        self.queue.finish()
        combined = pixel_rgba(accum)
        self.last_render = {"kernel_seconds": time.perf_counter() - started,
                            "samples": tile.traced, "features": sorted(flags)}
        return {"combined": combined.reshape(h, w, 4), "depth": depth, "normal": normal}

    def _lights_for(self, shading, flags) -> tuple:
        """The world and emitter buffers of `shading` on the loaded scene: the world
        texture's importance map and the emissive triangles' alias table, computed once per
        world and set of emissions (a frame's tiles share them)."""
        cl = self._cl
        geometry = self._loaded.geometry
        texture = shading.world_texture if "WORLD_TEXTURE" in flags else None
        emission = np.ascontiguousarray(shading.material_params[:, 4:7]) if "EMISSION" in flags \
            else None
        key = (None if texture is None else repr(texture.to_dict()),
               None if emission is None else emission.tobytes())
        if self._light_tables is None or self._light_tables[0] != key:
            mf = cl.mem_flags

            def upload(array):
                return cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR,
                                 hostbuf=np.ascontiguousarray(array))
            cdf, size = np.zeros(4, np.float32), (0, 0)
            if texture is not None:
                cdf, *size = world_importance(geometry, texture)
            records, count, power = (np.zeros((1, 4), np.float32), 0, 0.0) if emission is None \
                else pack_emitters(geometry, shading)
            self._light_tables = (key, (upload(pack_world(shading, size)), upload(cdf),
                                        upload(records), count, power))
        return self._light_tables[1]

    def prepare(self, view: View) -> None:
        """Check `view` against the loaded scene and build its render kernel (cached): what
        render_tile does first, callable on its own so that a slave can say it is compiling."""
        self._render_kernel(view)

    def _render_kernel(self, view: View) -> tuple:
        self._scene_buffers()
        if view is not self._checked_view:     # once per frame: its tiles share the view
            try:
                self._loaded.check_view(view)
            except SceneError as error:
                raise TracerError(str(error)) from None
            self._checked_view = view
        geometry = self._loaded.geometry
        flags = self._loaded.features(view) if self.specialise else ALL_FEATURES
        missing = [name for name in needed_arrays(flags) if getattr(geometry, name) is None]
        if missing:
            raise TracerError(f"features {sorted(flags)} need the geometry arrays {missing}; "
                              "load core.scene.features.full_geometry(geometry) to render unspecialised")
        return self._program(self._features(flags))["render_samples"], flags


# ray_order: rays count as scattered when consecutive origins lie this far apart on average
# (relative to the scene's size); camera rays (one origin) and rays from the hits of neighbouring
# pixels lie orders of magnitude closer. Queries this small keep their order.
SCATTERED_RAY_STEP = 0.02
MIN_REORDERED_RAYS = 4096


def ray_order(origins: np.ndarray, bounds: np.ndarray):
    """The order to trace a query's rays in: None (as given) unless they are scattered (module
    constants), else their origins' order along a Morton curve over the scene's box (what it
    gains and costs: docs/tracer.md, "Speed"); the results do not depend on it."""
    n = len(origins)
    if n < MIN_REORDERED_RAYS:
        return None
    lo, hi = bounds[0].astype(np.float64), bounds[1].astype(np.float64)
    size = float(np.max(hi - lo)) or 1.0
    sample = origins[np.linspace(0, n - 2, 1024).astype(np.int64)[:, None] + [0, 1]]
    step = np.abs(sample[:, 1] - sample[:, 0]).max(axis=1).mean()
    if step < SCATTERED_RAY_STEP * size:
        return None
    return morton_order(origins, lo, hi)


@functools.lru_cache(maxsize=8)
def tile_pixel_order(w: int, h: int) -> np.ndarray:
    """Tile-local pixel indices in the order the render kernel takes them: 16 x 16 blocks
    (row by row), Morton order inside each. Neighbouring work-items then trace neighbouring
    pixels, whose rays visit the same kd-tree nodes and triangles while they are in cache
    (PoCL runs a work-group's items one after another on one core): measured about 15 %
    faster on the dragon than row order. Each pixel's result does not depend on the order."""
    gy, gx = np.divmod(np.arange(w * h, dtype=np.int64), w)
    inside = np.zeros_like(gx)
    for bit in range(4):        # interleave the low 4 bits of x and y
        inside |= ((gx >> bit) & 1) << (2 * bit) | ((gy >> bit) & 1) << (2 * bit + 1)
    key = ((gy >> 4) * ((w + 15) >> 4) + (gx >> 4)) << 8 | inside
    order = np.argsort(key, kind="stable").astype(np.int32)
    order.flags.writeable = False
    return order


class _TileOnDevice:
    """One tile's render kernel and accumulators: the device side of slave/adaptive.py."""

    def __init__(self, tracer, kernel, fixed, scene_args, settings, accum, accum_buf, stats,
                 stats_buf):
        self.tracer, self.kernel, self.fixed, self.scene_args = tracer, kernel, fixed, scene_args
        strata = settings.samples_per_axis
        from pyopencl import cltypes
        limits = np.array((settings.max_bounces, settings.diffuse_bounces,
                           settings.glossy_bounces, settings.transmission_bounces), np.int32)
        clamps = np.array((settings.clamp_direct, settings.clamp_indirect, settings.filter_glossy,
                           0.0), np.float32)
        self.constants = (np.int32(0 if strata == 1 else strata),
                          limits.view(cltypes.int4)[0], np.int32(settings.transparent_bounces),
                          clamps.view(cltypes.float4)[0],
                          np.int32(settings.light_samples_per_axis), np.uint32(settings.seed))
        self.accum, self.accum_buf, self.stats, self.stats_buf = accum, accum_buf, stats, stats_buf
        self.next_pixel = tracer._cl.Buffer(tracer.context, tracer._cl.mem_flags.READ_WRITE, 4)
        self.traced = 0             # samples traced

    def run(self, pixels, start, count, aux):
        tracer, cl = self.tracer, self.tracer._cl
        pixels = np.ascontiguousarray(pixels, np.int32)
        if len(pixels) == 0:
            return
        pixel_buf = cl.Buffer(tracer.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                              hostbuf=pixels)
        if tracer.pixel_queue:      # one work-item per compute unit, each taking pixels in turn
            cl.enqueue_fill_buffer(tracer.queue, self.next_pixel, np.int32(0), 0, 4)
            workers = min(int(tracer.device.max_compute_units), len(pixels))
            sizes = (workers,), (1,)
        else:
            sizes = tracer._launch_sizes(len(pixels), None)
        self.kernel(tracer.queue, *sizes, *self.fixed, pixel_buf, np.int32(len(pixels)),
                    self.next_pixel, np.int32(start), np.int32(count), *self.constants,
                    np.int32(aux), *self.scene_args)
        self.traced += len(pixels) * count

    def read(self):
        cl, queue = self.tracer._cl, self.tracer.queue
        cl.enqueue_copy(queue, self.accum, self.accum_buf)
        cl.enqueue_copy(queue, self.stats, self.stats_buf)
        return self.accum, self.stats

    def write_accum(self, values):
        self.tracer._cl.enqueue_copy(self.tracer.queue, self.accum_buf, values)


def _sizes(tree) -> tuple:
    """What two equal compact trees share, to find candidates before comparing arrays."""
    return len(tree.nodes), len(tree.leaf_index32), len(tree.leaf_index16), tree.leaf_shift
