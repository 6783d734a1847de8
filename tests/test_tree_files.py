"""The master's kd-trees on disk (core/scene/tree_files.py): a tree read back is the tree that
was written, bit for bit, and renders as a scene; a damaged, foreign or outdated file is never
used; the folder keeps to its limit."""
import os
import pathlib
import shutil

import numpy as np
import pytest

from kdtrace.core.accel import binned, compact_cl
from kdtrace.core.accel.compact import compact_tree
from kdtrace.core.accel.kdtree import build_kdtree
from kdtrace.core.scene.model import Geometry
from kdtrace.core.scene.scene import Scene
from kdtrace.core.scene.tree_files import (DECIDING_SOURCES, EXTENSION_ROOT, TreeFiles,
                                           builder_version)
from tests.meshes import grid_plane, load_bunny, merge, uv_sphere


@pytest.fixture(scope="module")
def bunny():
    vertices, triangles = load_bunny()
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    standard = build_kdtree(geometry.vertices, geometry.triangles)
    return geometry, {mode: compact_tree(standard, geometry.triangle_count, mode)
                      for mode in ("compressed", "choi", "standard")}


def same_tree(a, b):
    for name in ("nodes", "leaf_index32", "leaf_index16", "bounds"):
        got, want = getattr(a, name), getattr(b, name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    assert a.leaf_shift == b.leaf_shift and a.params == b.params and a.stats == b.stats


def test_a_tree_read_back_is_the_tree_written_and_makes_the_same_scene(bunny, tmp_path):
    geometry, trees = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    for mode, tree in trees.items():
        files.write(files.key(geometry.content_hash(), mode, {}), tree, geometry.triangle_count)
    restarted = TreeFiles(tmp_path, 1 << 30)            # another Blender session
    for mode, tree in trees.items():
        read = restarted.read(restarted.key(geometry.content_hash(), mode, {}),
                              geometry.triangle_count)
        same_tree(read, tree)
        assert read.mode == mode and read.checked == (geometry.triangle_count,
                                                      Scene.from_parts(geometry, tree).depth)
        assert Scene.from_parts(geometry, read).hash == Scene.from_parts(geometry, tree).hash


def test_the_key_names_mesh_mode_settings_and_builder_version(bunny, tmp_path):
    geometry, _ = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    content = geometry.content_hash()
    keys = {files.key(content, "compressed", {"tau_occu": 0.5}),
            files.key(content, "compressed", {"tau_occu": 0.25}),
            files.key(content, "choi", {"tau_occu": 0.5}),
            files.key(content[::-1], "compressed", {"tau_occu": 0.5})}
    assert len(keys) == 4
    assert files.key(content, "compressed", {"a": 1, "b": 2}) == files.key(content, "compressed", {"b": 2, "a": 1})
    # Any change to a source that decides a tree gives another version, so another key.
    copy = tmp_path / "copy"
    for name in DECIDING_SOURCES:
        source = EXTENSION_ROOT / name
        target = copy / name
        target.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if source.is_dir() else shutil.copy)(source, target)
    assert builder_version(copy) == files.version
    # Every file the builder's and the compaction's programs are made of (and no other in
    # kernels/build/): a change in any of them gives another version.
    kernels = set(binned.KERNEL_FILES) | set(compact_cl.KERNEL_FILES)
    assert kernels == {str(p.relative_to(copy / "kernels"))
                       for p in (copy / "kernels/build").glob("*.cl")}
    for name in sorted(kernels):
        kernel = copy / "kernels" / name
        text = kernel.read_text()
        kernel.write_text(text + "\n")
        assert builder_version(copy) != files.version, name
        kernel.write_text(text)
    assert builder_version(copy) == files.version


@pytest.mark.parametrize("damage", ["truncated", "flipped node bit", "moved bound", "other stats",
                                    "other triangle count", "not npz"])
def test_a_damaged_or_foreign_file_is_deleted_not_used(bunny, tmp_path, damage):
    geometry, trees = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    key = files.key(geometry.content_hash(), "compressed", {})
    tree, count = trees["compressed"], geometry.triangle_count
    files.write(key, tree, count)
    path = files.files.path(key)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:1000])
    elif damage in ("flipped node bit", "moved bound", "other stats"):
        with np.load(path) as data:
            arrays = {name: data[name].copy() for name in data.files}
        if damage == "flipped node bit":
            arrays["nodes"][len(arrays["nodes"]) // 2, 1] ^= 1
        elif damage == "moved bound":     # still a valid tree: only the digest tells
            arrays["bounds"][0, 0] = np.nextafter(arrays["bounds"][0, 0], np.float32(-np.inf))
        else:
            arrays["stats"] = np.frombuffer(b'{"mode": "compressed"}', np.uint8)
        with open(path, "wb") as handle:
            np.savez(handle, **arrays)
    elif damage == "not npz":
        path.write_bytes(b"PK not a zip at all" * 100)
    if damage == "other triangle count":
        count -= 1
    assert files.read(key, count) is None
    assert not path.exists()
    assert files.read(key, geometry.triangle_count) is None     # gone: built again


def test_a_valid_digest_over_a_broken_tree_is_still_refused(tmp_path):
    # A file whose digest matches its content but whose tree indexes outside its arrays (made
    # by hand, or by a bug) fails the validation every scene's tree passes.
    sphere = uv_sphere(12, 6, 1.0, (0, 0, 1))
    vertices, triangles = merge(sphere, grid_plane(4.0, 2, 0.0))
    geometry = Geometry(vertices, triangles, np.zeros(len(triangles), np.uint16))
    tree = compact_tree(build_kdtree(geometry.vertices, geometry.triangles),
                        geometry.triangle_count, "standard")
    tree.leaf_index32 = tree.leaf_index32.copy()
    tree.leaf_index32[0] = geometry.triangle_count + 5
    tree.digest = None
    files = TreeFiles(tmp_path, 1 << 30)
    files.write("ab" * 16, tree, geometry.triangle_count)
    assert files.read("ab" * 16, geometry.triangle_count) is None
    assert not files.files.path("ab" * 16).exists()


def test_the_folder_keeps_to_its_limit_least_recently_used_first(bunny, tmp_path):
    geometry, trees = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    names = {}
    for number, (mode, tree) in enumerate(trees.items()):
        names[mode] = files.key(geometry.content_hash(), mode, {})
        files.write(names[mode], tree, geometry.triangle_count)
        os.utime(files.files.path(names[mode]), (1000 + number, 1000 + number))
    sizes = {mode: files.files.path(name).stat().st_size for mode, name in names.items()}
    # "compressed" is the oldest; reading it makes it the newest, so "choi" goes first.
    assert files.read(names["compressed"], geometry.triangle_count) is not None
    small = TreeFiles(tmp_path, sizes["compressed"] + sizes["standard"] + 1000)
    again = small.key(geometry.content_hash(), "compressed", {"other": 1})
    small.write(again, trees["compressed"], geometry.triangle_count)
    kept = {mode for mode, name in names.items() if small.files.path(name).exists()}
    assert small.files.path(again).exists() and kept == {"compressed"}
    # A tree bigger than the whole limit is not written (and nothing else is dropped for it).
    tiny = TreeFiles(tmp_path, 100)
    tiny.write("cd" * 16, trees["compressed"], geometry.triangle_count)
    assert not tiny.files.path("cd" * 16).exists() and small.files.path(again).exists()



def test_a_read_only_folder_serves_its_trees_and_reading_never_raises(bunny, tmp_path,
                                                                      monkeypatch):
    # A folder the user may read but not write (shared, or on a read-only disk): a tree is
    # still read, a damaged file is skipped though it cannot be deleted, and a write raises
    # OSError, which TreeCache turns into a warning. (Root writes anywhere: the refusals are
    # made by hand.)
    import kdtrace.core.npz_folder as npz_folder
    geometry, trees = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    key = files.key(geometry.content_hash(), "compressed", {})
    files.write(key, trees["compressed"], geometry.triangle_count)

    def refused(*args, **kwargs):
        raise PermissionError("read-only file system")
    monkeypatch.setattr(npz_folder.os, "utime", refused)
    monkeypatch.setattr(npz_folder.os, "replace", refused)
    monkeypatch.setattr(pathlib.Path, "unlink", refused)
    same_tree(files.read(key, geometry.triangle_count), trees["compressed"])
    with pytest.raises(OSError):
        files.write(files.key("other", "compressed", {}), trees["compressed"], geometry.triangle_count)
    path = files.files.path(key)
    data = path.read_bytes()
    monkeypatch.undo()
    path.write_bytes(data[:500])
    monkeypatch.setattr(pathlib.Path, "unlink", refused)
    assert files.read(key, geometry.triangle_count) is None and path.exists()


def test_esc_while_a_tree_is_read_stops_the_read_and_keeps_the_file(bunny, tmp_path):
    # The read calls the heartbeat between the digest's and the validation's pieces; its
    # exception (Esc in Blender) is not damage: it goes up and the file stays for next time.
    geometry, trees = bunny
    files = TreeFiles(tmp_path, 1 << 30)
    key = files.key(geometry.content_hash(), "compressed", {})
    files.write(key, trees["compressed"], geometry.triangle_count)

    class Esc(Exception):
        pass
    calls = []

    def esc_at_the_third_call():
        calls.append(1)
        if len(calls) == 3:
            raise Esc
    with pytest.raises(Esc):
        files.read(key, geometry.triangle_count, esc_at_the_third_call)
    assert files.files.path(key).exists()
    counted = []
    same_tree(files.read(key, geometry.triangle_count, lambda: counted.append(1)), trees["compressed"])
    assert len(counted) >= Scene.from_parts(geometry, trees["compressed"]).depth   # once a level at least
