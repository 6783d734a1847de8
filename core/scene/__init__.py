"""The scene: the model shared by the exporter, the master and the slaves (model.py), and the
features a scene needs compiled into the kernels (features.py)."""
