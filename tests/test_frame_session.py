"""The frame pipeline without Blender (core/frame/): a frame of a Blender scene's export,
rendered through the core frame session with a scripted host and local slaves, is F12's image
bit for bit; the host sees every tile, the progress and the end of the frame, and a cancel
stops the frame."""
from __future__ import annotations

import numpy as np
import pytest

from kdtrace.core.frame.exported import load_export, save_export
from kdtrace.core.frame.options import FrameOptions
from kdtrace.core.frame.render import FrameHost, render_frame
from kdtrace.core.frame.session import FrameSession
from tests.blender import build_extension, run_bpy_script

SETTINGS = {"use_zeroconf": False, "local_slaves": 2, "tile_size": 16, "samples_per_axis": 2}


class ScriptedHost(FrameHost):
    """Records what the frame shows; cancels once `cancel_after` tiles have arrived."""

    def __init__(self, cancel_after: int | None = None):
        self.tiles, self.progress_values, self.statuses, self.reports = [], [], [], []
        self.image, self.ended, self.cancel_after = None, False, cancel_after

    def cancelled(self) -> bool:
        return self.cancel_after is not None and len(self.tiles) >= self.cancel_after

    def status(self, message):
        self.statuses.append(message)

    def progress(self, fraction):
        self.progress_values.append(fraction)

    def report(self, level, message):
        self.reports.append((level, message))

    def tile(self, tile):
        self.tiles.append((tile.x, tile.y, tile.w, tile.h))

    def end(self, job):
        self.image, self.ended = {name: array.copy() for name, array in job.image.items()}, True


@pytest.fixture(scope="module")
def f12(tmp_path_factory):
    work = tmp_path_factory.mktemp("frame_session")
    run_bpy_script("render_and_export", work, zip=str(build_extension(work / "dist")),
                   out=str(work), width=64, height=48, settings=SETTINGS)
    return work


@pytest.fixture(scope="module")
def session():
    session = FrameSession()
    yield session
    session.close()


def options() -> FrameOptions:
    return FrameOptions(use_zeroconf=False, local_slaves=SETTINGS["local_slaves"],
                        tile_size=SETTINGS["tile_size"])


def test_a_frame_without_blender_is_f12_bit_for_bit(f12, session, tmp_path):
    exported, view = load_export(f12 / "export.npz")
    assert view.settings.samples_per_axis == SETTINGS["samples_per_axis"]
    host = ScriptedHost()
    report = render_frame(session, exported, view, options(), host, warnings=["a warning"])
    image = np.load(f12 / "f12.npy")
    assert host.ended and np.array_equal(host.image["combined"], image)
    assert len(host.tiles) == sum(report["tiles_per_slave"].values()) == 4 * 3
    assert sorted(host.tiles) == sorted((x, y, 16, 16) for x in range(0, 64, 16)
                                        for y in range(0, 48, 16))
    assert host.progress_values == sorted(host.progress_values) and host.progress_values[-1] == 1.0
    assert ("WARNING", "KD Trace: a warning") in host.reports
    assert session.last_warnings == ["a warning"] and session.last_render is report
    # The export survives its file: saved again, it reads back the same arrays.
    save_export(tmp_path / "again.npz", exported, view)
    again, view_again = load_export(tmp_path / "again.npz")
    assert view_again.to_dict() == view.to_dict()
    assert [m.content_hash() for m in again.meshes] == [m.content_hash() for m in exported.meshes]


def test_a_second_frame_reuses_the_tree_and_a_cancel_stops_the_frame(f12, session):
    exported, view = load_export(f12 / "export.npz")
    builds = session.trees.builds
    host = ScriptedHost(cancel_after=1)
    report = render_frame(session, exported, view, options(), host)
    assert session.trees.builds == builds and report["tree_sources"] == ["memory"]
    assert report["cancelled"] and host.ended
    assert 1 <= len(host.tiles) < 12
