"""Discovery that does not miss, on a LAN of network namespaces (test_netns.py) with Blender on
a host of its own, so that it sees only this LAN: a slave advertised before F12 renders the
first frame of a fresh Blender with KD Trace's default settings, and no local slave is started;
the browser that finds it runs while KD Trace is the render engine; a slave that appears during
a frame joins it. (These slaves and Blenders hold the tests' farm secret.) And the first run
as a new user has it, with no farm secret: a slave started on another machine is paired from
the Slaves panel in three steps and renders."""
import json
import re
import subprocess
import tempfile
import time
import uuid

import pytest

from tests.blender import ROOT, SCRIPTS, build_extension
from tests.test_netns import PORT, HostProcess, Lan, pytestmark, start_fake, start_slave  # noqa: F401

ATTEMPTS = 3   # fresh Blenders, one F12 each
BLENDER_HOST = 0


def start_blender(lan: Lan, script: str, work, env=None, **arguments) -> HostProcess:
    """tests/bpy_scripts/<script>.py in a fresh process on the LAN's host 0."""
    work.mkdir(parents=True, exist_ok=True)
    blender = HostProcess(lan.namespaces[BLENDER_HOST],
                          [str(SCRIPTS / f"{script}.py"), json.dumps(arguments),
                           str(work / "result.json")],
                          env={"BLENDER_USER_RESOURCES": str(work / "blender-user"),
                               "PYTHONPATH": str(ROOT), **(env or {})})
    blender.result_path = work / "result.json"
    return blender


def result(blender: HostProcess, timeout: float = 180) -> dict:
    assert blender.proc.wait(timeout) == 0, "".join(blender.lines)[-2000:] + blender.log[-3000:]
    return json.loads(blender.result_path.read_text())


@pytest.fixture(scope="module")
def lan():
    network = Lan(2)
    try:
        yield network
    finally:
        network.close()


@pytest.fixture(scope="module")
def lan_slave(lan):
    slave = start_slave(lan, 1, f"lan-{uuid.uuid4().hex[:6]}")
    yield slave
    slave.stop()


@pytest.fixture(scope="module")
def zip_path(tmp_path_factory):
    return build_extension(tmp_path_factory.mktemp("dist"))


def test_first_render_in_a_fresh_blender_uses_the_slave_on_the_lan(tmp_path, lan, lan_slave,
                                                                   zip_path):
    for attempt in range(ATTEMPTS):
        report = result(start_blender(lan, "render_once", tmp_path / f"blender-{attempt}",
                                      zip=str(zip_path), width=64, height=48))
        assert list(report["tiles_per_slave"]) == [lan_slave.name], report["tiles_per_slave"]
        assert report["local_slave_pids"] == [] and report["local_reason"] == "", report


def test_browser_runs_while_kdtrace_is_the_engine(tmp_path, lan, lan_slave, zip_path):
    report = result(start_blender(lan, "browse_while_selected", tmp_path, zip=str(zip_path),
                                  slave=lan_slave.name, wait_seconds=10.0))
    assert report["steps"] == {"cycles": False, "kdtrace": True, "discovery off": False}
    assert report["seen"] == [lan_slave.name]


def test_a_new_user_pairs_a_slave_from_the_addon_and_renders(tmp_path, lan, zip_path):
    """The first run (README, "First run"), with nothing configured: the slave, on its own
    machine, prints its ID and a pairing code; in Blender (1) KD Trace is selected and the
    Slaves panel lists the slave with that ID, (2) Pair with the code (a wrong code first:
    refused, nothing approved), (3) F12 renders on the slave, no local slave started. The
    slave then serves that Blender by ID; another master still gets nothing."""
    own = {"KDTRACE_SECRET": None, "KDTRACE_SLAVE_HOME": tempfile.mkdtemp(dir=tmp_path)}
    name = f"new-{uuid.uuid4().hex[:6]}"
    slave = start_slave(lan, 1, name, port=PORT + 1, env=own)
    try:
        deadline = time.monotonic() + 10
        while not (code := re.search(r"pairing code ([A-Z2-7]{4}-[A-Z2-7]{4})", slave.log)):
            assert time.monotonic() < deadline, slave.log
            time.sleep(0.1)
        blender = start_blender(lan, "pair_and_render", tmp_path, zip=str(zip_path), width=64,
                                height=48, slave=name, code=code[1], try_wrong_code=True,
                                env={"KDTRACE_SECRET": None})
        report = result(blender)
        assert report["panel"].endswith(f"ID {slave.id[:4]}-{slave.id[4:8]}-{slave.id[8:12]}-"
                                         f"{slave.id[12:16]}"), report
        assert report["wrong_code"] == ["CANCELLED"] and report["approved_after_wrong"] == []
        assert report["paired"] == ["FINISHED"] and report["approved"] == [slave.id]
        assert list(report["tiles_per_slave"]) == [name], report
        assert report["local_slave_pids"] == [] and report["local_reason"] == "", report
        time.sleep(0.3)
        short = report["master_id"][:4]
        assert f"(ID {short}-" in slave.log and "paired with the pairing code" in slave.log
        assert "wrong pairing code (4 tries left)" in slave.log
    finally:
        slave.stop()


def test_slave_found_during_a_frame_joins_it(tmp_path, zip_path):
    """F12 starts with one listed slave that takes tiles and never answers (it is dropped after
    the silence timeout); a slave that starts advertising once the frame has begun must join
    the frame and finish it."""
    lan = Lan(3)
    fake = late = None
    try:
        fake = start_fake(lan, 1, "hang", 47660)
        blender = start_blender(lan, "render_once", tmp_path, zip=str(zip_path), width=64,
                                height=48, hosts=[list(fake.endpoint)],
                                settings={"local_slaves": 0, "tile_size": 16})
        deadline = time.monotonic() + 120
        while not _connected(lan.namespaces[1], fake.endpoint[1]):   # F12 has found its slaves
            assert time.monotonic() < deadline and blender.alive(), blender.log[-3000:]
            time.sleep(0.1)
        late = start_slave(lan, 2, f"late-{uuid.uuid4().hex[:6]}")
        report = result(blender)
        assert report["joined_during_frame"] == [f"{late.endpoint[0]}:{late.endpoint[1]}"], report
        assert report["tiles_per_slave"] == {late.name: 12}, report["tiles_per_slave"]
    finally:
        for process in (late, fake):
            if process is not None:
                process.stop()
        lan.close()


def _connected(namespace: str, port: int) -> bool:
    listed = subprocess.run(["ip", "netns", "exec", namespace, "ss", "-Htn", "state", "established",
                             f"( sport = :{port} )"], capture_output=True, text=True).stdout
    return bool(listed.strip())
