"""Real files that nobody on this project made, for tests that open them as a user would: glTF
2.0 samples, a textured OBJ and old .blend files, all from Debian's `assimp-testmodels` package
(the Open Asset Import Library's test models). `real_files()` fetches the package once (apt, as
root: .ci/setup runs it) and unpacks the files used into assets/real/.

Where each comes from and its licence (tests/real_files.md has the list for people):
REAL_FILES maps a test name to (the file inside the package's models/ folder, what it is).
"""
from __future__ import annotations

import pathlib
import shutil
import subprocess
import tempfile

ASSETS = pathlib.Path(__file__).resolve().parent.parent / "assets" / "real"
PACKAGE = "assimp-testmodels"       # Debian 12: 5.2.5~ds0-1, 20 MB
MODELS = "usr/share/assimp/models"

REAL_FILES = {
    "box_textured": ("glTF2/BoxTextured-glTF/BoxTextured.gltf",
                     "Khronos glTF sample: a box with a PNG texture (mirrored-repeat wrap)"),
    "texture_transform": ("glTF2/textureTransform/TextureTransformTest.gltf",
                          "Khronos glTF sample: KHR_texture_transform offsets, rotations, scales"),
    "engine": ("glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
               "Khronos glTF sample: an engine of 82 meshes, binary glTF"),
    "clearcoat": ("glTF2/ClearCoat-glTF/ClearCoatTest.gltf",
                  "Khronos glTF sample: KHR_materials_clearcoat, textures and normal maps"),
    "two_uv_maps": ("glTF2/BoxTexcoords-glTF/boxTexcoords.gltf",
                    "glTF box whose texture reads its second UV map"),
    "spider": ("OBJ/spider.obj", "Wavefront OBJ (MilkShape 3D) with an MTL file and JPEG textures"),
    "area_light_269": ("BLEND/AreaLight_269.blend", "a Blender 2.69 file: a cube, an area light"),
    "torus_250": ("BLEND/TorusLightsCams_250_compressed.blend",
                  "a compressed Blender 2.50 file: a torus, lamps and cameras"),
}


def real_files() -> dict[str, pathlib.Path]:
    """Test name -> the file in assets/real/ (fetched and unpacked once)."""
    paths = {name: ASSETS / relative for name, (relative, _) in REAL_FILES.items()}
    if not all(path.exists() for path in paths.values()):
        _unpack()
    missing = [str(path) for path in paths.values() if not path.exists()]
    assert not missing, f"{PACKAGE} did not hold {missing}"
    return paths


def _unpack() -> None:
    """Download the .deb with apt and copy the folders of the files used into assets/real/."""
    with tempfile.TemporaryDirectory() as tmp:
        fetched = subprocess.run(["apt-get", "download", PACKAGE], cwd=tmp, capture_output=True,
                                 text=True)
        if fetched.returncode:
            subprocess.run(["apt-get", "update", "-qq"], check=True, capture_output=True)
            subprocess.run(["apt-get", "download", PACKAGE], cwd=tmp, check=True,
                           capture_output=True)
        [deb] = pathlib.Path(tmp).glob("*.deb")
        subprocess.run(["dpkg-deb", "-x", str(deb), tmp + "/x"], check=True)
        models = pathlib.Path(tmp, "x", MODELS)
        for relative, _ in REAL_FILES.values():
            source = (models / relative).parent
            target = (ASSETS / relative).parent
            target.mkdir(parents=True, exist_ok=True)
            for item in source.iterdir():     # the file and what it references beside it
                if item.is_file() and not (target / item.name).exists():
                    shutil.copy2(item, target / item.name)
