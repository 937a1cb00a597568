"""The runtime file through which client commands find ``magnet up``: written owner-only, read back, ignored when
its writer is gone, malformed or when the command was given its own Zenoh options; removed only by its writer."""

import argparse
import json
import os

from magnet.wire import DEFAULT_PREFIX
from services.common.endpoint import (
    connect_line,
    read_runtime_file,
    remove_runtime_file,
    runtime_file,
    use_local_pipeline,
    write_runtime_file,
)

ENDPOINTS = ["tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002"]


def args(**given):
    base = {"connect": [], "listen": [], "config": None, "no_multicast_scouting": False, "prefix": DEFAULT_PREFIX}
    return argparse.Namespace(**{**base, **given})


def test_the_file_is_per_user_owner_only_and_points_a_bare_command_at_the_pipeline(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    path = write_runtime_file("fleet1", ENDPOINTS, {"calibrator": 7001, "compass": 7002}, None)
    assert path == runtime_file() == tmp_path / "magnet" / f"up-{os.getpid()}.json"
    assert path.stat().st_mode & 0o777 == 0o600 and path.parent.stat().st_mode & 0o777 == 0o700
    bare = args()
    assert use_local_pipeline(bare)
    assert bare.connect == ENDPOINTS and bare.no_multicast_scouting and bare.prefix == "fleet1"
    own = args(connect=["tcp/10.0.0.1:7447"])
    assert not use_local_pipeline(own) and own.connect == ["tcp/10.0.0.1:7447"]
    assert not use_local_pipeline(args(config="site.json5")) and not use_local_pipeline(args(listen=["tcp/x:1"]))
    mine = args(prefix="other")
    assert use_local_pipeline(mine) and mine.prefix == "other"  # a prefix given stays
    assert connect_line(ENDPOINTS) == (
        "--no-multicast-scouting --connect tcp/127.0.0.1:7001 --connect tcp/127.0.0.1:7002"
    )
    remove_runtime_file()
    assert not path.exists() and not use_local_pipeline(args())


def test_a_file_left_by_a_dead_pipeline_or_malformed_is_ignored_and_not_removed_by_others(tmp_path, monkeypatch):
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    path = runtime_file()
    assert path == tmp_path / ".cache" / "magnet" / f"up-{os.getpid()}.json"
    path.parent.mkdir(parents=True)
    no_such_pid = 2**22 + 1  # above Linux's largest pid_max: no process has it
    record = {"v": 1, "pid": no_such_pid, "prefix": "magnet", "connect": ENDPOINTS, "ports": {}}
    path.write_text(json.dumps(record))
    assert read_runtime_file() is None and read_runtime_file(path, check_alive=False) is not None
    remove_runtime_file()
    assert path.exists(), "only the process that wrote it removes it"
    for bad in ("{", json.dumps({**record, "pid": os.getpid(), "connect": []}), json.dumps([1])):
        path.write_text(bad)
        assert read_runtime_file() is None


def test_two_pipelines_keep_their_own_files_and_a_command_reaches_the_newest_running_one(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    parent = os.getppid()  # a process that runs: stands for a first ``magnet up``
    first = runtime_file(parent)
    first.parent.mkdir(mode=0o700, parents=True)
    first.write_text(json.dumps({"v": 1, "pid": parent, "prefix": "first", "connect": ["tcp/127.0.0.1:7101"]}))
    os.utime(first, ns=(1, 1))  # older
    second = write_runtime_file("second", ENDPOINTS, {}, None)  # this process: a second ``magnet up``
    assert first != second and first.exists()
    bare = args()
    assert use_local_pipeline(bare) and bare.prefix == "second" and bare.connect == ENDPOINTS
    remove_runtime_file()  # the second exits: the first pipeline's file stays, and the tools find it
    assert not second.exists() and first.exists()
    again = args()
    assert use_local_pipeline(again) and again.prefix == "first" and again.connect == ["tcp/127.0.0.1:7101"]
