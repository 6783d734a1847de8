"""The repository root under the name `kdtrace`, the one the installed slave has.

The wheel (pyproject.toml) installs core/, slave/ and kernels/ as kdtrace.core, kdtrace.slave
and kdtrace.kernels, so that they cannot collide with a user's own top-level packages. This
package gives a checkout and the installed extension the same names: its __path__ is the
folder above, so with that folder on sys.path (tests and benchmarks put the root there; local
slaves run with the extension's root as their working folder) `python -m kdtrace.slave` and
`import kdtrace.core...` work as in the wheel, and the slave's relative imports (`from
..core.net import protocol`) reach kdtrace.core. The root's own __init__.py (the extension's
entry point, which registers the add-on) is not run by importing kdtrace: only this file is.
The wheel leaves this file out: there, kdtrace is a namespace package.
"""
import os

__path__ = [os.path.dirname(os.path.dirname(os.path.abspath(__file__)))]
