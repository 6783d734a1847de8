"""Render settings stored in the .blend (Scene.kdtrace) and machine settings (add-on preferences)."""
import pathlib

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       IntProperty, PointerProperty, StringProperty)

from ..core.accel.compact import USER_SETTING_LIMITS as TREE_LIMITS, compact_params
from ..core.frame import viewport
from ..core.frame import denoising as DENOISING
from ..core.frame.options import DISCOVERY_SECONDS_RANGE, LOCAL_SLAVES_RANGE, FrameOptions
from ..core.net.master import DEFAULT_TILE_SIZE, DEFAULT_TILES_IN_FLIGHT, MAX_TILES_IN_FLIGHT
from ..core.net.protocol import DEFAULT_MODEL, DEFAULT_PORT, MAX_TILE_SIZE
from ..core.npz_folder import NpzFolder
from ..core.scene.model import RENDER_SETTING_LIMITS as LIMITS, RenderSettings
from ..core.scene.tree_files import DEFAULT_LIMIT_MIB as TREE_FILES_MIB, LIMIT_MIB_RANGE

# Defaults and limits live with what they configure (core/); the panel only shows them.
RENDER = RenderSettings()
TREE = compact_params()             # the default mode, compressed, and its thresholds
FRAME = FrameOptions()              # how slaves are found, tiles handed out
PREFILTER_TEXT = {"NONE": "No prefiltering: for guides without noise",
                  "FAST": "The guides are denoised together with the image",
                  "ACCURATE": "Each guide is denoised first (slower, sharper)"}
QUALITY_TEXT = {"HIGH": "The best quality", "BALANCED": "Between quality and speed",
                "FAST": "The fastest, lowest quality"}


class KDTraceHost(bpy.types.PropertyGroup):
    """A slave given by address, for networks where multicast discovery does not work."""
    host: StringProperty(name="Host", description="Host name or IP address of the slave")
    port: IntProperty(name="Port", description="TCP port the slave listens on",
                      default=DEFAULT_PORT, min=1, max=65535)
    enabled: BoolProperty(name="Use", description="Use this slave", default=True)


class KDTraceApprovedSlave(bpy.types.PropertyGroup):
    """A slave the user approved by its ID (Slaves panel: Approve or Pair): the master sends
    scenes to it (docs/protocol.md, "Identities and trust")."""
    slave_id: StringProperty(name="ID", description="The slave's ID, as its log shows it")
    name: StringProperty(name="Name", description="The slave's name when it was approved")


class KDTraceRenderSettings(bpy.types.PropertyGroup):
    tile_size: IntProperty(
        name="Tile Size", description="Width and height of the image tiles handed to slaves, in pixels",
        default=DEFAULT_TILE_SIZE, min=8, max=MAX_TILE_SIZE)
    use_zeroconf: BoolProperty(
        name="Find Slaves on the LAN", description="Discover slaves with zeroconf (mDNS) before rendering",
        default=True)
    discovery_seconds: FloatProperty(
        name="Discovery Time", description="How long F12 waits for a first slave to answer when "
        "the LAN browser has only just started (it browses while KD Trace is the render engine)",
        default=FRAME.discovery_seconds, min=DISCOVERY_SECONDS_RANGE[0],
        max=DISCOVERY_SECONDS_RANGE[1], subtype="TIME_ABSOLUTE", unit="TIME_ABSOLUTE")
    tile_partition: EnumProperty(
        name="Tiles", description="How the image is cut into tiles",
        items=[("SIZE", "By Size", "Square tiles of Tile Size pixels", 0),
               ("2", "2 x 2", "The image cut into 2 x 2 tiles", 2),
               ("4", "4 x 4", "The image cut into 4 x 4 tiles (the paper's choice)", 4),
               ("8", "8 x 8", "The image cut into 8 x 8 tiles", 8),
               ("16", "16 x 16", "The image cut into 16 x 16 tiles", 16)],
        default="SIZE")
    tiles_in_flight: IntProperty(
        name="Tiles in Flight", description="Tiles handed to each slave ahead of time, to hide "
        "network latency", default=DEFAULT_TILES_IN_FLIGHT, min=1, max=MAX_TILES_IN_FLIGHT)
    payload: EnumProperty(
        name="Tile Format", description="How finished tiles travel back",
        items=[("F32", "Float 32", "Exact", 0),
               ("F16", "Float 16", "Half the bytes; colour error below 1e-3", 1),
               ("F16_ZLIB", "Float 16, Compressed", "Half the bytes or fewer; for slow networks", 2),
               ("U8", "8-bit Preview", "sRGB 8 bits per channel: a quarter of the bytes, for "
                "interactive previews (colour exact to its 8-bit code)", 3),
               ("U8_ZLIB", "8-bit Preview, Compressed", "The smallest; for shared Wi-Fi", 4)],
        default="F32")
    interaction: EnumProperty(
        name="Interaction", description="How the master talks to each slave (the paper's Fig. 3)",
        items=[("3b", "Overlapped", "Each slave holds several tiles at once, so it renders "
                "while finished tiles travel", 0),
               ("3a", "Simple", "Each slave is given one tile at a time; the next is asked for "
                "once that tile has arrived", 1)],
        default=DEFAULT_MODEL)

    # The viewport's Rendered mode (defaults and ranges: core/frame/viewport.py).
    viewport_samples_per_axis: IntProperty(
        name="Viewport Max Samples", description="N x N samples per pixel the viewport refines "
        "to (progressively: 1, then 4, 16, ... after each change)",
        default=viewport.SAMPLES_PER_AXIS, min=viewport.SAMPLES_PER_AXIS_RANGE[0],
        max=viewport.SAMPLES_PER_AXIS_RANGE[1])
    viewport_denoise: BoolProperty(
        name="Viewport Denoise", description="Denoise the viewport's image (Open Image Denoise, "
        "from a few samples on)", default=viewport.DENOISE.enabled)
    viewport_time_limit: FloatProperty(
        name="Viewport Time Limit", description="Seconds the viewport refines after a change "
        "(0: until its max samples)", default=viewport.TIME_LIMIT,
        min=viewport.TIME_LIMIT_RANGE[0], max=viewport.TIME_LIMIT_RANGE[1],
        subtype="TIME_ABSOLUTE", unit="TIME_ABSOLUTE")
    # Sampling and Light Paths, as Cycles' panels (defaults and ranges: core RenderSettings).
    samples_per_axis: IntProperty(
        name="Max Samples", description="N x N stratified samples per pixel at most "
        "(64: 4096 samples, Cycles' default)",
        default=RENDER.samples_per_axis, min=LIMITS["samples_per_axis"][0],
        max=LIMITS["samples_per_axis"][1])
    adaptive: BoolProperty(
        name="Adaptive Sampling", description="Stop sampling a pixel once its "
        "noise, estimated as Cycles does, is below the threshold", default=RENDER.adaptive)
    adaptive_threshold: FloatProperty(
        name="Noise Threshold", description="Noise level below which a pixel gets no more "
        "samples (Cycles' Noise Threshold)",
        default=RENDER.adaptive_threshold, min=LIMITS["adaptive_threshold"][0],
        max=LIMITS["adaptive_threshold"][1], precision=4)
    adaptive_min_samples: IntProperty(
        name="Min Samples", description="Samples every pixel gets before adaptive sampling "
        "decides (0: automatic, as Cycles: 64 at a Noise Threshold of 0.01)",
        default=RENDER.adaptive_min_samples, min=LIMITS["adaptive_min_samples"][0],
        max=LIMITS["adaptive_min_samples"][1])
    undersample: BoolProperty(
        name="Undersample", description="With adaptive sampling, trace every other pixel "
        "first and fill a pixel between converged neighbours that agree with their average "
        "(fewer samples than Cycles at the same threshold, a little more error)",
        default=RENDER.undersample)
    max_bounces: IntProperty(
        name="Total", description="Total maximum number of bounces",
        default=RENDER.max_bounces, min=LIMITS["max_bounces"][0], max=LIMITS["max_bounces"][1])
    diffuse_bounces: IntProperty(
        name="Diffuse", description="Maximum number of diffuse reflection bounces, bounded by "
        "the total maximum", default=RENDER.diffuse_bounces, min=LIMITS["diffuse_bounces"][0],
        max=LIMITS["diffuse_bounces"][1])
    glossy_bounces: IntProperty(
        name="Glossy", description="Maximum number of glossy reflection bounces, bounded by the "
        "total maximum", default=RENDER.glossy_bounces, min=LIMITS["glossy_bounces"][0],
        max=LIMITS["glossy_bounces"][1])
    transmission_bounces: IntProperty(
        name="Transmission", description="Maximum number of transmission (refraction) "
        "bounces, bounded by the total maximum", default=RENDER.transmission_bounces,
        min=LIMITS["transmission_bounces"][0], max=LIMITS["transmission_bounces"][1])
    transparent_bounces: IntProperty(
        name="Transparent", description="Maximum number of alpha cut-outs a ray passes through",
        default=RENDER.transparent_bounces, min=LIMITS["transparent_bounces"][0],
        max=LIMITS["transparent_bounces"][1])
    clamp_direct: FloatProperty(
        name="Direct Light", description="Largest mean of RGB one sample may add through the "
        "first surface (0: no clamping)", default=RENDER.clamp_direct,
        min=LIMITS["clamp_direct"][0], max=LIMITS["clamp_direct"][1])
    clamp_indirect: FloatProperty(
        name="Indirect Light", description="Largest mean of RGB one sample may add after a "
        "bounce (0: no clamping); removes fireflies, with a little bias",
        default=RENDER.clamp_indirect, min=LIMITS["clamp_indirect"][0],
        max=LIMITS["clamp_indirect"][1])
    filter_glossy: FloatProperty(
        name="Filter Glossy", description="Blur sharp glossy reflections after wide bounces "
        "(fewer fireflies from caustics; 0: off)", default=RENDER.filter_glossy,
        min=LIMITS["filter_glossy"][0], max=LIMITS["filter_glossy"][1])
    light_samples_per_axis: IntProperty(
        name="Light Samples", description="L x L shadow samples per soft light, a textured world "
        "and the emissive meshes, per camera sample",
        default=RENDER.light_samples_per_axis, min=LIMITS["light_samples_per_axis"][0],
        max=LIMITS["light_samples_per_axis"][1])
    # Film > Pixel Filter, as Cycles' (defaults and range: core RenderSettings).
    pixel_filter: EnumProperty(
        name="Pixel Filter", description="How camera samples spread in and around their pixel",
        items=[("BOX", "Box", "Samples uniform over the filter width", 0),
               ("GAUSSIAN", "Gaussian", "A Gaussian of the filter width", 1),
               ("BLACKMAN_HARRIS", "Blackman-Harris", "A Blackman-Harris window of twice the "
                "filter width (Cycles' default)", 2)],
        default=RENDER.pixel_filter)
    filter_width: FloatProperty(
        name="Width", description="Pixel filter width in pixels", default=RENDER.filter_width,
        min=LIMITS["filter_width"][0], max=LIMITS["filter_width"][1], subtype="PIXEL")
    seed: IntProperty(name="Seed", description="Seed of the sampling pattern",
                      default=RENDER.seed, min=LIMITS["seed"][0], max=LIMITS["seed"][1])
    # Sampling > Denoise, as Cycles' (defaults and choices: core/frame/denoising.py).
    use_denoising: BoolProperty(
        name="Denoise", description="Denoise the rendered image with Open Image Denoise once "
        "the last tile is in (the whole image at once: no seams between tiles)",
        default=DENOISING.DENOISE)
    denoising_prefilter: EnumProperty(
        name="Prefilter", description="How the albedo and normal guides are cleaned before "
        "denoising", items=[(name, name.title(), PREFILTER_TEXT[name], index)
                            for index, name in enumerate(DENOISING.PREFILTER_CHOICES)],
        default=DENOISING.PREFILTER)
    denoising_quality: EnumProperty(
        name="Quality", description="Open Image Denoise's quality mode",
        items=[(name, name.title(), QUALITY_TEXT[name], index)
               for index, name in enumerate(DENOISING.QUALITY_CHOICES)],
        default=DENOISING.QUALITY)

    # The kd-tree layout (core/accel/compact.py, docs/kdtree_compression.md); part of the scene
    # the slaves receive, so a change gives another scene hash (and one upload).
    kdtree_mode: EnumProperty(
        name="kd-Tree", description="How the kd-tree is stored (smaller trees send and fit better; "
        "tracing may take a little longer)",
        items=[("standard", "Standard", "SAH kd-tree in the 8-byte node layout (Wald 2004)", 0),
               ("choi", "Choi et al.", "One triangle reference per inner node, no path limit, "
                "2-byte leaves", 1),
               ("compressed", "Compressed", "Up to two triangle references per inner node and 8 per "
                "path, 2-byte leaves (the paper's kd-tree)", 2)],
        default=TREE.mode)
    tau_occu: FloatProperty(
        name="Occupancy Threshold", description="Lift a triangle to an inner node only if rays "
        "entering the node met it at least this often in the leaves below (tau_occu)",
        default=TREE.tau_occu, min=TREE_LIMITS["tau_occu"][0], max=TREE_LIMITS["tau_occu"][1],
        precision=3)
    tau_freq: FloatProperty(
        name="Frequency Threshold", description="Lift a triangle only if it appears in at least "
        "this share of the leaves below the node (tau_freq)", default=TREE.tau_freq,
        min=TREE_LIMITS["tau_freq"][0], max=TREE_LIMITS["tau_freq"][1], precision=3,
        subtype="FACTOR")
    refs_per_path: IntProperty(
        name="References per Path", description="Triangle references on any root-to-leaf path "
        "(mode Compressed)", default=TREE.refs_per_path, min=TREE_LIMITS["refs_per_path"][0],
        max=TREE_LIMITS["refs_per_path"][1])

    hosts: CollectionProperty(type=KDTraceHost, name="Hosts",
                              description="Slaves to use in any case, by address")
    active_host: IntProperty(name="Active Host", default=0)
    local_slaves: IntProperty(
        name="Local Slaves", description="Slaves to start on this machine when no other slave answers",
        default=FRAME.local_slaves, min=LOCAL_SLAVES_RANGE[0], max=LOCAL_SLAVES_RANGE[1])
    use_local_slaves_always: BoolProperty(
        name="Always Use Local Slaves", description="Start local slaves even when slaves on the LAN answer",
        default=False)

    @classmethod
    def register(cls):
        bpy.types.Scene.kdtrace = PointerProperty(type=cls)

    @classmethod
    def unregister(cls):
        del bpy.types.Scene.kdtrace


class KDTraceViewLayerSettings(bpy.types.PropertyGroup):
    """A view layer's KD Trace passes beyond Blender's own switches (View Layer > Passes)."""
    denoising_store_passes: BoolProperty(
        name="Denoising Data", description="Denoising Albedo and Denoising Normal passes (as "
        "Cycles'), for the compositor's Denoise node", default=False)

    @classmethod
    def register(cls):
        bpy.types.ViewLayer.kdtrace = PointerProperty(type=cls)

    @classmethod
    def unregister(cls):
        del bpy.types.ViewLayer.kdtrace


class KDTracePreferences(bpy.types.AddonPreferences):
    bl_idname = __package__.rpartition(".")[0]  # the extension's package, not addon/

    slave_python: StringProperty(
        name="Python for Local Slaves",
        description="Python interpreter with pyopencl, numpy and zeroconf, used to start local "
        "slaves (empty: the Python running Blender)", default="", subtype="FILE_PATH")
    slave_device: StringProperty(
        name="Local Slave Device", description="OpenCL device of local slaves: auto, cpu, gpu or "
        "platform:device indices", default="auto")
    secret_file: StringProperty(
        name="Farm Secret File", description="File holding the farm secret (made with New Farm "
        "Secret or `kdtrace-slave --new-secret FILE`): slaves that prove it need no approval, "
        "and slaves that hold it serve this computer (empty: the KDTRACE_SECRET environment "
        "variable, else none)", default="", subtype="FILE_PATH")
    approved_slaves: CollectionProperty(
        type=KDTraceApprovedSlave, name="Approved Slaves",
        description="Slaves this computer sends scenes to (approved once, by ID)")
    tree_cache_folder: StringProperty(
        name="kd-Tree Cache Folder", description="Folder where built kd-trees are kept, so "
        "that an unchanged mesh is not built again after Blender restarts (empty: the "
        "extension's own user folder)", default="", subtype="DIR_PATH")
    tree_cache_mib: IntProperty(
        name="kd-Tree Cache Size", description="Most MiB of kd-trees kept on disk; the least "
        "recently used go first (0: keep none)", default=TREE_FILES_MIB,
        min=LIMIT_MIB_RANGE[0], max=LIMIT_MIB_RANGE[1])

    def draw(self, context):
        for name in ("slave_python", "slave_device"):
            self.layout.prop(self, name)
        row = self.layout.row()
        row.prop(self, "secret_file")
        row.operator("kdtrace.new_farm_secret", text="", icon="ADD")
        box = self.layout.box()
        box.label(text="Approved slaves (they get this computer's scenes):")
        for index, slave in enumerate(self.approved_slaves):
            row = box.row()
            row.label(text=f"{slave.name}  ID {short_id_text(slave.slave_id)}", icon="CHECKMARK")
            row.operator("kdtrace.slave_forget", text="", icon="X").index = index
        if not self.approved_slaves:
            box.label(text="None yet: approve or pair slaves in the Slaves panel")
        for name in ("tree_cache_folder", "tree_cache_mib"):
            self.layout.prop(self, name)
        files, size = tree_folder_usage(self)
        row = self.layout.row()
        row.label(text=f"{files} kd-tree(s) on disk, {size / 2 ** 20:.1f} MiB")
        row.operator("kdtrace.clear_tree_cache")


def preferences(context):
    return context.preferences.addons[KDTracePreferences.bl_idname].preferences


def short_id_text(slave_id: str) -> str:
    from ..core.net.identity import grouped
    return grouped(slave_id[:16])


def identity_folder() -> str:
    """Where this computer's master identity is kept: the extension's user folder (which
    upgrades keep); private to the user."""
    return bpy.utils.extension_path_user(KDTracePreferences.bl_idname, path="identity")


def approved_ids(prefs) -> tuple:
    return tuple(slave.slave_id for slave in prefs.approved_slaves if slave.slave_id)


def tree_folder(prefs) -> str:
    """Where the master keeps kd-trees on disk (core/scene/tree_files.py): the preferences'
    folder, else the extension's own user folder (Blender's extension_path_user, which
    upgrades keep)."""
    if prefs.tree_cache_folder:
        return bpy.path.abspath(prefs.tree_cache_folder)
    return bpy.utils.extension_path_user(KDTracePreferences.bl_idname, path="kd-trees")


def tree_folder_usage(prefs) -> tuple[int, int]:
    """(kd-trees, bytes) in the tree folder, without making it."""
    folder = pathlib.Path(tree_folder(prefs))
    return NpzFolder(folder, 0).usage() if folder.is_dir() else (0, 0)


classes = (KDTraceHost, KDTraceApprovedSlave, KDTraceRenderSettings, KDTraceViewLayerSettings,
           KDTracePreferences)
