"""The frame pipeline without Blender: from an exported scene to a finished image through the
slaves. `FrameSession` keeps what lives across frames (kd-trees, mesh orders, the last scene,
local slaves, the LAN browser); `render_frame` runs one frame for a `FrameHost` (the F12 engine
in addon/, a test's scripted host, a benchmark); `FrameOptions` holds a frame's settings with
their defaults."""
