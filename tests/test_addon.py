"""The whole path, headless: the extension zip is built and validated with Blender's own tool,
installed into an isolated user folder, and renders through slaves that zeroconf found."""
import json
import re
import socket
import struct
import threading

import numpy as np
import pytest

from kdtrace.core.accel.compact import USER_SETTING_LIMITS, compact_params
from kdtrace.core.net.tiles import tile_grid
from kdtrace.core.scene.model import RENDER_SETTING_LIMITS, RenderSettings
from tests.blender import build_extension, run_bpy_script
from tests.processes import SlaveProcess


@pytest.fixture
def two_advertised_slaves():
    """Real slave processes on loopback, advertised with zeroconf there."""
    slaves = [SlaveProcess(name) for name in ("zc-slave-a", "zc-slave-b")]
    yield slaves
    for slave in slaves:
        slave.stop()


def test_render_through_slaves_found_by_zeroconf(tmp_path, two_advertised_slaves):
    zip_path = build_extension(tmp_path / "dist")
    png = tmp_path / "render.png"
    width, height, tile_size = 160, 120, 32
    # 4 x 4 samples: tiles of some 50-100 ms, so that neither slave can render all 20 while the
    # other loads the scene (at one sample a tile took 5 ms, and one slave sometimes took all).
    report = run_bpy_script("render_with_discovered_slaves", tmp_path, zip=str(zip_path),
                            png=str(png), width=width, height=height, tile_size=tile_size,
                            discovery_seconds=5.0, samples_per_axis=4)
    assert png.exists() and png.stat().st_size > 1000
    tiles = report["tiles_per_slave"]
    assert set(tiles) == {"zc-slave-a", "zc-slave-b"}, report["log"][-3000:]
    assert sum(tiles.values()) == len(tile_grid((0, 0, width, height), tile_size))
    assert report["tree_built"] and report["triangles"] > 3000


@pytest.fixture
def slave_of_another_version():
    """A TCP server that answers every HELLO as a slave speaking protocol version 99 would."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(10)

    def answer():
        try:
            connection, _ = server.accept()
        except OSError:
            return
        with connection:
            connection.recv(65536)
            body = json.dumps({"message": "hello from the future"}).encode()
            connection.sendall(struct.pack("!4sHHIQ", b"KDTR", 99, 2, len(body), 0) + body)

    threading.Thread(target=answer, daemon=True).start()
    yield server.getsockname()[1]
    server.close()


@pytest.mark.parametrize("case, message", [
    ("dead host", "cannot reach slave 127.0.0.1:9 (connection refused)"),
    ("empty host", "host 2 in the slave list has no valid address: '  '"),
    ("other version", "speaks version 99"),
    ("missing device", "cannot use OpenCL device '7:7'"),
])
def test_problems_reach_the_user_as_reports(tmp_path, slave_of_another_version, case, message):
    settings = {
        "dead host": dict(hosts=[["127.0.0.1", 9]]),
        "empty host": dict(hosts=[["127.0.0.1", 9], ["  ", 47600]]),
        "other version": dict(hosts=[["127.0.0.1", slave_of_another_version]]),
        "missing device": dict(local_slaves=1, slave_device="7:7"),
    }[case]
    zip_path = build_extension(tmp_path / "dist")
    result = run_bpy_script("render_failing", tmp_path, zip=str(zip_path), **settings)
    reports = [line for line in result["log"].splitlines() if line.startswith("Error: KD Trace:")]
    assert any(message in line for line in reports), result["log"][-3000:]
    assert "Traceback" not in result["log"]
    assert result["last_render"] == {}


def test_slave_pass_shows_who_rendered_each_tile_and_combined_is_clean(tmp_path):
    from kdtrace.core.net.slave_colors import slave_color
    zip_path = build_extension(tmp_path / "dist")
    width, height, tile_size = 160, 120, 32
    result = run_bpy_script("render_passes", tmp_path, zip=str(zip_path), out=str(tmp_path),
                            width=width, height=height, tile_size=tile_size)
    assert {"Image", "Depth", "Normal", "Slave"} <= set(result["compositor_outputs"])
    two, one = result["reports"]["2"], result["reports"]["1"]
    assert len(two["tiles_per_slave"]) == 2 and len(one["tiles_per_slave"]) == 1
    # The same scene again: its one mesh (flat: everything realised) keeps the first's hash.
    assert (two["mesh_hashes_reused"], one["mesh_hashes_reused"]) == (0, 1)
    assert two["triangles_in_spatial_order"] and one["triangles_in_spatial_order"]
    assert two["tree_built"] and not one["tree_built"]

    def load(slaves, name):
        return np.load(tmp_path / f"slaves{slaves}-{name}.npy")

    # Whichever slaves render, the pixels are the same, and no tile frame is left in them.
    for name in ("Combined", "Depth", "Normal"):
        assert np.array_equal(load(2, name), load(1, name)), name
    # The Slave pass: every tile one flat colour, that of the slave that rendered it.
    colors = {name: np.array(slave_color(name) + (1.0,), np.float32) for name in two["tiles_per_slave"]}
    counted = {name: 0 for name in colors}
    for x, y, w, h in tile_grid((0, 0, width, height), tile_size):
        tile = load(2, "Slave")[y:y + h, x:x + w].reshape(-1, 4)
        matches = [name for name, c in colors.items() if np.allclose(tile, c, atol=1e-6)]
        assert len(matches) == 1, f"tile at {x},{y} is not one slave's colour"
        counted[matches[0]] += 1
    assert counted == two["tiles_per_slave"]


def test_enable_disable_reload_leaves_nothing_behind(tmp_path):
    zip_path = build_extension(tmp_path / "dist")
    result = run_bpy_script("enable_disable_reload", tmp_path, zip=str(zip_path))
    assert len(result["rounds"]) == 3
    for round_ in result["rounds"]:
        assert round_["rendered"] and round_["local_slaves"] == 1, result["log"][-3000:]
        assert round_["leftovers"] == []
    # The second reads the kd-tree the first built: the add-on's memory went with the disable,
    # the extension's user folder kept the tree (core/scene/tree_files.py). The third, given
    # a cache folder that is a file, warns and builds.
    assert [r["tree_sources"] for r in result["rounds"]] == [["built"], ["disk"], ["built"]]
    assert "Warning: KD Trace: no kd-tree cache on disk" in result["log"]
    assert len({r["tree_nodes"] for r in result["rounds"]}) == 1
    assert "kd-tree read from disk" in result["log"]
    # Then the preferences' button deletes it (one file) and the trees in memory.
    (files, size), after = result["usage"]
    assert files == 1 and size > 1000 and after == [0, 0]
    assert not list((tmp_path / "blender-user").rglob("kd-trees/*.npz"))
    assert result["cleared"] == ["FINISHED"] and result["in_memory"] == 0


def test_animation_rebuilds_and_uploads_only_when_geometry_changes(tmp_path):
    zip_path = build_extension(tmp_path / "dist")
    result = run_bpy_script("render_animation", tmp_path, zip=str(zip_path), out=str(tmp_path),
                            width=96, height=72)
    frames = {f["frame"]: f for f in result["frames"]}
    assert sorted(frames) == [1, 2, 3, 4, 5]
    # The sphere moves until frame 3, the camera over frames 3-5, the plane's mesh changes at
    # frame 5. An animation exports every object as an instance of its object-space mesh
    # (docs/instances.md, "Scene deltas"): the sphere's mesh and tree stay, frames 2-3 send each
    # slave only the instances, frame 4 (the scene of frame 3) only the query, and frame 5
    # rebuilds and sends only the plane (SCENE_MESHES), not the sphere and the bunny.
    assert [frames[f]["tree_built"] for f in range(1, 6)] == [True, False, False, False, True]
    # Meshes the same bits as the last frame's take its hashes instead of hashing again.
    assert [frames[f]["hashes_reused"] for f in range(1, 6)] == [0, 3, 3, 3, 2]
    assert frames[1]["builds"] == frames[4]["builds"] == 3     # sphere, plane, bunny
    assert result["builds"] == frames[5]["builds"] == 4        # and the lifted plane
    assert frames[1]["uploaded_to"] and all(frames[f]["uploaded_to"] == [] for f in range(2, 6))
    first = frames[1]["scene_bytes"]
    assert len(first) == 2 and all(sent > 400_000 for sent in first.values()), first
    for f in (2, 3):     # 3 instances of 53 bytes, the query, SCENE_INSTANCES' JSON
        assert sorted(frames[f]["scene_bytes"]) == sorted(first)
        assert all(160 < sent < 1150 for sent in frames[f]["scene_bytes"].values()), frames[f]
    # The query alone, with its two holder proofs (64 hex digits each: docs/protocol.md).
    assert all(sent < 450 for sent in frames[4]["scene_bytes"].values()), frames[4]
    # The plane's two triangles and tree, every mesh's hash, the instances.
    assert all(sent < 3000 for sent in frames[5]["scene_bytes"].values()), frames[5]
    images = {f: np.load(tmp_path / f"anim_{f:04d}.npy") for f in range(1, 6)}
    assert all(not np.array_equal(images[f], images[f + 1]) for f in range(1, 5)), "every frame moves"
    # A still realises the objects that are alone (world-space mesh 0, built anew as it moved);
    # the same pixels within float rounding of the transformed rays (8-bit PNGs).
    assert result["stills_built"] == [[True, 0], [True, 0]]     # (built, hashes reused)
    for frame in (2, 5):
        still = np.load(tmp_path / f"still_{frame:04d}.npy")
        diff = np.abs(images[frame] - still)
        assert diff.max() <= 2.5 / 255 and (diff == 0).mean() > 0.99, (diff.max(), (diff == 0).mean())


def test_every_panel_draws_the_settings_it_offers(tmp_path):
    result = run_bpy_script("draw_panels", tmp_path, zip=str(build_extension(tmp_path / "dist")))
    drawn = result["drawn"]
    assert {"tile_partition", "tile_size"} <= set(drawn["RENDER_PT_kdtrace"])
    # Sampling, Light Paths and Film, as Cycles' panels, show every render setting between them.
    assert set(RenderSettings().to_dict()) <= (set(drawn["RENDER_PT_kdtrace_sampling"])
                                               | set(drawn["RENDER_PT_kdtrace_light_paths"])
                                               | set(drawn["RENDER_PT_kdtrace_film"]))
    assert {"pixel_filter", "filter_width"} <= set(drawn["RENDER_PT_kdtrace_film"])
    assert {"samples_per_axis", "adaptive", "adaptive_threshold"} <= set(
        drawn["RENDER_PT_kdtrace_sampling"])
    assert {"max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces",
            "clamp_indirect"} <= set(drawn["RENDER_PT_kdtrace_light_paths"])
    assert {"kdtree_mode", "tau_occu", "tau_freq"} <= set(drawn["RENDER_PT_kdtrace_kdtree"])
    # Sampling > Denoise and View Layer > Passes (issue 40), with core's defaults.
    assert {"denoising_prefilter", "denoising_quality"} <= set(drawn["RENDER_PT_kdtrace_denoise"])
    assert {"use_pass_z", "use_pass_mist", "use_pass_normal", "denoising_store_passes"} <= set(
        drawn["VIEWLAYER_PT_kdtrace_passes_data"])
    assert {"use_pass_diffuse_color", "use_pass_glossy_color", "use_pass_emit"} <= set(
        drawn["VIEWLAYER_PT_kdtrace_passes_light"])
    from kdtrace.core.frame import denoising
    assert [result["settings"][name]["default"] for name in
            ("use_denoising", "denoising_prefilter", "denoising_quality")] == [
        denoising.DENOISE, denoising.PREFILTER, denoising.QUALITY]
    assert {"payload", "interaction", "secret_file"} <= set(drawn["RENDER_PT_kdtrace_network"])
    assert {"use_zeroconf", "local_slaves"} <= set(drawn["RENDER_PT_kdtrace_slaves"])
    # Trust (issue 39): this computer's ID, a refused slave offered for approval by its ID, and
    # the approved slaves in the preferences.
    slaves_panel = drawn["RENDER_PT_kdtrace_slaves"]
    assert any(re.fullmatch(r"label:This computer: ID ([A-Z2-7]{4}-){3}[A-Z2-7]{4}", line)
               for line in slaves_panel), slaves_panel
    assert "label:10.0.0.9:47600  10.0.0.9:47600  ID AAAA-AAAA-AAAA-AAAA  listed" in slaves_panel
    assert "label:approved-box  ID BBBB-BBBB-BBBB-BBBB" in drawn["preferences"]
    assert "secret_file" in drawn["preferences"]
    # The panel offers exactly core's defaults and ranges: every render setting is there (the
    # exporter copies them all by name), and so are the kd-tree settings.
    panel = result["settings"]
    for name, default in RenderSettings().to_dict().items():
        assert name in panel, f"the panel has no render setting {name!r}"
        assert panel[name]["default"] == pytest.approx(default), name
        if name in RENDER_SETTING_LIMITS:
            assert [panel[name]["min"], panel[name]["max"]] == pytest.approx(
                list(RENDER_SETTING_LIMITS[name])), name
    tree = compact_params()
    assert panel["kdtree_mode"]["default"] == tree.mode
    for name, limits in USER_SETTING_LIMITS.items():
        assert panel[name]["default"] == pytest.approx(getattr(tree, name)), name
        assert [panel[name]["min"], panel[name]["max"]] == pytest.approx(list(limits)), name
    # The legend lists the local slave that rendered (named <host>-local-1).
    assert any(line.startswith("label:") and line.endswith("-local-1")
               for line in drawn["RENDER_PT_kdtrace_legend"])
    # The preferences: the kd-tree cache's folder and size, with core's default and range,
    # and what it holds (the render above left its tree there).
    from kdtrace.core.scene.tree_files import DEFAULT_LIMIT_MIB, LIMIT_MIB_RANGE
    assert {"slave_device", "tree_cache_folder", "tree_cache_mib"} <= set(drawn["preferences"])
    assert "label:1 kd-tree(s) on disk" in " ".join(drawn["preferences"])
    size = result["preferences"]["tree_cache_mib"]
    assert size["default"] == DEFAULT_LIMIT_MIB and [size["min"], size["max"]] == list(LIMIT_MIB_RANGE)
