"""The Blender-free parts of KD Trace, in pipeline order:

- scene/: what is rendered (geometry, camera, lights, materials) and what a scene needs
  compiled (features); the exporter fills it, the wire rebuilds it;
- accel/: the acceleration structure: the SAH kd-tree build, its compaction into the paper's
  compressed layouts, and the check of a tree that comes from elsewhere;
- net/: master and slaves: the wire protocol, discovery on the LAN, tiles and the master's
  render jobs;
- opencl.py: devices and kernel programs, for everything that runs kernels/ sources.

Imports between them go scene <- accel <- net; none imports bpy, addon/ or slave/.
"""
