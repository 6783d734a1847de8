"""The tracer's kernel sources (slave/tracer.py KERNEL_FILES, docs/tracer.md "Kernels"): one
list names every file of kernels/trace/ and kernels/shade/ in the order they are concatenated,
no file includes another, so the build key (a hash of the concatenated text and the options)
covers every source of a program, and no file holds more than one job's worth of code."""
from __future__ import annotations

import re
import shutil

import core.opencl
from core.opencl import KERNEL_DIR, kernel_source
from slave.tracer import KERNEL_FILES, kernel_files_through

# Generated tables, not code (.ci/ggx_albedo.py writes it).
GENERATED = {"shade/ggx_albedo.cl"}
MAX_LINES = 900


def test_every_tracer_source_is_listed_once_and_includes_nothing():
    assert len(set(KERNEL_FILES)) == len(KERNEL_FILES)
    on_disk = {path.relative_to(KERNEL_DIR).as_posix()
               for folder in ("trace", "shade") for path in (KERNEL_DIR / folder).glob("*.cl")}
    assert on_disk == set(KERNEL_FILES)
    for name in KERNEL_FILES:
        text = (KERNEL_DIR / name).read_text()
        assert not re.search(r"^\s*#\s*include", text, re.M), f"kernels/{name} includes a file"


def test_the_program_text_changes_with_every_source(tmp_path, monkeypatch):
    """Programs are cached by a hash of kernel_source's text: a change to any listed file
    must change that text (a file the compiler read by itself would not)."""
    copy = tmp_path / "kernels"
    shutil.copytree(KERNEL_DIR, copy)
    monkeypatch.setattr(core.opencl, "KERNEL_DIR", copy)
    before = kernel_source(KERNEL_FILES)
    for name in KERNEL_FILES:
        path = copy / name
        text = path.read_text()
        path.write_text(text + "\n// changed\n")
        assert kernel_source(KERNEL_FILES) != before, name
        path.write_text(text)
    assert kernel_source(KERNEL_FILES) == before


def test_a_prefix_of_the_sources_ends_at_the_named_file():
    assert kernel_files_through(KERNEL_FILES[0]) == KERNEL_FILES[:1]
    assert kernel_files_through(KERNEL_FILES[-1]) == KERNEL_FILES


def test_each_kernel_file_stays_under_the_size_of_one_job():
    for name in KERNEL_FILES:
        if name not in GENERATED:
            lines = len((KERNEL_DIR / name).read_text().splitlines())
            assert lines <= MAX_LINES, f"kernels/{name} has {lines} lines: split it by job"
