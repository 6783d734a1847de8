"""What the exporter hands the frame pipeline (docs/instances.md), and that export kept in a
file, so that tests and benchmarks run the frame pipeline on a Blender scene without Blender."""
from __future__ import annotations

import json
from typing import NamedTuple

import numpy as np

from ..scene.model import Geometry, View


class InstancedExport(NamedTuple):
    """Object-space meshes (mesh 0 the realised triangles, where there are any) placed by
    instances, and the textures; core.scene.scene.Scene.from_instances takes them with a tree
    per mesh."""
    meshes: list                # Geometry per mesh, without textures
    instance_mesh: np.ndarray   # (I,) mesh of each instance
    to_world: np.ndarray        # (I, 4, 4) float64
    texels: np.ndarray | None
    texture_sizes: np.ndarray | None
    to_world_end: np.ndarray | None = None  # (I, 4, 4) at shutter close where objects move


def save_export(path, exported: InstancedExport, view: View) -> None:
    """One .npz: each mesh's arrays ("mesh<i>.<name>"), the instances, the textures and the
    view (as its JSON)."""
    arrays = {f"mesh{i}.{name}": array for i, mesh in enumerate(exported.meshes)
              for name, array in mesh.arrays().items()}
    for name in ("instance_mesh", "to_world", "texels", "texture_sizes", "to_world_end"):
        if getattr(exported, name) is not None:
            arrays[name] = getattr(exported, name)
    arrays["view"] = np.frombuffer(json.dumps(view.to_dict()).encode(), np.uint8)
    np.savez(path, **arrays)


def load_export(path) -> tuple[InstancedExport, View]:
    """save_export's file, read back (no pickles; the view checked by View.from_dict)."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    meshes = []
    while f"mesh{len(meshes)}.vertices" in arrays:
        prefix = f"mesh{len(meshes)}."
        meshes.append(Geometry(**{name[len(prefix):]: array for name, array in arrays.items()
                                  if name.startswith(prefix)}))
    view = View.from_dict(json.loads(arrays["view"].tobytes()))
    return InstancedExport(meshes, arrays["instance_mesh"], arrays["to_world"],
                           arrays.get("texels"), arrays.get("texture_sizes"),
                           arrays.get("to_world_end")), view
