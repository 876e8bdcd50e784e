"""Per-instance mapper state on a shared volume (protocol 1.14, cluster.slots): each mapper
process claims its own locked slot directory and id; a slot frees when its process dies."""

import subprocess
import sys
import textwrap

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
