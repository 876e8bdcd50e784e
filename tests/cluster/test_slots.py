"""Per-instance mapper state on a shared volume (protocol 1.14, cluster.slots): each mapper
process claims its own locked slot directory and id; a slot frees when its process dies."""

import os
import subprocess
import sys
import textwrap

import pytest

from aisdf_mapper.slots import claim


def test_slots_are_exclusive_between_processes_and_free_when_one_dies(tmp_path):
    a = claim(tmp_path)
    assert (a.n, a.mapper_id, a.dir) == (1, "mapper-1", tmp_path / "slot-1")
    code = textwrap.dedent(f"""
        import sys, time
        from aisdf_mapper.slots import claim
        s = claim({str(tmp_path)!r})
        print(s.n, s.mapper_id, flush=True)
        sys.stdin.readline()
    """)
    other = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().split() == ["2", "mapper-2"]  # slot 1 is held by this process
    finally:
        other.kill()
        other.wait(10)
    b = claim(tmp_path)  # the killed process's slot is free again
    assert b.n == 2
    a.release()
    assert claim(tmp_path).n == 1


def test_a_second_mapper_given_the_same_checkpoint_directory_stops_with_a_clear_error(tmp_path):
    """Without slots a mapper locks its checkpoint directory (``docker compose up --scale
    mapper=3`` without shards must not give three writers one journal); the lock goes with the
    process."""
    from aisdf_mapper.slots import lock_dir

    held = lock_dir(tmp_path)
    port = 47000 + os.getpid() % 1000
    r = subprocess.run([sys.executable, "-m", "aisdf_mapper.main", "--preset", "cpu", "--checkpoint-dir", str(tmp_path),
                        "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert f"another mapper holds the checkpoint directory {tmp_path}" in r.stderr
    assert "AISDF_MAPPER_SHARDS=true" in r.stderr
    assert not any(tmp_path.glob("mapper-*"))  # it wrote nothing
    held.release()
    again = lock_dir(tmp_path)  # free once its holder lets go (or dies)
    with pytest.raises(RuntimeError, match="another mapper holds"):
        lock_dir(tmp_path)
    again.release()
