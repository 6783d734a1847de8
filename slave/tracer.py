"""The OpenCL tracer: ray queries against a kd-tree and camera tiles (docs/tracer.md).

One kernel source set (kernels/trace.cl, sampling.cl, shading.cl, intersect.cl, render.cl) serves
both `intersect` and `render_tile`, so both share the same traversal and triangle test. Runs on
PoCL's CPU device and on GPU drivers alike: single precision, no extensions, no fast-math options.
The render kernel is compiled per feature set (core/features.py): a scene compiles only what it
uses. docs/tracer.md and docs/shading.md describe the kernels and the sampling.
"""
from __future__ import annotations

import hashlib
import math
import os
import pathlib
import tempfile
import time
from typing import NamedTuple

import numpy as np

from core.features import ALL_FEATURES, MIRROR_ROUGHNESS, needed_arrays, scene_features
from core.kdtree_compact import as_compact, validate_compact
from core.scene import MATERIAL_PARAMS, Geometry, View

KERNEL_DIR = pathlib.Path(__file__).resolve().parent.parent / "kernels"
# Concatenated in this order: each file uses only what the ones before it define.
KERNEL_FILES = ("trace.cl", "sampling.cl", "shading.cl", "intersect.cl", "packet.cl", "render.cl")
LIGHT_CODES = {"POINT": 0, "SUN": 1, "SPOT": 2, "AREA": 3}
LIGHT_FLOAT4S = 6           # float4 slots per light in the kernel's light buffer
MATERIAL_FLOAT4S = 4
CAMERA_FLOAT4S = 7
MIN_STACK_SIZE = 32
PACKET_RAYS = 8             # rays per work-item of intersect_packets on CPU devices
LIGHT_KINDS = tuple(LIGHT_CODES)


class TracerError(RuntimeError):
    """The tracer cannot run: no OpenCL device, a kernel that does not build, bad input."""


class RayHits(NamedTuple):
    t: np.ndarray           # float32, inf on a miss
    triangle: np.ndarray    # int32, -1 on a miss
    u: np.ndarray           # float32, weight of the triangle's second vertex
    v: np.ndarray           # float32, weight of the third vertex


def kernel_sources() -> str:
    return "\n".join((KERNEL_DIR / name).read_text() for name in KERNEL_FILES)


def kernel_options(features: dict) -> list:
    """THE place that turns scene features into build options.

    features: "stack_size" (int, at least the kd-tree depth + 1), "flags" (the scene's feature
    set from core.features.scene_features: light kinds and shading features, each becomes
    -DHAS_<NAME>), "light_kinds" (extra light kinds, for callers that only name those),
    "correct_divide_sqrt" (bool: the device can round / and sqrt correctly, which keeps pixels
    identical across devices), "packet" (rays per work-item of intersect_packets: 8 on CPU
    devices, 0 elsewhere). Never fast-math: traversal needs inf/NaN/-0.
    """
    options = [f"-DKD_STACK_SIZE={int(features.get('stack_size', MIN_STACK_SIZE))}",
               f"-DMIRROR_ROUGHNESS={MIRROR_ROUGHNESS!r}f"]
    flags = set(features.get("flags", ())) | set(features.get("light_kinds", ()))
    options += [f"-DHAS_{flag}" for flag in sorted(flags)]
    if features.get("correct_divide_sqrt"):
        options.append("-cl-fp32-correctly-rounded-divide-sqrt")
    if features.get("packet"):
        options.append(f"-DKD_PACKET={int(features['packet'])}")
    return options


def _ensure_pocl_cache_dir() -> None:
    """PoCL needs a writable cache dir even with caching off; give it one of ours."""
    if os.environ.get("POCL_CACHE_DIR"):
        return
    base = pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache")
    for candidate in (base / "kdtrace" / "pocl", pathlib.Path(tempfile.gettempdir()) / "kdtrace-pocl"):
        try:
            candidate.mkdir(parents=True, exist_ok=True)
            if os.access(candidate, os.W_OK):
                os.environ["POCL_CACHE_DIR"] = str(candidate)
                return
        except OSError:
            continue


def _select_device(cl, device):
    """None/"auto": the first GPU, else the first CPU device; "cpu"; "gpu"; or "P:D" indices."""
    try:
        platforms = cl.get_platforms()
    except cl.Error as error:
        platforms, reason = [], str(error)
    else:
        reason = "none installed"
    if not platforms:
        raise TracerError(f"no OpenCL platform found ({reason}); install a GPU driver or "
                          "`pip install pocl-binary-distribution` for the CPU device")
    devices = [(p, d) for p in platforms for d in p.get_devices()]
    spec = "auto" if device is None else str(device).strip().lower()
    if spec in ("auto", "gpu", "cpu"):
        want = {"gpu": (cl.device_type.GPU,), "cpu": (cl.device_type.CPU,),
                "auto": (cl.device_type.GPU, cl.device_type.CPU)}[spec]
        for kind in want:
            for p, d in devices:
                if d.type & kind:
                    return d
        if spec == "auto" and devices:
            return devices[0][1]
        raise TracerError(f"no OpenCL {spec} device; found: "
                          + ", ".join(f"{p.name}: {d.name}" for p, d in devices))
    try:
        p_index, d_index = (int(part) for part in spec.split(":"))
        return platforms[p_index].get_devices()[d_index]
    except (ValueError, IndexError):
        raise TracerError(f"device {device!r} not found: use auto, cpu, gpu or P:D with "
                          f"{len(platforms)} platform(s)") from None


class Tracer:
    """Ray queries and tile rendering on one OpenCL device (docs/architecture.md, "Tracer")."""

    def __init__(self, device=None):
        _ensure_pocl_cache_dir()    # before the ICD loader initialises PoCL
        import pyopencl as cl
        self._cl = cl
        self.device = _select_device(cl, device)
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self._programs = {}         # (source hash, options, device) -> {name: kernel}
        self._scene = None
        self._stack_size = MIN_STACK_SIZE
        self._material_count = 0
        self._geometry = None
        self.specialise = True      # False: compile every feature (for measuring specialisation)
        self.last_render = {}       # kernel seconds, samples traced, features of the last tile
        self.local_size = None      # work-group size; None lets the driver choose (measured best on PoCL)
        self._orders = {}           # (w, h) -> pixel order of a tile (_pixel_order)
        # Rays per work-item in intersect(): CPU devices trace 8 neighbouring rays together in
        # vector lanes (kernels/packet.cl); 0 = one ray per work-item (GPUs).
        self.packet = PACKET_RAYS if self.device.type & cl.device_type.CPU else 0

    @property
    def device_info(self) -> dict:
        d = self.device
        return {"name": d.name.strip(), "compute_units": int(d.max_compute_units),
                "memory": int(d.global_mem_size), "platform": d.platform.name.strip()}

    # -- programs ------------------------------------------------------------------------
    def _features(self, flags=(), packet=0) -> dict:
        fp = getattr(self.device, "single_fp_config", 0)
        return {"stack_size": self._stack_size, "flags": tuple(sorted(flags)),
                "correct_divide_sqrt": bool(fp & self._cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT),
                "packet": packet}

    def _program(self, features: dict):
        cl = self._cl
        source = kernel_sources()
        options = kernel_options(features)
        digest = hashlib.sha256((source + "\0" + " ".join(options)).encode()).hexdigest()[:16]
        # The hash in the options makes every cache (PoCL's, pyopencl's, the driver's) key on it.
        options = options + [f"-DKDTRACE_HASH=0x{digest}"]
        key = (digest, tuple(options), self.device.int_ptr)
        kernels = self._programs.get(key)
        if kernels is None:
            program = cl.Program(self.context, source)
            try:
                program.build(options=options, devices=[self.device])
            except cl.Error as error:
                try:
                    log = program.get_build_info(self.device, cl.program_build_info.LOG)
                except cl.Error:
                    log = str(error)
                saved = pathlib.Path(tempfile.gettempdir()) / f"kdtrace-failed-{digest}.cl"
                saved.write_text(source)
                raise TracerError(f"kernel build failed on {self.device.name.strip()} with options "
                                  f"{' '.join(options)}; source saved to {saved}\n{log}") from None
            # Kernel objects retrieved once: each retrieval makes a new, costly object.
            kernels = self._programs[key] = {k.function_name: k for k in program.all_kernels()}
        return kernels

    def _local(self):
        return None if self.local_size is None else (self.local_size,)

    def _global_size(self, n):
        # A set local size must divide the global size; the kernels skip the padding items.
        ls = self.local_size or 1
        return (-(-n // ls) * ls,)

    # -- scene ---------------------------------------------------------------------------
    def load(self, geometry: Geometry, tree) -> None:
        """Upload the geometry and its kd-tree once; later calls trace against them.

        `tree`: a compact kd-tree (core.kdtree_compact.CompactTree, or anything with its arrays
        nodes, leaf_index32, leaf_index16, bounds, leaf_shift: any of the modes standard, choi,
        ours), or a plain core.kdtree.KDTree, which is converted with mode "standard". Checked
        before upload, since it may come from the network (validate_compact).
        """
        cl = self._cl
        tri_count = geometry.triangle_count
        try:
            tree = as_compact(tree, tri_count)
        except ValueError as error:
            raise TracerError(f"invalid kd-tree: {error}") from None
        nodes = np.ascontiguousarray(tree.nodes, dtype=np.uint32)
        leaf32 = np.ascontiguousarray(tree.leaf_index32, dtype=np.uint32).reshape(-1)
        leaf16 = np.ascontiguousarray(tree.leaf_index16, dtype=np.uint16).reshape(-1)
        bounds = np.asarray(tree.bounds, dtype=np.float32)
        leaf_shift = int(np.asarray(tree.leaf_shift).reshape(-1)[0])
        if len(geometry.material_ids) != tri_count:
            raise TracerError("one material id per triangle is required")
        if tri_count and int(geometry.triangles.max()) >= len(geometry.vertices):
            raise TracerError("a triangle refers to a vertex that does not exist")
        try:
            depth = validate_compact(nodes, leaf32, leaf16, bounds, leaf_shift, tri_count)
        except ValueError as error:
            raise TracerError(f"invalid kd-tree: {error}") from None
        self._stack_size = max(MIN_STACK_SIZE, -(-(depth + 1) // 16) * 16)

        # Triangles as three float4 corners each: one gather per triangle in the kernel.
        corners = np.zeros((max(tri_count, 1), 3, 4), np.float32)
        corners[:tri_count, :, :3] = geometry.vertices[geometry.triangles]
        box = np.zeros((2, 4), np.float32)
        box[:, :3] = bounds
        box[0, 3] = np.abs(bounds).max()   # the scene's extent, for the tie tolerance (trace.cl)
        mf = cl.mem_flags

        def upload(array):  # OpenCL has no empty buffers
            array = np.ascontiguousarray(array)
            if array.nbytes == 0:
                array = np.zeros(1, array.dtype)
            return cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=array)

        try:
            geometry.validate()
        except ValueError as error:
            raise TracerError(f"invalid geometry: {error}") from None

        def optional(array, dtype):
            return upload(np.zeros(4, dtype) if array is None else np.ascontiguousarray(array, dtype))

        self._scene = {"nodes": upload(nodes), "leaf_index32": upload(leaf32),
                       "leaf_index16": upload(leaf16), "leaf_shift": np.uint32(leaf_shift),
                       "tri_verts": upload(corners), "bounds": upload(box),
                       "material_ids": upload(geometry.material_ids),
                       "normals": optional(geometry.normals, np.float32),
                       "uvs": optional(geometry.uvs, np.float32),
                       "texels": optional(geometry.texels, np.float16),
                       "texture_sizes": optional(geometry.texture_sizes, np.uint32)}
        self._material_count = int(geometry.material_ids.max()) + 1 if tri_count else 0
        self._geometry = geometry

    def _scene_buffers(self):
        if self._scene is None:
            raise TracerError("call load(geometry, tree) before tracing")
        return self._scene

    # -- ray queries ---------------------------------------------------------------------
    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf) -> RayHits:
        """Nearest hit of each ray with t in [tmin, tmax], t in units of the direction's length."""
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
        scene = self._scene_buffers()
        n = len(origins)
        out = RayHits(np.empty(n, np.float32), np.empty(n, np.int32),
                      np.empty(n, np.float32), np.empty(n, np.float32))
        if n == 0:
            return out
        mf = cl.mem_flags
        ctx = self.context
        o_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=origins)
        d_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=directions)
        outs = [cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes) for a in out]
        # Only intersect() compiles the packet kernel (render programs build without it).
        if self.packet:
            kernel = self._program(self._features(packet=self.packet))["intersect_packets"]
            work_items = -(-n // self.packet)
        else:
            kernel = self._program(self._features())["intersect_rays"]
            work_items = n
        kernel(self.queue, self._global_size(work_items), self._local(), o_buf, d_buf, np.float32(tmin), np.float32(tmax),
               np.uint32(n), scene["nodes"], scene["leaf_index32"], scene["leaf_index16"],
               scene["leaf_shift"], scene["tri_verts"],
               scene["bounds"], *outs)
        for host, buf in zip(out, outs):
            cl.enqueue_copy(self.queue, host, buf)
        self.queue.finish()
        return out

    # -- camera tiles --------------------------------------------------------------------
    def render_tile(self, view: View, x: int, y: int, w: int, h: int) -> dict:
        """Render pixels [x, x+w) x [y, y+h) of the full image (top-left origin).

        Samples as view.settings says (core/scene.py RenderSettings): uniform N x N stratified,
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
        if self._material_count > len(shading.materials):
            raise TracerError(f"the geometry uses {self._material_count} materials, "
                              f"the shading has {len(shading.materials)}")
        textures = shading.param("texture")
        if len(textures) and textures.max() >= self._geometry.texture_count:
            raise TracerError(f"a material uses texture {int(textures.max())}, the geometry has "
                              f"{self._geometry.texture_count}")
        flags = scene_features(self._geometry, view) if self.specialise else ALL_FEATURES
        missing = [name for name in needed_arrays(flags) if getattr(self._geometry, name) is None]
        if missing:
            raise TracerError(f"features {sorted(flags)} need the geometry arrays {missing}; "
                              "load core.features.full_geometry(geometry) to render unspecialised")
        kernel = self._program(self._features(flags))["render_samples"]
        mf = cl.mem_flags
        ctx = self.context

        def upload(array):
            return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(array))

        settings = view.settings
        n = w * h
        accum = np.zeros((n, 4), np.float32)
        stats = np.zeros((n, 2), np.float32)
        depth = np.empty((h, w), np.float32)
        normal = np.empty((h, w, 3), np.float32)
        accum_buf = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=accum)
        stats_buf = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=stats)
        depth_buf = cl.Buffer(ctx, mf.WRITE_ONLY, depth.nbytes)
        normal_buf = cl.Buffer(ctx, mf.WRITE_ONLY, normal.nbytes)
        fixed = (upload(_pack_camera(view)), np.int32(x), np.int32(y), np.int32(w))
        scene_args = (scene["nodes"], scene["leaf_index32"], scene["leaf_index16"],
               scene["leaf_shift"], scene["tri_verts"], scene["bounds"],
                      scene["material_ids"], upload(_pack_materials(shading)),
                      upload(_pack_lights(shading.lights)), np.uint32(len(shading.lights)),
                      scene["normals"], scene["uvs"], scene["texels"], scene["texture_sizes"],
                      accum_buf, stats_buf, depth_buf, normal_buf)
        strata = settings.samples_per_axis
        total = strata * strata
        started = time.perf_counter()
        traced = 0

        def run(pixels, start, count, aux):
            nonlocal traced
            pixels = np.ascontiguousarray(pixels, np.int32)
            kernel(self.queue, self._global_size(len(pixels)), self._local(), *fixed,
                   upload(pixels), np.int32(len(pixels)), np.int32(start), np.int32(count),
                   np.int32(0 if total == 1 else strata), np.int32(settings.max_bounces),
                   np.int32(settings.diffuse_bounces), np.int32(settings.light_samples_per_axis),
                   np.uint32(settings.seed), np.int32(aux), *scene_args)
            traced += len(pixels) * count

        every = self._pixel_order(w, h)
        if not settings.adaptive or total <= settings.adaptive_min_samples:
            run(every, 0, total, 1)
        else:
            count = max(1, settings.adaptive_min_samples)
            run(every, 0, 0, 1)                     # depth and normal of every pixel
            active = self._undersample(run, accum_buf, stats_buf, accum, stats, x, y, w, h,
                                       count, settings.adaptive_threshold)
            while count < total:
                cl.enqueue_copy(self.queue, stats, stats_buf)
                error = _pixel_error(stats, count, w, h)
                active = active[error[active] > settings.adaptive_threshold]
                if len(active) == 0:
                    break
                batch = min(count, total - count)   # doubling
                run(active, count, batch, 0)
                count += batch
        cl.enqueue_copy(self.queue, accum, accum_buf)
        cl.enqueue_copy(self.queue, depth, depth_buf)
        cl.enqueue_copy(self.queue, normal, normal_buf)
        self.queue.finish()
        combined = np.empty((n, 4), np.float32)
        combined[:, :3] = accum[:, :3] / np.maximum(accum[:, 3:4], 1.0)
        combined[:, 3] = 1.0
        self.last_render = {"kernel_seconds": time.perf_counter() - started,
                            "samples": traced, "features": sorted(flags)}
        return {"combined": combined.reshape(h, w, 4), "depth": depth, "normal": normal}


    def _pixel_order(self, w: int, h: int) -> np.ndarray:
        """Tile-local pixel indices in the order the render kernel takes them: 16 x 16 blocks
        (row by row), Morton order inside each. Neighbouring work-items then trace neighbouring
        pixels, whose rays visit the same kd-tree nodes and triangles while they are in cache
        (PoCL runs a work-group's items one after another on one core): measured about 15 %
        faster on the dragon than row order. Each pixel's result does not depend on the order.
        Cached per tile size."""
        order = self._orders.get((w, h))
        if order is None:
            gy, gx = np.divmod(np.arange(w * h, dtype=np.int64), w)
            inside = np.zeros_like(gx)
            for bit in range(4):        # interleave the low 4 bits of x and y
                inside |= ((gx >> bit) & 1) << (2 * bit) | ((gy >> bit) & 1) << (2 * bit + 1)
            key = ((gy >> 4) * ((w + 15) >> 4) + (gx >> 4)) << 8 | inside
            order = np.argsort(key, kind="stable").astype(np.int32)
            if len(self._orders) >= 8:
                self._orders.clear()
            self._orders[(w, h)] = order
        return order

    def _undersample(self, run, accum_buf, stats_buf, accum, stats, x, y, w, h, count,
                     threshold):
        """Adaptive undersampling (after Kim et al. 2016): trace the pixels with even global
        coordinates (and the tile's last row and column, so every other pixel has traced
        neighbours inside the tile); a pixel between them whose traced neighbours agree (their
        luminance within 4 x threshold) and are converged is their average and traces nothing;
        the others are traced. Global parity, so the same pixels are traced in every tiling of
        the rows and columns. Returns the traced pixels (tile-local indices)."""
        cl = self._cl
        gy, gx = np.meshgrid(np.arange(y, y + h), np.arange(x, x + w), indexing="ij")
        coarse = ((gx % 2 == 0) & (gy % 2 == 0)) | (gx == x + w - 1) & (gy % 2 == 0) \
            | (gy == y + h - 1) & (gx % 2 == 0) | ((gx == x + w - 1) & (gy == y + h - 1))
        traced = np.flatnonzero(coarse.ravel()).astype(np.int32)
        run(traced, 0, count, 0)
        cl.enqueue_copy(self.queue, accum, accum_buf)
        cl.enqueue_copy(self.queue, stats, stats_buf)
        colour = (accum[:, :3] / np.maximum(accum[:, 3:4], 1.0)).reshape(h, w, 3)
        lum = (stats[:, 0] / count).reshape(h, w)
        error = _pixel_error(stats, count, w, h).reshape(h, w)
        sum_c = np.zeros((h, w, 3), np.float32)
        n_c = np.zeros((h, w), np.int32)
        lo = np.full((h, w), np.inf, np.float32)
        hi = np.full((h, w), -np.inf, np.float32)
        worst = np.zeros((h, w), np.float32)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dx == dy == 0:
                    continue
                # neighbour (r + dy, c + dx) of pixel (r, c), when traced
                src = (slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0)))
                dst = (slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0)))
                # Of the 8 neighbours, the traced ones are the nearest ring: left/right or
                # up/down for pixels on a traced row or column, the diagonals for the others.
                ok = coarse[src]
                sum_c[dst] += np.where(ok[..., None], colour[src], 0)
                n_c[dst] += ok
                lo[dst] = np.where(ok, np.minimum(lo[dst], lum[src]), lo[dst])
                hi[dst] = np.where(ok, np.maximum(hi[dst], lum[src]), hi[dst])
                worst[dst] = np.where(ok, np.maximum(worst[dst], error[src]), worst[dst])
        smooth = ~coarse & (n_c >= 2) & (hi - lo <= 4 * threshold) & (worst <= threshold)
        fill = np.flatnonzero(smooth.ravel())
        if len(fill):
            interpolated = (sum_c / np.maximum(n_c, 1)[..., None]).reshape(-1, 3)[fill]
            accum[fill, :3] = interpolated
            accum[fill, 3] = 1.0
            stats[fill] = 0.0                   # converged: never refined
            cl.enqueue_copy(self.queue, accum_buf, accum)
        rest = np.flatnonzero((~coarse & ~smooth).ravel()).astype(np.int32)
        if len(rest):
            run(rest, 0, count, 0)
        done = ~smooth.ravel()
        return np.flatnonzero(done).astype(np.int32)


def _pixel_error(stats: np.ndarray, count: int, w: int, h: int) -> np.ndarray:
    """Per pixel, sigma / n: the spread of its samples (of min(luminance, 1)) over their count.
    Sampling until sigma / n <= threshold gives each pixel n proportional to sigma, which is
    the allocation that minimises the image's mean squared error for a given number of samples
    (minimise sum sigma_i^2 / n_i with sum n_i fixed). Widened to half its 4-neighbours' value
    (in the spirit of Kim et al. 2016: what a coarse pass finds noisy or at an edge, and its
    neighbourhood, is refined; smooth regions keep the minimum)."""
    mean = stats[:, 0] / count
    variance = np.maximum(stats[:, 1] / count - mean * mean, 0.0) * (count / max(count - 1, 1))
    error = (np.sqrt(variance) / count).reshape(h, w)
    widened = error.copy()
    widened[1:] = np.maximum(widened[1:], 0.5 * error[:-1])
    widened[:-1] = np.maximum(widened[:-1], 0.5 * error[1:])
    widened[:, 1:] = np.maximum(widened[:, 1:], 0.5 * error[:, :-1])
    widened[:, :-1] = np.maximum(widened[:, :-1], 0.5 * error[:, 1:])
    return widened.reshape(-1)


def _pack_materials(shading) -> np.ndarray:
    """The material buffer laid out as kernels/shading.cl documents it."""
    params = shading.material_params
    col = {name: params[:, i] for i, name in enumerate(MATERIAL_PARAMS)}
    out = np.zeros((max(len(params), 1), MATERIAL_FLOAT4S, 4), np.float32)
    out[:len(params), 0] = shading.materials
    out[:len(params), 1] = np.stack([col["metallic"], col["roughness"], col["transmission"],
                                     col["ior"]], -1)
    out[:len(params), 2] = np.stack([col["emission_r"], col["emission_g"], col["emission_b"],
                                     col["specular"]], -1)
    out[:len(params), 3, 0] = col["texture"]
    out[:len(params), 3, 1] = 1.0           # texture alpha drives alpha (1 = yes)
    return out.reshape(-1, 4)


def _pack_camera(view: View) -> np.ndarray:
    """The camera buffer laid out as kernels/render.cl documents it."""
    cam = view.camera
    m = cam.to_world
    forward = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
    length = np.linalg.norm(forward)
    if not length > 0:
        raise TracerError("camera to_world maps the view axis to zero")
    out = np.zeros((CAMERA_FLOAT4S, 4), np.float64)
    out[0:3] = m[:3]
    out[3] = (cam.ndc_scale[0], cam.ndc_scale[1], cam.ndc_offset[0], cam.ndc_offset[1])
    out[4, :3] = forward / length
    out[4, 3] = 0.0 if cam.kind == "PERSP" else 1.0
    out[5] = (cam.clip_start, min(cam.clip_end, 3e38), view.width, view.height)
    out[6, :3] = view.shading.world_color
    return out.astype(np.float32)


def light_intensity(light) -> tuple:
    """The unit factor of each light kind (docs/tracer.md), times its colour.

    POINT/SPOT: W -> W/sr over the full sphere (P / 4 pi); SUN: W/m^2 as is; AREA: a one-sided
    Lambertian emitter of power P has peak intensity P / pi (W/sr along its axis).
    """
    factor = {"POINT": 1.0 / (4.0 * math.pi), "SPOT": 1.0 / (4.0 * math.pi),
              "SUN": 1.0, "AREA": 1.0 / math.pi}[light.kind]
    return tuple(c * light.power * factor for c in light.color)


def _pack_lights(lights) -> np.ndarray:
    """The light buffer laid out as kernels/shading.cl documents it."""
    out = np.zeros((max(len(lights), 1) * LIGHT_FLOAT4S, 4), np.float64)
    for i, light in enumerate(lights):
        row = out[i * LIGHT_FLOAT4S:(i + 1) * LIGHT_FLOAT4S]
        direction = np.asarray(light.direction, np.float64)
        norm = np.linalg.norm(direction)
        direction = direction / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
        row[0] = (*light.position, LIGHT_CODES[light.kind])
        row[1, :3] = direction
        row[2, :3] = light_intensity(light)
        row[5, 0] = 1.0
        if light.kind == "SPOT":
            cos_half = math.cos(light.spot_size / 2)
            row[1, 3] = cos_half
            # Cycles: smoothstep((cos - cos_half) / ((1 - cos_half) * blend)); 0 = hard edge.
            span = (1.0 - cos_half) * light.spot_blend
            row[2, 3] = 1.0 / span if span > 0 else 0.0
        if light.kind in ("POINT", "SPOT"):
            row[3, 3] = light.radius
        if light.kind == "SUN":
            row[5, 0] = math.cos(min(light.radius, math.pi) / 2)
        if light.kind == "AREA":
            u, v = _unit(light.axis_u, (1, 0, 0)), _unit(light.axis_v, (0, 1, 0))
            row[3, :3] = u * light.size_u
            row[4, :3] = v * light.size_v
            row[4, 3] = 1.0 if light.shape in ("DISK", "ELLIPSE") else 0.0
    return out.astype(np.float32)


def _unit(vector, fallback) -> np.ndarray:
    vector = np.asarray(vector, np.float64)
    norm = np.linalg.norm(vector)
    return vector / norm if norm > 0 else np.asarray(fallback, np.float64)
