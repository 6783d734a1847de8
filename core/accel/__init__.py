"""The acceleration structure: an SAH kd-tree over the scene's triangles (kdtree.py), rewritten
into one compact node layout for the tracer and the wire (compact.py, docs/kdtree_compression.md)."""
