"""Scene deltas (docs/instances.md, "Scene deltas"): a frame whose instances alone changed sends
the slaves only the instance arrays (SCENE_INSTANCES), through real TCP to real slaves, and the
slaves render it with the pixels of the whole scene loaded afresh."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.net.master import Master
from kdtrace.core.net.protocol import MsgType
from kdtrace.core.scene.model import (Camera, Geometry, Light, RenderSettings, SceneError, Shading,
                                      View)
from kdtrace.core.scene.scene import Scene
from tests.meshes import grid_plane, look_at, uv_sphere
from tests.processes import SlaveProcess
from tests.test_network import render_all


def _mesh(vertices, triangles, material):
    geometry = Geometry(vertices, triangles, np.full(len(triangles), material, np.uint16))
    return geometry, build_kdtree(geometry.vertices, geometry.triangles)


def _placement(moved=()):
    """Ten objects: the ground and nine spheres of two meshes; the spheres in `moved` shifted."""
    matrices = [np.eye(4)]
    for i in range(9):
        m = np.diag([0.6 + 0.05 * i] * 3 + [1.0])
        m[:3, 3] = (2.0 * (i % 3) - 2.0, 2.0 * (i // 3) - 2.0, 0.8)
        if i in moved:
            m[:3, 3] += (0.4, -0.3, 0.5)
        matrices.append(m)
    return [0] + [1 + i % 2 for i in range(9)], np.array(matrices)


@pytest.fixture(scope="module")
def scenes():
    """The ten objects; two of them moved; then one of the sphere meshes changed too."""
    meshes = [_mesh(*grid_plane(12.0, 2), material=0), _mesh(*uv_sphere(48, 24), material=1),
              _mesh(*uv_sphere(12, 6), material=1)]
    which, matrices = _placement()
    first = Scene.from_instances(meshes, which, matrices)
    moved = _placement(moved=(2, 7))[1]
    changed = Scene.from_instances(meshes[:2] + [_mesh(*uv_sphere(10, 5), material=1)], which,
                                   moved)
    return first, first.moved(moved), changed


def _view():
    shading = Shading(np.array([[0.8, 0.8, 0.8, 1.0], [0.9, 0.3, 0.2, 1.0]], np.float32),
                      [Light("SUN", (1.0, 1.0, 1.0), 3.0, direction=(-0.3, -0.2, -1.0))],
                      (0.1, 0.1, 0.12))
    camera = Camera("PERSP", look_at((8.0, -7.0, 7.0), (0.0, 0.0, 0.5)), ndc_scale=(0.6, 0.45))
    return View(camera, 32, 24, shading, settings=RenderSettings(
        samples_per_axis=1, adaptive=False, max_bounces=0, light_samples_per_axis=1))


def test_moving_two_of_ten_objects_sends_only_the_instances(scenes):
    first, second, changed = scenes
    assert second.meshes_hash == first.meshes_hash and second.hash != first.hash
    slaves = [SlaveProcess(f"kdt-delta-{n}-{os.getpid()}") for n in "ab"]
    try:
        with Master([s.endpoint for s in slaves]) as master:
            master.connect()
            master.load_scene(first)
            mesh_bytes = sum(a.nbytes for a in first.wire_arrays().values())
            assert len(master.uploaded_to) == 2
            assert all(b > mesh_bytes for b in master.scene_bytes.values())
            view = _view()
            render_all(master.render(view, tile_size=16))     # the slaves' tracers hold `first`

            master.load_scene(second)
            # Only the instance arrays (10 x 53 bytes) and two small control messages crossed
            # the sockets: no geometry, no tree.
            instance_bytes = sum(a.nbytes for a in second.instance_arrays().values())
            assert instance_bytes == 10 * 53
            assert master.uploaded_to == []
            assert sorted(master.scene_bytes) == sorted(c.label for c in master.slaves)
            for sent in master.scene_bytes.values():
                assert instance_bytes < sent < instance_bytes + 1500, sent
            images, _ = render_all(master.render(view, tile_size=16))

            # One mesh changed: only it travels (SCENE_MESHES), the others are taken by hash.
            master.load_scene(changed)
            mesh_bytes = sum(a.nbytes for a in changed.mesh_wire_arrays([0, 0, 1]).values())
            assert master.uploaded_to == []
            for sent in master.scene_bytes.values():
                assert mesh_bytes < sent < mesh_bytes + 2000, (sent, mesh_bytes)
            assert mesh_bytes < sum(a.nbytes for a in changed.wire_arrays().values()) / 5
            changed_images, _ = render_all(master.render(view, tile_size=16))

            # A slave that lost the meshes since it answered says so; the master then uploads.
            connection = master.slaves[0]
            connection.send(MsgType.SCENE_INSTANCES, {"scene_hash": second.hash,
                                                      "meshes_hash": "0" * 32},
                            second.instance_arrays())
            assert master._scene_ready(connection, second.hash)[:2] == (False, False)
            for slave in slaves:    # their output arrives on reader threads: wait for it
                deadline = time.monotonic() + 10
                while not ("placed scene" in slave.log and "sent 1 of the 3 meshes" in slave.log):
                    assert time.monotonic() < deadline, slave.log
                    time.sleep(0.05)
    finally:
        for slave in slaves:
            slave.stop()
    for slave in slaves:
        assert "Traceback" not in slave.log, slave.log
    # The slaves placed `second` on the meshes they held and kept their buffers: the same bits
    # as `second` loaded whole here.
    from kdtrace.slave.tracer import Tracer
    tracer = Tracer()
    tracer.load(second)
    expected = tracer.render_tile(view, 0, 0, view.width, view.height)
    for name in ("combined", "depth", "normal"):
        np.testing.assert_array_equal(images[name], expected[name], err_msg=name)
    tracer.load(changed)
    changed_expected = tracer.render_tile(view, 0, 0, view.width, view.height)
    for name in ("combined", "depth", "normal"):
        np.testing.assert_array_equal(changed_images[name], changed_expected[name], err_msg=name)
    assert not np.array_equal(changed_expected["combined"], expected["combined"])
    tracer.load(second)
    tracer.load(first)      # the same meshes: only the top level goes to the device, twice
    tracer.load(second)
    assert tracer.mesh_loads_skipped == 2
    again = tracer.render_tile(view, 0, 0, view.width, view.height)
    np.testing.assert_array_equal(again["combined"], expected["combined"])


def test_instances_from_the_wire_are_checked(scenes):
    first, second, _ = scenes
    assert first.placed_from_wire(second.instance_arrays()).hash == second.hash
    arrays = second.instance_arrays()
    bad = [({**arrays, "instance_mesh": np.full(10, 3, np.uint32)}, "uses mesh 3"),
           ({**arrays, "instance_to_world": arrays["instance_to_world"].astype("<f2")}, "must be"),
           ({**arrays, "instance_visibility": arrays["instance_visibility"][:4]}, "one each"),
           ({k: v for k, v in arrays.items() if k != "instance_mesh"}, "instance arrays must"),
           ({**arrays, "nodes": first.tree.nodes}, "instance arrays must")]
    for changed, message in bad:
        with pytest.raises(SceneError, match=message):
            first.placed_from_wire(changed)
    # Other instances of the same meshes: another count, other meshes.
    # Moving instances (motion blur) carry their shutter-close transforms.
    blurred = first.placed(first.instances.mesh, first.instances.to_world,
                           to_world_end=second.instances.to_world)
    assert "instance_to_world_end" in blurred.instance_arrays()
    assert first.placed_from_wire(blurred.instance_arrays()).hash == blurred.hash
    held = {bytes(h): part for h, part in zip(first.mesh_hashes, first.mesh_parts)}
    assert Scene.from_mesh_wire(blurred.mesh_wire_arrays([0, 0, 0]), held.get).hash == blurred.hash
    hashes = first.mesh_hashes
    placed = first.placed([1, 2, 2], _placement()[1][1:4])
    assert placed.meshes_hash == first.meshes_hash and placed.instances.count == 3
    assert placed.mesh_hashes is hashes      # the same meshes: hashed once


def test_meshes_from_the_wire_are_checked(scenes):
    first, _, changed = scenes
    held = {bytes(h): part for h, part in zip(first.mesh_hashes, first.mesh_parts)}
    assert (changed.mesh_hashes[:2] == first.mesh_hashes[:2]).all()
    assert (changed.mesh_hashes[2] != first.mesh_hashes[2]).any()
    arrays = changed.mesh_wire_arrays([0, 0, 1])
    assert Scene.from_mesh_wire(arrays, held.get).hash == changed.hash
    assert Scene.from_mesh_wire(changed.mesh_wire_arrays([1, 1, 1]), {}.get).hash == changed.hash
    counts = arrays["mesh_counts"].copy()
    counts[0, 1] += 1
    bad = [({**arrays, "mesh_new": np.array([0, 1, 1], np.uint8)}, "do not add up"),
           ({**arrays, "mesh_new": np.array([0, 0, 2], np.uint8)}, "0/1"),
           ({**arrays, "mesh_counts": counts}, "do not add up"),
           ({**arrays, "triangles": arrays["triangles"] + 5}, "triangle|vert"),
           ({k: v for k, v in arrays.items() if k != "nodes"}, "must carry")]
    for changed_arrays, message in bad:
        with pytest.raises(SceneError, match=message):
            Scene.from_mesh_wire(changed_arrays, held.get)
    with pytest.raises(SceneError, match="neither carried nor held"):
        Scene.from_mesh_wire(arrays, {}.get)


def test_a_restarted_slave_finds_the_meshes_on_disk(scenes, tmp_path):
    from kdtrace.slave.scene_cache import SceneCache
    first, second, changed = scenes
    SceneCache(2, tmp_path).put(first)
    fresh = SceneCache(2, tmp_path)                  # a restarted slave: nothing in memory
    assert fresh.with_meshes(second.meshes_hash).hash == first.hash
    assert fresh.with_meshes(changed.meshes_hash) is None
    # A pointer to a scene that is gone (or names another one) is dropped.
    (tmp_path / f"{first.hash}.npz").unlink()
    assert SceneCache(2, tmp_path).with_meshes(first.meshes_hash) is None
    assert not (tmp_path / f"meshes-{first.meshes_hash}.txt").exists()
