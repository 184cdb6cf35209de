"""DDS domain allocation of test processes (tests/ros_domain.py): concurrent processes get
different ids, never 0 nor the caller's ROS_DOMAIN_ID, and an id is free again once its holder
has exited, however it exits. No DDS: only the locks are exercised."""
import os
import pathlib
import signal
import subprocess
import sys

import pytest

import ros_domain

TESTS = pathlib.Path(__file__).resolve().parent
# acquires one id with a given scan start and lock dir, prints it, holds it until stdin closes
HOLDER = ("import sys; sys.path.insert(0, sys.argv[1]); import ros_domain\n"
          "print(ros_domain.acquire(start=int(sys.argv[2]), lock_dir=sys.argv[3]), flush=True)\n"
          "sys.stdin.read()\n")


def _holder(start, lock_dir, user_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(user_domain))
    return subprocess.Popen([sys.executable, "-c", HOLDER, str(TESTS), str(start), str(lock_dir)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)


def _read_id(proc):
    line = proc.stdout.readline()
    assert line.strip().isdigit(), (line, proc.stderr.read() if proc.poll() is not None else "")
    return int(line)


def test_concurrent_processes_get_different_ids_and_release_them_at_exit(tmp_path):
    start = 7     # both scan from the same id: without the locks they would pick the same one
    procs = [_holder(start, tmp_path, user_domain=start + 1) for _ in range(2)]
    try:
        ids = [_read_id(p) for p in procs]    # both alive now, each holding its id
        assert ids[0] != ids[1], ids
        for d in ids:
            assert d not in (0, start + 1) and 1 <= d <= ros_domain.MAX_DOMAIN_ID, ids
            assert ros_domain.is_held_elsewhere(d, str(tmp_path)), d
        # the same start with the holders alive: a third caller gets neither of their ids
        third = _holder(start, tmp_path, user_domain=start + 1)
        try:
            assert _read_id(third) not in ids
        finally:
            third.kill()     # kill -9: the kernel still drops the lock
            third.communicate()
        procs[0].communicate(input="", timeout=30)      # a clean exit
        procs[1].send_signal(signal.SIGKILL)
        procs[1].communicate(timeout=30)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    for d in ids:
        assert not ros_domain.is_held_elsewhere(d, str(tmp_path)), f"domain {d} still locked after its holder exited"


def test_domain_scan_skips_held_user_and_zero_ids(tmp_path, monkeypatch):
    monkeypatch.setitem(os.environ, "ROS_DOMAIN_ID", "3")
    lock_dir = str(tmp_path)
    session = ros_domain.held()
    try:
        got = ros_domain.acquire(start=0, ids=[0, 3, 4, 5], lock_dir=lock_dir)
        assert got == 4      # 0 and the environment's 3 skipped, 4 free
        assert ros_domain.acquire(start=0, ids=[0, 3, 4, 5], lock_dir=lock_dir) == 5   # 4 is ours now
        with pytest.raises(RuntimeError, match="no free ROS domain id.*" + lock_dir):
            ros_domain.acquire(start=0, ids=[0, 3, 4, 5], lock_dir=lock_dir)
        assert ros_domain.held(lock_dir) == [4, 5] and ros_domain.held() == session
    finally:
        ros_domain.release(4, lock_dir)
        ros_domain.release(5, lock_dir)
    assert ros_domain.held(lock_dir) == []
    assert ros_domain.acquire(start=0, ids=[0, 3, 4, 5], lock_dir=lock_dir) == 4   # given back: free again
    ros_domain.release(4, lock_dir)


def test_this_session_holds_its_domain():
    """conftest exported the id it holds, so a concurrent session cannot take it."""
    domain = int(os.environ["ROS_DOMAIN_ID"])
    assert domain in ros_domain.held() and domain != 0
    probe = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import ros_domain;"
                            " print(ros_domain.is_held_elsewhere(int(sys.argv[2])))", str(TESTS), str(domain)],
                           capture_output=True, text=True, timeout=30)
    assert probe.stdout.strip() == "True", probe.stdout + probe.stderr
