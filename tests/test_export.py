"""What the add-on exports from Blender's evaluated depsgraph: modifiers applied, collection and
particle instances placed with their world transforms, everything triangulated."""
import numpy as np
import pytest

from tests.blender import build_extension, run_bpy_script


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    work = tmp_path_factory.mktemp("export")
    return run_bpy_script("export_instances", work, zip=str(build_extension(work / "dist")))


def test_modifiers_are_applied(exported):
    arrayed = exported["groups"]["arrayed"]
    assert arrayed["triangles"] == 3 * 12
    assert np.allclose(arrayed["min"], [-0.5, -0.5, -0.5]) and np.allclose(arrayed["max"], [2.5, 0.5, 0.5])


def test_collection_instances_are_placed_in_the_world(exported):
    instances = exported["groups"]["instances"]
    assert instances["triangles"] == 2 * 12
    assert np.allclose(instances["min"], [10, 0, 0]) and np.allclose(instances["max"], [20.5, 0.5, 0.5])


def test_particle_instances_replace_their_hidden_emitter(exported):
    particles = exported["groups"]["particles"]
    assert particles["triangles"] == 5 * 20
    assert np.all(np.array(particles["min"])[:2] >= [-1.1, 8.9]) and np.all(np.array(particles["max"])[:2] <= [1.1, 11.1])
    # The viewport depsgraph the test exports also shows the ico sphere itself (a render's does not).
    assert exported["groups"]["instanced object"]["triangles"] == 20
    assert exported["groups"]["scattered"]["triangles"] == 6 * 12
    # The viewport also shows the scattered cube (z -80) and the nested and the floor.
    assert exported["triangles"] == 3 * 12 + 2 * 12 + 5 * 20 + 20 + 6 * 12 + 12 + 4 * 12 + 2


def _geometry(arrays):
    from kdtrace.core.scene.model import Geometry
    return Geometry(np.array(arrays["vertices"], np.float32).reshape(-1, 3),
                    np.array(arrays["triangles"], np.uint32).reshape(-1, 3),
                    np.array(arrays["material_ids"], np.uint16),
                    None if arrays["normals"] is None else np.array(arrays["normals"]))


def test_shared_meshes_are_exported_once_and_instanced(exported):
    """Meshes of several instances (collection instances, nested ones, particles with the
    viewport's own ico sphere, geometry nodes' Instance on Points) once in object space; the
    others realised in mesh 0: the arrayed cube, the floor and the cube that geometry nodes
    scatter (its instances share an evaluated copy of its mesh, not its own)."""
    meshes = [_geometry(m) for m in exported["meshes"]]
    which = np.array(exported["instance_mesh"])
    assert sorted(m.triangle_count for m in meshes) == [12, 12, 12, 20, 3 * 12 + 2 + 12]
    assert meshes[0].triangle_count == 3 * 12 + 2 + 12 and which[0] == 0
    assert sorted(np.bincount(which)[1:].tolist()) == [2, 4, 6, 6]
    referenced = sum(meshes[m].triangle_count for m in which)
    assert referenced == exported["triangles"]


def test_nested_collection_instances_render_as_realised(exported):
    """The exporter's instanced scene renders as its realised one (the same Blender scene
    exported both ways)."""
    from kdtrace.core.accel.kdtree import build_kdtree
    from kdtrace.core.scene.model import RenderSettings, View
    from kdtrace.core.scene.scene import Scene
    from kdtrace.slave.tracer import Tracer
    realised_geometry = _geometry(exported["realised"])
    realised = Scene.from_parts(realised_geometry, build_kdtree(realised_geometry.vertices,
                                                                realised_geometry.triangles))
    meshes = [_geometry(m) for m in exported["meshes"]]
    instanced = Scene.from_instances([(m, build_kdtree(m.vertices, m.triangles)) for m in meshes],
                                     exported["instance_mesh"], exported["to_world"])
    assert instanced.instances.referenced_triangles == realised_geometry.triangle_count
    view = View.from_dict(exported["view"])
    view.settings = RenderSettings(samples_per_axis=2, adaptive=False, max_bounces=1)
    tracer = Tracer()
    images = []
    for scene in (realised, instanced):
        tracer.load(scene)
        images.append(tracer.render_tile(view, 0, 0, view.width, view.height))
    a, b = images[0]["combined"][..., :3], images[1]["combined"][..., :3]
    nested = (images[0]["depth"] < 1e9).mean()
    assert nested > 0.3                           # the camera sees the nested instances
    assert np.abs(a - b).max(axis=2).mean() < 1e-3 and (np.abs(a - b).max(axis=2) < 1e-2).mean() > 0.99


def test_mesh_arrays_match_blenders_per_element_reads(tmp_path):
    """meshes.mesh_arrays reads Blender's attribute arrays (a mesh of triangles only without
    loop triangles); the reference is Blender's per-element reads of the loop triangles, on
    quads and an n-gon, triangles only, and custom normals, each with materials per face,
    flat and smooth faces and a UV map."""
    result = run_bpy_script("export_arrays", tmp_path, zip=str(build_extension(tmp_path / "dist")))
    assert result["quads"]["all_triangles"] is False
    assert result["triangles"]["all_triangles"] is True and result["custom"]["all_triangles"]
    for name in ("quads", "triangles", "custom"):
        for array in ("vertices", "triangles", "slots", "normals", "uvs"):
            assert result[name][array]["equal"], (name, array, result[name][array])
        assert result[name]["slots"]["distinct"] == 3      # every material slot is used
    assert result["quads"]["triangles"]["shape"] == [6 * 2 + 7, 3]
    assert result["wire"]["triangles"] == result["wire"]["slots"] == 0   # edges only: skipped
