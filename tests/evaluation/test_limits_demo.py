import os

from mjx_pathtrack.evaluation.limits_demo import plot


def test_demo_writes_a_png(tmp_path):
    out = tmp_path / "demo.png"
    plot(str(out), dt=0.05, steps=20)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert os.listdir(tmp_path) == ["demo.png"]  # nothing half-written left behind
