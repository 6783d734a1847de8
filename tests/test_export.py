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
    assert exported["triangles"] == 3 * 12 + 2 * 12 + 5 * 20 + 20
