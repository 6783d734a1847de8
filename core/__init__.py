"""The Blender-free parts of KD Trace, in pipeline order:

- accel/: the acceleration structure: the SAH kd-tree build, its compaction into the paper's
  compressed layouts, and the check of a tree that comes from elsewhere;
- scene/: what is rendered (geometry, camera, lights, materials) and what a scene needs
  compiled (features); the exporter fills it, the wire rebuilds it;
- net/: master and slaves: the wire protocol, discovery on the LAN, tiles and the master's
  render jobs;
- frame/: one frame for any host (the F12 engine, tests, benchmarks): kd-trees kept across
  frames, the frame's scene, slaves found, tiles received;
- layout.py (host/kernel records), opencl.py (devices and kernel programs), denoise.py (Open
  Image Denoise), npz_folder.py (size-limited folders of arrays).

Each imports only those before it: accel <- scene <- net <- frame; none imports bpy, addon/
or slave/.
"""
